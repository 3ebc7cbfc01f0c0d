"""Benchmark of ``usl-convert-captures --poses sfm``: time and accuracy of COLMAP's SfM (pycolmap, CPU).

Renders the test capture (``tests.pipelines.captures.synthetic_capture``: a table and a chair along a 100-degree
arc, noise-textured, with depth and detections), leaves out its poses, converts it with
``--poses sfm`` and reports wall time and CPU time (this process and its threads: pycolmap runs
in-process) of the whole conversion, the fraction of frames SfM registered, the worst relative
rotation error over all pairs of registered frames, and the metric scale's error (scale from the
depth maps; the truth is known). Target: 24 frames of 640x480 in <= 2 minutes on 2 cores, >= 90 %
registered, <= 1 degree, scale within 2 %.

    PYOPENGL_PLATFORM=egl python scripts/bench/captures_sfm.py [--frames 24] [--size 640 480] [--work /tmp/bench_sfm]
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the checkout: its tests' rendered capture

from pipelines.captures.cli import main as convert  # noqa: E402
from tests.pipelines.captures.synthetic_capture import render_capture, write_detections, write_transforms  # noqa: E402
from usl.records import RecordsDataset, load_manifest  # noqa: E402


def cpu_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def rotation_degrees(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))))


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--frames", type=int, default=24)
    p.add_argument("--size", type=int, nargs=2, default=(640, 480), metavar=("W", "H"))
    p.add_argument("--work", type=Path, default=Path("/tmp/bench_captures_sfm"))
    args = p.parse_args()
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    shutil.rmtree(args.work, ignore_errors=True)
    truth = render_capture(args.frames, *args.size)
    capture = args.work / "capture"
    write_transforms(truth, capture)
    write_detections(truth, capture)
    (capture / "transforms.json").unlink()  # only images/, depth/ and detections.json are left
    out = args.work / "records"
    wall, cpu = time.perf_counter(), cpu_seconds()
    if convert([str(capture), "--out", str(out), "--quiet", "--poses", "sfm"]) != 0:
        return 1
    wall, cpu = time.perf_counter() - wall, cpu_seconds() - cpu
    (about,) = load_manifest(out)["provenance"].values()
    frames = RecordsDataset(out, "train").read_scene("capture", columns=["view_id", "cam_to_world"])
    poses = {f["view_id"]: np.asarray(f["cam_to_world"], float).reshape(4, 4) for f in frames}
    views = sorted(poses)
    worst = max(
        rotation_degrees(
            (np.linalg.inv(poses[a]) @ poses[b])[:3, :3].T
            @ (np.linalg.inv(truth.cam_to_world[a]) @ truth.cam_to_world[b])[:3, :3]
        )
        for a in views
        for b in views
        if a < b
    )
    # the scale error: camera-centre distances of all pairs, records against truth
    centres = np.array([poses[v][:3, 3] for v in views])
    true_centres = np.array([truth.cam_to_world[v][:3, 3] for v in views])
    spans = np.linalg.norm(centres[:, None] - centres[None], axis=-1)
    true_spans = np.linalg.norm(true_centres[:, None] - true_centres[None], axis=-1)
    ratio = spans[true_spans > 0] / true_spans[true_spans > 0]
    print(
        f"{args.frames} frames {args.size[0]}x{args.size[1]}, {os.cpu_count()} cores: wall {wall:.1f} s, "
        f"CPU {cpu:.1f} s; registered {len(views)}/{args.frames} ({about['frames_unposed']} not); worst relative "
        f"rotation {worst:.3f} deg; scale error {100 * (np.median(ratio) - 1):+.2f} % "
        f"(from {about['scale_samples']} sparse points, spread {100 * about['scale_spread']:.2f} %)"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
