"""Table 1 at CPU scale: mean ± std over seeds of each row's held-out metrics (scripts/experiments/table1.sh).

    python3 scripts/experiments/table1_summary.py runs/table1            # writes table1.md and table1.json there
    python3 scripts/experiments/table1_summary.py --combine runs/table1/runs/usl5/seed0/eval  # its builds' summary.json
    python3 scripts/experiments/table1_summary.py --run runs/table1/runs/usl5/seed0/eval   # one run's line

Runs are scored as the main job scores its model: usl-eval on every input view of the train split
of each held-out build (``EVAL/seed<k>/metrics.json``), and ``--combine`` writes their mean ± std
over the builds to ``EVAL/summary.json`` in the main job's format (``usl.evaluation.report.builds_summary``).
A run's figure on a metric is that mean over the builds.

Reads the output folder table1.sh lays out: ``plan.tsv`` (the trained rows and their status),
``baselines/eval/summary.json`` (usl-eval's fixed and random rows, scored once) and
``runs/<row>/seed<k>/{train,eval}`` (a training run and the ``summary.json`` of its scoring). The
std is the sample std (ddof=1) over the seeds that finished; one seed prints its mean and n=1.
Each row names the checkpoint its runs scored (the run folder's last checkpoint). Below the table,
each of the paper's six orderings of the rows is judged on the means (see ``orderings``).
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from table1_plan import ROWS, Row  # a sibling script: python puts this folder on sys.path

from usl.evaluation.report import COLUMNS, Column, builds_summary, mean_std, mean_std_cell, read_builds, row_values
from usl.records.atomic import write_text_atomic

TABLE_COLUMNS: list[Column] = COLUMNS["scene_shapes"]  # usl-eval's Table 1 columns: titles, scales, decimals
BY_METRIC = {c.metric: c for c in TABLE_COLUMNS}
ALL_METRICS = tuple(BY_METRIC)
SUMMARY = "summary.json"  # a scored run's (or the baselines') figures over the held-out builds
_SEED = re.compile(r"^seed(\d+)$")
_CHECKPOINT = re.compile(r"^model_(\d+)\.pt$")


@dataclass
class Run:
    seed: int
    checkpoint: str  # relative to the table's folder
    iteration: int
    metrics: dict[str, float | None]


@dataclass
class RowSummary:
    row: Row
    status: str  # "baseline", "trained", "no finished run" or the plan's "skipped: ..."
    runs: list[Run] = field(default_factory=list)

    def values(self, metric: str) -> list[float]:
        return [r.metrics[metric] for r in self.runs if r.metrics.get(metric) is not None]

    def mean_std(self, metric: str) -> tuple[float | None, float | None]:
        """Mean and sample std (ddof=1; None for fewer than two values)."""
        return mean_std(self.values(metric))


def combine(eval_dir: Path) -> None:
    """Write ``eval_dir/summary.json``: the mean ± std over the held-out builds scored there
    (``seed<k>/metrics.json``), the one file the table reads of a run."""
    builds = read_builds(eval_dir)
    summary = builds_summary(builds, row_values(builds, TABLE_COLUMNS))
    write_text_atomic(eval_dir / SUMMARY, json.dumps(summary, indent=2) + "\n")


def heldout_means(summary_json: Path, name: str | None = None) -> dict[str, float | None]:
    """Predictor ``name``'s mean over the held-out builds of each metric, from a ``summary.json``
    (``None``: its only predictor)."""
    rows = json.loads(summary_json.read_text())["rows"]
    chosen = [n for n in rows if name is None or n == name]
    if len(chosen) != 1:
        want = repr(name) if name else "exactly one predictor"
        raise ValueError(f"{summary_json}: expected {want}, found: {', '.join(rows) or 'none'}")
    return {c.metric: rows[chosen[0]].get(c.metric, {}).get("mean") for c in TABLE_COLUMNS}


def scored_checkpoint(train_dir: Path) -> tuple[Path, int]:
    """The run folder's last checkpoint (what ``usl-eval --checkpoint RUN`` scores) and its iteration."""
    pointer = train_dir / "checkpoints" / "last_checkpoint"
    name = pointer.read_text().strip()
    match = _CHECKPOINT.match(name)
    if match is None:
        raise ValueError(f"{pointer}: {name!r} is not a checkpoint name (model_<iteration>.pt)")
    return pointer.parent / name, int(match.group(1))


