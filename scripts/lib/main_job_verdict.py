"""Prints the main job's held-out table and checks what the README claims of it.

The claim (exit 1 if it fails): on Scene-Shapes scenes the model never saw (a build with another
--seed), USL beats the fixed-depth and random-depth spheres on Chamfer, F1 and Mask IoU in the
other views. Mask IoU in the input view, where a sphere filling the true box is already a strong
fit, is compared and printed but not claimed (README: the main job's model does not beat the
fixed-depth sphere there yet). The learning targets of issue F are printed as MET / MISSED.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

METRICS = (("chamfer", "lower"), ("f1", "higher"), ("mask_iou_input", "higher"), ("mask_iou_views", "higher"))
CLAIMED = {"chamfer", "f1", "mask_iou_views"}
# metrics.json stores IoUs as fractions, F1 in percent (as the table prints them x100 / as is)
TARGETS = {"chamfer": 0.060, "f1": 50.0, "mask_iou_input": 0.50, "mask_iou_views": 0.33}


def better(ours: float, theirs: float, direction: str) -> bool:
    return ours < theirs if direction == "lower" else ours > theirs


def main(metrics_path: str) -> int:
    report = json.loads(Path(metrics_path).read_text())
    rows = {p["name"]: p["metrics"] for p in report["predictors"]}
    print((Path(metrics_path).parent / "table.md").read_text())
    ok = True
    for metric, direction in METRICS:
        ours = rows["USL"][metric]
        for baseline in ("Fixed depth", "Random depth"):
            wins = better(ours, rows[baseline][metric], direction)
            claimed = metric in CLAIMED
            ok &= wins or not claimed
            verdict = ("PASS" if wins else "FAIL") if claimed else ("beats" if wins else "below") + " (not claimed)"
            print(
                f"{verdict}: USL {metric} {ours:.3f} vs {baseline} {rows[baseline][metric]:.3f} ({direction} is better)"
            )
    for metric, direction in METRICS:
        ours, goal = rows["USL"][metric], TARGETS[metric]
        met = ours <= goal if direction == "lower" else ours >= goal
        print(
            f"target {'MET' if met else 'MISSED'}: USL {metric} {ours:.3f} ({'<=' if direction == 'lower' else '>='} {goal})"
        )
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1]))
