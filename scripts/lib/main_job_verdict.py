"""The main job's held-out table over several builds, and a check of what the README claims of it.

    python3 scripts/lib/main_job_verdict.py runs/main/eval     # reads runs/main/eval/seed*/metrics.json

Each ``seed<k>/metrics.json`` is usl-eval's report on a Scene-Shapes build made with ``--seed k``
(shape models and scenes the model never saw), every input view of every scene scored. Prints, and
writes to ``table.md`` and ``summary.json`` in the folder: each row's mean ± std over the builds
(sample std) and every build's figures.

The claim (exit 1 if it fails): on every held-out build, USL beats the fixed-depth and the
random-depth spheres on all four metrics (Chamfer, F1, Mask IoU in the input view and in the other
views). The learning targets are printed as MET / MISSED: the means lead the fixed-depth sphere by
at least 6 points of Mask IoU in the input view and 12 in the other views.
"""

from __future__ import annotations

import json
import statistics
import sys
from pathlib import Path

from usl.evaluation.report import COLUMNS, builds_summary, mean_std_cell, read_builds, row_values

TABLE_COLUMNS = COLUMNS["scene_shapes"]  # Chamfer, F1, Mask IoU input, Mask IoU views: titles, scales, decimals
MODEL, SPHERES = "USL", ("Fixed depth", "Random depth")
# points of Mask IoU (x100) by which USL's means must lead the fixed-depth sphere
LEAD_TARGETS = {"mask_iou_input": 6.0, "mask_iou_views": 12.0}


def markdown(builds: dict[int, dict], values: dict[str, dict[str, list[float]]]) -> str:
    seeds = ", ".join(str(s) for s in builds)
    views = sum(b["num_input_views"] for b in builds.values())
    titles = " | ".join(c.title for c in TABLE_COLUMNS)

    lines = [
        f"Held-out Scene-Shapes builds (seeds {seeds}): every input view of every scene, {views} input views;",
        "mean ± std over the builds (Builds: how many scored the row).",
        "",
        f"| Model | {titles} | Builds |",
        "|:---|" + ":---:|" * (len(TABLE_COLUMNS) + 1),
    ]
    for name, row in values.items():
        cells = " | ".join(mean_std_cell(row[c.metric], c) for c in TABLE_COLUMNS)
        lines.append(f"| {name} | {cells} | {max(len(v) for v in row.values())} |")
    lines += ["", "Every build:", "", f"| Model | Seed | {titles} |", "|:---|:---:|" + ":---:|" * len(TABLE_COLUMNS)]
    for seed, report in builds.items():
        for predictor in report["predictors"]:
            cells = " | ".join(
                mean_std_cell([v] if (v := predictor["metrics"].get(c.metric)) is not None else [], c)
                for c in TABLE_COLUMNS
            )
            lines.append(f"| {predictor['name']} | {seed} | {cells} |")
    return "\n".join(lines) + "\n"


def verdict(builds: dict[int, dict], values: dict[str, dict[str, list[float]]]) -> tuple[bool, list[str]]:
    """Whether every build's USL row beats both spheres on every metric, and the lines that say so."""
    ok, lines = True, []
    for seed, report in builds.items():
        rows = {p["name"]: p["metrics"] for p in report["predictors"]}
        missing = [name for name in (MODEL, *SPHERES) if name not in rows]
        if missing:
            raise SystemExit(
                f"main_job_verdict: seed{seed}/metrics.json has no row for {', '.join(missing)} "
                "(usl-eval --rows random,fixed,model)"
            )
        for c in TABLE_COLUMNS:
            ours = rows[MODEL][c.metric]
            for sphere in SPHERES:
                theirs = rows[sphere][c.metric]
                wins = ours < theirs if c.lower_is_better else ours > theirs
                ok &= wins
                if not wins:
                    lines.append(f"FAIL: seed {seed}: USL {c.metric} {ours:.3f} vs {sphere} {theirs:.3f}")
    count = len(builds) * len(TABLE_COLUMNS) * len(SPHERES)
    if ok:
        lines.append(
            f"PASS: on every build (seeds {', '.join(map(str, builds))}) USL beats both spheres on all four metrics ({count} comparisons)"
        )
    for metric, goal in LEAD_TARGETS.items():
        lead = 100 * (statistics.fmean(values[MODEL][metric]) - statistics.fmean(values[SPHERES[0]][metric]))
        met = lead >= goal
        lines.append(
            f"target {'MET' if met else 'MISSED'}: USL's mean {metric} leads {SPHERES[0]} by {lead:+.1f} points (>= {goal:+.0f})"
        )
    return ok, lines


def main(folder: str) -> int:
    root = Path(folder)
    try:
        builds = read_builds(root)
    except ValueError as exc:
        raise SystemExit(f"main_job_verdict: {exc}") from None
    values = row_values(builds, TABLE_COLUMNS)
    table = markdown(builds, values)
    ok, lines = verdict(builds, values)
    summary = {**builds_summary(builds, values), "claim_holds": ok}
    (root / "table.md").write_text(table)
    (root / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    print(table)
    print("\n".join(lines))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1]))