def read_runs(out: Path, row: Row) -> list[Run]:
    """The row's runs scored on every held-out build (their ``summary.json``), by seed."""
    runs = []
    for seed_dir in (out / "runs" / row.slug).glob("seed*"):
        match, summary_json = _SEED.match(seed_dir.name), seed_dir / "eval" / SUMMARY
        if match is None or not summary_json.is_file():
            continue
        checkpoint, iteration = scored_checkpoint(seed_dir / "train")
        runs.append(Run(int(match.group(1)), str(checkpoint.relative_to(out)), iteration, heldout_means(summary_json)))
    return sorted(runs, key=lambda r: r.seed)


def read_plan(out: Path) -> dict[str, str]:
    """slug -> status of the trained rows, from ``plan.tsv``."""
    plan = out / "plan.tsv"
    if not plan.is_file():
        raise ValueError(f"{plan}: missing (scripts/experiments/table1.sh writes it before training)")
    return {line.split("\t")[0]: line.split("\t")[2] for line in plan.read_text().splitlines() if line.strip()}


def summarize(out: Path) -> list[RowSummary]:
    plan = read_plan(out)
    baselines = out / "baselines" / "eval" / SUMMARY
    summaries = []
    for row in ROWS:
        if not row.trained:
            if baselines.is_file():
                summaries.append(RowSummary(row, "baseline", [Run(0, "–", 0, heldout_means(baselines, row.baseline))]))
            else:
                summaries.append(RowSummary(row, "no finished run"))
        elif row.slug in plan:  # rows of this checkout's plan; the plan's status says why a row did not train
            status, runs = plan[row.slug], []
            if status == "train":
                runs = read_runs(out, row)
                status = "trained" if runs else "no finished run"
            summaries.append(RowSummary(row, status, runs))
    return summaries


def cell(summary: RowSummary, column: Column) -> str:
    return mean_std_cell(summary.values(column.metric), column)


def seeds_cell(summary: RowSummary) -> str:
    if summary.status == "baseline":
        return "– (not trained)"
    if not summary.runs:
        return summary.status
    return f"n={len(summary.runs)} (seed {', '.join(str(r.seed) for r in summary.runs)})"


def checkpoints_cell(summary: RowSummary) -> str:
    """The checkpoint file name(s) and iteration(s) the row's runs scored (paths: the per-run table)."""
    if summary.status != "trained":
        return "–"
    scored = sorted({(r.iteration, Path(r.checkpoint).name) for r in summary.runs})
    return "; ".join(f"{name} (iteration {iteration})" for iteration, name in scored)


