"""Prints the main job's table and checks the claim the README makes: USL beats the fixed-depth and
random-depth baselines on Mask IoU (other views) and 3D Chamfer. Exits 1 if it does not."""
from __future__ import annotations

import json
import sys
from pathlib import Path

CLAIMS = (("mask_iou_views", "higher"), ("chamfer", "lower"))


def main(metrics_path: str) -> int:
    report = json.loads(Path(metrics_path).read_text())
    rows = {p["name"]: p["metrics"] for p in report["predictors"]}
    print((Path(metrics_path).parent / "table.md").read_text())
    ok = True
    for metric, better in CLAIMS:
        ours = rows["USL"][metric]
        for baseline in ("Fixed depth", "Random depth"):
            theirs = rows[baseline][metric]
            wins = ours > theirs if better == "higher" else ours < theirs
            ok &= wins
            print(f"{'PASS' if wins else 'FAIL'}: USL {metric} {ours:.3f} vs {baseline} {theirs:.3f} ({better} is better)")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1]))
