"""Benchmark of ``usl-convert-hypersim`` on synthetic 1024x768 Hypersim frames.

Prints, measured side by side in one run:
  * frames per CPU-second of one single-threaded process (= frames/s/core) converting to
    full-resolution and half-resolution records, with a per-stage breakdown of one frame. CPU time,
    not wall time, so other jobs on a shared machine do not distort it (they still share caches);
  * peak resident memory of whole CLI builds of 2 and of 6 scenes (it must not grow with scenes).

Frames come from the test fixture writer (tests/pipelines/hypersim/hypersim_fixture.py) with the
release's dtypes and gzip level 9; scenes beyond the first hard-link its image files.

    python scripts/bench/hypersim.py [--frames 6] [--workdir DIR]
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from types import ModuleType

import numpy as np

from pipelines.hypersim.convert import (
    ConvertOptions,
    TrajectoryConverter,
    TrajectoryUnit,
    build_trajectory,
    single_threaded_worker,
)
from pipelines.hypersim.frames import read_hdf5_frame
from pipelines.hypersim.instances import category_votes, instance_entries
from pipelines.hypersim.metadata import read_camera_csv
from pipelines.hypersim.tonemap import apply_tonemap, tonemap_scale
from usl.records import encode_depth, encode_image

REPO = Path(__file__).resolve().parents[2]


def _load_fixture_writer() -> ModuleType:
    """The Hypersim test fixture's writer, loaded by path: a test helper, not part of the installed packages."""
    spec = importlib.util.spec_from_file_location(
        "hypersim_fixture", REPO / "tests/pipelines/hypersim/hypersim_fixture.py"
    )
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses look their module up while being defined
    spec.loader.exec_module(module)
    return module


fixture = _load_fixture_writer()

WIDTH, HEIGHT = 1024, 768
MAX_SCENES = 6


def make_inputs(root: Path, frames: int) -> tuple[Path, Path, Path]:
    """Scene ai_001_001 rendered for real; ai_001_002.. share its frames through hard links."""
    scenes = root / "scenes"
    template = fixture.make_scene("ai_001_001", WIDTH, HEIGHT, keyframes=frames)
    source = fixture.write_scene(scenes, template, {"cam_00": list(range(frames))})
    rows = fixture.split_rows("ai_001_001", "cam_00", range(frames), "train")
    names = ["ai_001_001"]
    for k in range(2, MAX_SCENES + 1):
        name = f"ai_001_{k:03d}"
        names.append(name)
        for path in source.rglob("*"):
            target = scenes / name / path.relative_to(source)
            if path.is_dir():
                target.mkdir(parents=True, exist_ok=True)
            else:
                os.link(path, target)
        rows += fixture.split_rows(name, "cam_00", range(frames), "train")
    split_csv = fixture.write_split_csv(root / "split.csv", rows)
    clones = [fixture.make_scene(n, WIDTH, HEIGHT, keyframes=frames) for n in names]
    return scenes, split_csv, fixture.write_camera_csv(root / "cameras.csv", clones)


def unit_for(scenes: Path, camera_csv: Path, frames: int, options: ConvertOptions) -> TrajectoryUnit:
    model = read_camera_csv(camera_csv)["ai_001_001"]
    return TrajectoryUnit("ai_001_001", "cam_00", str(scenes / "ai_001_001"), model, tuple(range(frames)), (), options)


def frames_per_second(unit: TrajectoryUnit, repeats: int = 2) -> float:
    build_trajectory(unit)  # warm the page cache and imports
    best = min(_timed(lambda: build_trajectory(unit)) for _ in range(repeats))
    return len(unit.frames) / best


def _timed(fn) -> float:
    """CPU seconds of this (single-threaded) process."""
    start = time.process_time()
    fn()
    return time.process_time() - start


def stage_breakdown(unit: TrajectoryUnit) -> dict[str, float]:
    """CPU milliseconds per stage for frame 0 (median of 5)."""
    converter = TrajectoryConverter(unit)
    raw = read_hdf5_frame(converter.paths, 0)
    valid = raw.entity != -1
    planar = raw.distance * converter.depth_factor
    resampler = converter.resampler
    depth = resampler.depth(planar)
    labels = resampler.labels(raw.instance)
    rgb = apply_tonemap(resampler.colour(raw.rgb), tonemap_scale(raw.rgb, valid))
    stages = {
        "read 5 HDF5 files": lambda: read_hdf5_frame(converter.paths, 0),
        "tone map (+resize)": lambda: apply_tonemap(resampler.colour(raw.rgb), tonemap_scale(raw.rgb, valid)),
        "planar depth (+resize)": lambda: resampler.depth(raw.distance * converter.depth_factor),
        "category votes": lambda: category_votes(raw.instance, raw.semantic),
        "instance masks": lambda: instance_entries(labels, depth),
        "encode image": lambda: encode_image(rgb, unit.options.image_codec, unit.options.image_quality),
        "encode depth PNG": lambda: encode_depth(depth),
    }
    return {name: 1000 * float(np.median([_timed(fn) for _ in range(5)])) for name, fn in stages.items()}


def peak_rss_mib(scenes: Path, split_csv: Path, camera_csv: Path, count: int, out: Path) -> float:
    """Peak RSS of a fresh process running the CLI on the first ``count`` scenes (--workers 1)."""
    folders = [str(scenes / f"ai_001_{k:03d}") for k in range(1, count + 1)]
    argv = folders + ["--split-csv", str(split_csv), "--camera-csv", str(camera_csv), "--out", str(out), "--quiet"]
    code = (
        "import resource, sys\nfrom pipelines.hypersim.cli import main\n"
        f"assert main({argv!r}) == 0\n"
        "print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)"
    )
    result = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, check=True)
    return int(result.stdout.strip().splitlines()[-1]) / 1024


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=6, help="frames per scene")
    parser.add_argument("--workdir", type=Path, default=None, help="keep inputs and outputs here")
    args = parser.parse_args()
    single_threaded_worker()
    with tempfile.TemporaryDirectory() as tmp:
        root = args.workdir or Path(tmp)
        root.mkdir(parents=True, exist_ok=True)
        start = time.perf_counter()
        scenes, split_csv, camera_csv = make_inputs(root, args.frames)
        print(f"wrote {args.frames} frames of {WIDTH}x{HEIGHT} in {time.perf_counter() - start:.1f} s")
        print(f"\nframes per CPU-second, one thread ({args.frames} frames, JPEG q95, best of 2):")
        for label, resolution, depth in (
            ("full 1024x768", None, True),
            ("half 512x384", (512, 384), True),
            ("full, no depth", None, False),
            ("half, no depth", (512, 384), False),
        ):
            options = ConvertOptions(resolution=resolution, store_depth=depth)
            unit = unit_for(scenes, camera_csv, args.frames, options)
            print(f"  {label:16s} {frames_per_second(unit):6.2f} frames/s/core")
            if depth:
                for stage, ms in stage_breakdown(unit).items():
                    print(f"      {stage:24s} {ms:7.1f} ms")
        print("\npeak RSS of a CLI build (--workers 1):")
        rss = {n: peak_rss_mib(scenes, split_csv, camera_csv, n, root / f"out{n}") for n in (2, MAX_SCENES)}
        for n, mib in rss.items():
            print(f"  {n} scenes ({n * args.frames:3d} frames): {mib:7.1f} MiB")
        print(f"  ratio {MAX_SCENES} / 2 scenes: {rss[MAX_SCENES] / rss[2]:.2f}")


if __name__ == "__main__":
    main()