def _markdown(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|:---|" + ":---:|" * (len(header) - 1)]
    return "\n".join(lines + ["| " + " | ".join(r) + " |" for r in rows])


@dataclass(frozen=True)
class Comparison:
    text: str  # the metric and both rows' mean ± seed std, in the table's units
    holds: bool


@dataclass(frozen=True)
class Ordering:
    key: str  # a-f, as docs/results.md lists the paper's orderings
    claim: str
    verdict: str  # "holds", "does not hold" or "not measured"
    comparisons: tuple[Comparison, ...]  # those whose rows both finished
    missing: tuple[str, ...]  # labels of the rows it needs that have no finished run


def _figure(summary: RowSummary, column: Column) -> str:
    return f"{summary.row.label} {cell(summary, column)}"


def beats(row: RowSummary, other: RowSummary, column: Column) -> Comparison:
    """``row``'s mean is better than ``other``'s: lower for an error such as Chamfer, higher otherwise."""
    mine, theirs = row.mean_std(column.metric)[0], other.mean_std(column.metric)[0]
    holds = mine < theirs if column.lower_is_better else mine > theirs
    return Comparison(f"{column.title}: {_figure(row, column)} vs {_figure(other, column)}", holds)


def costs_little(row: RowSummary, other: RowSummary, column: Column) -> Comparison:
    """``row`` is worse than ``other`` by at most the larger of the two rows' seed std (0 when
    neither has two seeds): a gap inside the spread over seeds is not a cost the table resolves."""
    (mine, my_std), (theirs, their_std) = row.mean_std(column.metric), other.mean_std(column.metric)
    tolerance = max(my_std or 0.0, their_std or 0.0)
    cost = mine - theirs if column.lower_is_better else theirs - mine
    allowed = f"{tolerance * column.scale:.{column.decimals}f}"
    return Comparison(
        f"{column.title}: {_figure(row, column)} vs {_figure(other, column)}, tolerance {allowed}", cost <= tolerance
    )


USL_ROWS = ("usl2", "usl5", "usl5_vertalign", "usl5_no_dist")
BASELINES = ("fixed", "random")
# The paper's orderings of Table 1 (docs/results.md): key, claim, and the comparisons that decide it
# as (test, row, other row, metrics).
ORDERINGS = (
    (
        "a",
        "every USL row beats both baselines on all four metrics",
        tuple((beats, usl, base, ALL_METRICS) for usl in USL_ROWS for base in BASELINES),
    ),
    (
        "b",
        "USL (5 views) beats USL (2 views) on Chamfer, F1 and Mask IoU in the other views",
        ((beats, "usl5", "usl2", ("chamfer", "f1", "mask_iou_views")),),
    ),
    (
        "c",
        "RoIMap (USL (5 views)) beats VertAlign (USL (5) w/o RoIMap) on every metric",
        ((beats, "usl5", "usl5_vertalign", ALL_METRICS),),
    ),
    (
        "d",
        "removing ℓ_dist costs little in 3D: USL (5) w/o ℓ_dist is behind USL (5 views) on Chamfer and F1 "
        "by at most the larger of the two rows' seed std",
        ((costs_little, "usl5_no_dist", "usl5", ("chamfer", "f1")),),
    ),
    (
        "e",
        "removing ℓ_dist mostly costs Mask IoU: USL (5) w/o ℓ_dist is below USL (5 views) in the input and the other views",
        ((beats, "usl5", "usl5_no_dist", ("mask_iou_input", "mask_iou_views")),),
    ),
    (
        "f",
        "Mesh R-CNN (3D sup.) beats every USL row on every metric",
        tuple((beats, "meshrcnn_3d", usl, ALL_METRICS) for usl in USL_ROWS),
    ),
)
LISTED = 4  # comparisons an ordering that holds lists (those of two rows); (a) and (f) give their count


def _measured(summary: RowSummary) -> bool:
    return all(summary.values(metric) for metric in ALL_METRICS)


def orderings(summaries: Sequence[RowSummary]) -> list[Ordering]:
    """Each of the paper's orderings judged on the rows' means: "does not hold" as soon as one
    comparison of finished rows fails (a row missing does not undo a failure), else "not measured"
    while a row it needs has no finished run, else "holds"."""
    rows = {s.row.slug: s for s in summaries if _measured(s)}
    judged = []
    for key, claim, checks in ORDERINGS:
        needed = {slug for _, row, other, _ in checks for slug in (row, other)}
        missing = tuple(r.label for r in ROWS if r.slug in needed and r.slug not in rows)
        comparisons = tuple(
            test(rows[row], rows[other], BY_METRIC[metric])
            for test, row, other, metrics in checks
            if row in rows and other in rows
            for metric in metrics
        )
        verdict = "does not hold" if not all(c.holds for c in comparisons) else "not measured" if missing else "holds"
        judged.append(Ordering(key, claim, verdict, comparisons, missing))
    return judged


def ordering_line(ordering: Ordering) -> str:
    """An ordering's verdict and what decides it: the failing comparisons, the missing rows, or
    the comparisons it rests on."""
    if ordering.verdict == "does not hold":
        shown = "fails on " + "; ".join(c.text for c in ordering.comparisons if not c.holds)
    elif ordering.verdict == "not measured":
        shown = f"no finished run of {', '.join(ordering.missing)}"
    elif len(ordering.comparisons) <= LISTED:
        shown = "; ".join(c.text for c in ordering.comparisons)
    else:
        shown = f"all {len(ordering.comparisons)} comparisons; figures in the table above"
    return f"- ({ordering.key}) {ordering.claim}: **{ordering.verdict}** ({shown})"


def scored_on(out: Path) -> str:
    """The held-out builds and input views of the folder's scorings (each distinct set, so a folder
    scored two ways shows it), from their ``summary.json``."""
    scorings = set()
    for summary_json in [*out.glob(f"baselines/eval/{SUMMARY}"), *out.glob(f"runs/*/seed*/eval/{SUMMARY}")]:
        summary = json.loads(summary_json.read_text())
        scorings.add((tuple(summary["seeds"]), sum(summary["num_input_views"].values())))
    return "; ".join(
        f"held-out builds with seeds {', '.join(map(str, seeds))} ({views} input views per model)"
        for seeds, views in sorted(scorings)
    )


def markdown(summaries: Sequence[RowSummary], scored: str, judged: Sequence[Ordering]) -> str:
    """How the runs were scored, the table (mean ± std over seeds), the paper's orderings judged
    on it and, below them, every run with the checkpoint it scored."""
    intro = (
        f"Scored on every input view of the train split of {scored or 'no held-out build yet'}: a run's figure is "
        "its mean over the builds, a cell the mean ± sample std over the training seeds."
    )
    header = ["Model"] + [c.title for c in TABLE_COLUMNS] + ["Seeds", "Checkpoint"]
    table = _markdown(
        header,
        [[s.row.label] + [cell(s, c) for c in TABLE_COLUMNS] + [seeds_cell(s), checkpoints_cell(s)] for s in summaries],
    )
    verdicts = "\n".join(ordering_line(o) for o in judged)
    per_run = [
        [s.row.label, str(r.seed)] + [cell(RowSummary(s.row, s.status, [r]), c) for c in TABLE_COLUMNS] + [r.checkpoint]
        for s in summaries
        if s.status == "trained"
        for r in s.runs
    ]
    runs = _markdown(["Model", "Seed"] + [c.title for c in TABLE_COLUMNS] + ["Checkpoint scored"], per_run)
    return (
        f"{intro}\n\n{table}\n\nThe paper's orderings, judged on the means (figures: mean ± std over seeds):\n\n"
        f"{verdicts}\n\nEvery run:\n\n{runs}\n"
    )


def as_json(summaries: Sequence[RowSummary]) -> list[dict[str, Any]]:
    rows = []
    for s in summaries:
        metrics = {}
        for c in TABLE_COLUMNS:
            mean, std = s.mean_std(c.metric)
            metrics[c.metric] = {"mean": mean, "std": std, "values": s.values(c.metric)}
        rows.append(
            {
                "label": s.row.label,
                "slug": s.row.slug,
                "status": s.status,
                "n": len(s.runs),
                "metrics": metrics,
                "runs": [
                    {"seed": r.seed, "checkpoint": r.checkpoint, "iteration": r.iteration}
                    for r in s.runs
                    if s.status == "trained"
                ],
            }
        )
    return rows


def run_line(eval_dir: Path) -> str:
    """One run's means over the held-out builds, in the table's units, for table1.sh's progress lines."""
    metrics = heldout_means(eval_dir / SUMMARY)
    return ", ".join(
        f"{c.title} {'–' if metrics.get(c.metric) is None else f'{metrics[c.metric] * c.scale:.{c.decimals}f}'}"
        for c in TABLE_COLUMNS
    )


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("out", nargs="?", help="the table's output folder (scripts/experiments/table1.sh --out)")
    p.add_argument("--run", help="print one run's eval folder as a line instead")
    p.add_argument("--combine", help="write an eval folder's summary.json over its held-out builds instead")
    args = p.parse_args(argv)
    try:
        if args.combine:
            combine(Path(args.combine))
            return 0
        if args.run:
            print(run_line(Path(args.run)))
            return 0
        if not args.out:
            p.error("give the table's output folder, or --run / --combine EVAL_DIR")
        out = Path(args.out)
        summaries = summarize(out)
        judged, scored = orderings(summaries), scored_on(out)
        text = markdown(summaries, scored, judged)
        (out / "table1.md").write_text(text)
        document = {"scored_on": scored, "rows": as_json(summaries), "orderings": [asdict(o) for o in judged]}
        (out / "table1.json").write_text(json.dumps(document, indent=1, ensure_ascii=False) + "\n")
    except (OSError, ValueError, KeyError) as exc:
        print(f"table1_summary: error: {exc}", file=sys.stderr)
        return 2
    print(text, end="")
    return 0


if __name__ == "__main__":
    sys.exit(main())
