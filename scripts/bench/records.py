"""Reader throughput: random 5-view samples per second per core, as a training DataLoader reads them.

A sample = one scene's 5 views read by random access (row groups of that scene only), with
images, masks and boxes decoded to tensors (usl.data.decode_frame). Measured in one process (one
core) and with 2 DataLoader workers side by side, so the per-core figure and scaling print together.
Then what verifying readers cost, in CPU time side by side: the same samples read with and without
Parquet page checksum verification (always on in usl's readers), and ``data.verify=sha256``.

    python scripts/bench/records.py --root data/scene_shapes_small --split train
"""

from __future__ import annotations

import argparse
import os
import random
import time
from functools import partial

import pyarrow.parquet as pq
import torch
from torch.utils.data import DataLoader, Dataset

from usl.data import CategoryIndex, decode_frame
from usl.records import RecordsDataset
from usl.records.shards import sha256_file

VIEWS_PER_SAMPLE = 5


class FiveViewSamples(Dataset):
    def __init__(self, root: str, split: str, num_samples: int, seed: int = 0):
        self.records = RecordsDataset(root, split)
        self.categories = CategoryIndex(self.records.categories)
        rng = random.Random(seed)
        self.picks = []
        for _ in range(num_samples):
            scene = rng.choice(self.records.scene_ids)
            n = self.records.num_views(scene)
            self.picks.append((scene, sorted(rng.sample(range(n), min(VIEWS_PER_SAMPLE, n)))))

    def __len__(self) -> int:
        return len(self.picks)

    def __getitem__(self, i: int) -> int:
        scene, views = self.picks[i]
        frames = [decode_frame(row, self.categories) for row in self.records.read_scene(scene, views)]
        return sum(int(f.masks.shape[0]) for f in frames)


def measure(dataset: Dataset, workers: int) -> tuple[float, float]:
    """(samples per wall second, samples per CPU second of this process; meaningful for workers=0)."""
    loader = DataLoader(dataset, batch_size=None, num_workers=workers, shuffle=False)
    start, cpu = time.perf_counter(), time.process_time()
    for _ in loader:
        pass
    return len(dataset) / (time.perf_counter() - start), len(dataset) / (time.process_time() - cpu)


def cpu_seconds(fn) -> float:
    start = time.process_time()
    fn()
    return time.process_time() - start


def verification_cost(dataset: FiveViewSamples) -> str:
    """CPU seconds to read (and decode) the samples with vs without page checksums; sha256 MB/s."""
    records = dataset.records
    files = sorted({records.source(scene) for scene, _ in dataset.picks})

    def read(verify: bool, decode: bool) -> None:
        opened = {f: pq.ParquetFile(f, page_checksum_verification=verify) for f in files}
        for scene, views in dataset.picks:
            loc = records.locations[scene]
            meta = opened[records.source(scene)].metadata
            first = loc.first_row
            groups, start = [], 0
            for g in range(meta.num_row_groups):
                if start + meta.row_group(g).num_rows > first + min(views) and start <= first + max(views):
                    groups.append(g)
                start += meta.row_group(g).num_rows
            table = opened[records.source(scene)].read_row_groups(groups)
            if decode:
                base = sum(meta.row_group(g).num_rows for g in range(groups[0]))
                for row in table.take([first + v - base for v in views]).to_pylist():
                    decode_frame(row, dataset.categories)

    lines = []
    for decode, what in ((False, "Parquet read only"), (True, "read + decode to tensors")):
        plain, checked = cpu_seconds(partial(read, False, decode)), cpu_seconds(partial(read, True, decode))
        lines.append(f"page checksums, {what}: {plain:.3f} s -> {checked:.3f} s CPU (x{checked / plain:.3f})")
    megabytes = sum(os.path.getsize(f) for f in files) / 2**20
    seconds = cpu_seconds(lambda: [sha256_file(f) for f in files])
    lines.append(
        f"data.verify=sha256: {megabytes:.0f} MB of shards in {seconds:.3f} s CPU ({megabytes / seconds:.0f} MB/s, once per run)"
    )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--root", required=True)
    parser.add_argument("--split", default="train")
    parser.add_argument("--samples", type=int, default=200)
    args = parser.parse_args()
    torch.set_num_threads(1)
    dataset = FiveViewSamples(args.root, args.split, args.samples)
    row = dataset.records.read_scene(dataset.picks[0][0], [0])[0]
    print(f"dataset {args.root} [{args.split}]: {len(dataset.records)} scenes, images {row['width']}x{row['height']}")
    one, one_cpu = measure(dataset, 0)
    two, _ = measure(dataset, 2)
    print(f"1 process : {one:7.1f} five-view samples/s wall, {one_cpu:7.1f} per CPU-second (target >= 40 per core)")
    print(f"2 workers : {two:7.1f} five-view samples/s wall -> {two / 2:7.1f} per core; scaling x{two / one:.2f}")
    print(f"load average during the run: {os.getloadavg()[0]:.1f} (wall figures need an idle machine)")
    print(verification_cost(dataset))


if __name__ == "__main__":
    main()
