"""What verifying readers cost: page CRC checks on every read, sha256 on open, size on open.

Builds a small records folder of 512x512 JPEG views (random texture, so images do not compress
away; ~30 MB) unless ``--root`` names one, then measures side by side in one run, in CPU time:
reading random 5-view samples (the row groups holding them) with and without Parquet page
checksum verification, and the cost of ``data.verify=sha256`` per MB.

    python scripts/bench_verify.py [--root data/scene_shapes_small --split train]
"""
from __future__ import annotations

import argparse
import random
import tempfile
import time
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq

from pipelines.common import BuildOptions, ShardPlan, run_build
from usl.data import CategoryIndex, decode_frame
from usl.records import RecordsDataset, SceneRecord, encode_image, frame_row, make_instance
from usl.records.shards import sha256_file

SPEC = {"name": "bench", "categories": [{"id": 1, "name": "thing"}], "layout": {"z0": 1, "z1": 2, "rho0": 0.1, "rho1": 1}}
SIZE, VIEWS = 512, 24


def bench_scene(unit: tuple[str, int]) -> SceneRecord:
    scene_id, seed = unit
    rng = np.random.default_rng(seed)
    mask = np.zeros((SIZE, SIZE), bool)
    mask[100:300, 150:400] = True
    rows = []
    for view in range(VIEWS):
        image = rng.integers(0, 255, (SIZE // 8, SIZE // 8, 3), dtype=np.uint8).repeat(8, 0).repeat(8, 1)
        rows.append(frame_row(scene_id, view, encode_image(image, "jpeg"), np.eye(3), np.eye(4),
                              [make_instance(1, 1, mask)], SIZE, SIZE))
    return SceneRecord(scene_id, rows)


def cpu_seconds(fn, repeats: int = 3) -> float:
    best = float("inf")
    for _ in range(repeats):
        start = time.process_time()
        fn()
        best = min(best, time.process_time() - start)
    return best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--root", type=Path)
    parser.add_argument("--split", default="train")
    parser.add_argument("--samples", type=int, default=200)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="usl-bench-verify-") as tmp:
        root = args.root
        if root is None:
            root = Path(tmp) / "ds"
            units = [(f"scene{i:03d}", i) for i in range(16)]
            run_build(BuildOptions(root, progress=False), SPEC, {}, [ShardPlan("train", k, units[8 * k:8 * k + 8])
                                                                    for k in range(2)], bench_scene, {})
        measure(root, args.split, args.samples)


def measure(root: Path, split: str, num_samples: int) -> None:
    records = RecordsDataset(root, split)
    rng = random.Random(0)
    picks = []
    for _ in range(num_samples):
        scene = rng.choice(records.scene_ids)
        loc = records.locations[scene]
        views = sorted(rng.sample(range(loc.num_rows), min(5, loc.num_rows)))
        picks.append((records.root / records.shards[loc.shard]["frames"]["file"], [loc.first_row + v for v in views]))
    files = {path: None for path, _ in picks}

    categories = CategoryIndex(records.categories)

    def read(verify: bool, decode: bool = False) -> None:
        opened = {p: pq.ParquetFile(p, page_checksum_verification=verify) for p in files}
        for path, rows in picks:
            meta = opened[path].metadata
            starts = np.cumsum([0] + [meta.row_group(i).num_rows for i in range(meta.num_row_groups)])
            groups = sorted({int(np.searchsorted(starts, r, side="right") - 1) for r in rows})
            table = opened[path].read_row_groups(groups)
            if decode:
                base = int(starts[groups[0]])
                for row in table.take([r - base for r in rows]).to_pylist():
                    decode_frame(row, categories)

    plain, checked = cpu_seconds(lambda: read(False)), cpu_seconds(lambda: read(True))
    plain_decoded, checked_decoded = cpu_seconds(lambda: read(False, True), 1), cpu_seconds(lambda: read(True, True), 1)
    megabytes = sum(p.stat().st_size for p in files) / 2**20
    sha = cpu_seconds(lambda: [sha256_file(p) for p in files], repeats=1)
    size = cpu_seconds(lambda: [p.stat().st_size for p in files for _ in range(1000)]) / 1000
    print(f"dataset {root} [{split}]: {len(records)} scenes, {len(files)} shard(s), {megabytes:.0f} MB")
    print(f"read {num_samples} random 5-view samples: {plain:.3f} s CPU without page checksums, {checked:.3f} s with "
          f"-> x{checked / plain:.3f}")
    print(f"  the same samples decoded to tensors (as training reads them): {plain_decoded:.3f} s vs {checked_decoded:.3f} s "
          f"-> x{checked_decoded / plain_decoded:.3f}")
    print(f"sha256 on open (data.verify=sha256): {sha:.3f} s CPU for {megabytes:.0f} MB ({megabytes / sha:.0f} MB/s), "
          f"once per run; size check: {size * 1e6:.1f} us CPU per open")


if __name__ == "__main__":
    main()
