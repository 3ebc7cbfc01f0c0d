"""Scene-Shapes builder throughput at 512x512: frames/s per core with 1 and 2 workers, side by side.

Each configuration builds the same small dataset from scratch through the real CLI (planning,
rendering, encoding, Parquet writing, manifest), in this process so worker start-up counts too.
Two per-core figures are printed: wall-clock frames/s divided by the workers, and frames per
CPU-second of the build (its own and its workers' user+system time), which stays meaningful on a
machine that other jobs share.

    python scripts/bench/scene_shapes.py [--scenes 8] [--resolution 512] [--workers 1 2]
"""

from __future__ import annotations

import argparse
import os
import resource
import tempfile
import time
from pathlib import Path

from pipelines.scene_shapes.cli import main as build_main
from usl.records import load_manifest


def cpu_seconds() -> float:
    """User + system time of this process and of its finished children (the pool workers)."""
    total = 0.0
    for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN):
        usage = resource.getrusage(who)
        total += usage.ru_utime + usage.ru_stime
    return total


def run(workers: int, scenes: int, resolution: int, views: tuple[int, int], root: Path) -> dict[str, float]:
    out = root / f"workers-{workers}"
    argv = [
        "--out",
        str(out),
        "--num-scenes",
        str(scenes),
        "--num-models",
        "60",
        "--resolution",
        str(resolution),
        "--azimuths",
        str(views[0]),
        "--heights",
        str(views[1]),
        "--workers",
        str(workers),
        "--quiet",
    ]
    cpu0, wall0 = cpu_seconds(), time.perf_counter()
    if build_main(argv) != 0:
        raise SystemExit(f"build with --workers {workers} failed")
    wall, cpu = time.perf_counter() - wall0, cpu_seconds() - cpu0
    frames = sum(s["num_frames"] for s in load_manifest(out)["splits"].values())
    return {"workers": workers, "frames": frames, "wall": wall, "cpu": cpu}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", type=int, default=8)
    parser.add_argument("--resolution", type=int, default=512)
    parser.add_argument("--azimuths", type=int, default=8)
    parser.add_argument("--heights", type=int, default=3)
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    args = parser.parse_args()
    print(
        f"Scene-Shapes build, {args.scenes} scenes x {args.azimuths * args.heights} views at "
        f"{args.resolution}x{args.resolution}, {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f}"
    )
    with tempfile.TemporaryDirectory() as tmp:
        results = [run(w, args.scenes, args.resolution, (args.azimuths, args.heights), Path(tmp)) for w in args.workers]
    print(f"{'workers':>7} {'frames':>6} {'wall s':>7} {'frames/s':>8} {'frames/s/core':>13} {'frames/CPU-s':>12}")
    for r in results:
        fps = r["frames"] / r["wall"]
        print(
            f"{r['workers']:>7} {r['frames']:>6} {r['wall']:>7.1f} {fps:>8.2f} {fps / r['workers']:>13.2f} "
            f"{r['frames'] / r['cpu']:>12.2f}"
        )
    print("target: >= 2 frames/s/core")


if __name__ == "__main__":
    main()
