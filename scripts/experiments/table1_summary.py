"""Table 1 at CPU scale: mean ± std over seeds of each row's held-out metrics (scripts/experiments/table1.sh).

    python3 scripts/experiments/table1_summary.py runs/table1            # writes table1.md and table1.json there
    python3 scripts/experiments/table1_summary.py --run runs/table1/runs/usl5/seed0/eval   # one run's line

Reads the output folder table1.sh lays out: ``plan.tsv`` (the trained rows and their status),
``baselines/eval/metrics.json`` (usl-eval's fixed and random rows, scored once) and
``runs/<row>/seed<k>/{train,eval}`` (a training run and usl-eval's ``metrics.json`` of it). The
std is the sample std (ddof=1) over the seeds that finished; one seed prints its mean and n=1.
Each row names the checkpoint its runs scored (the run folder's last checkpoint).
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from table1_plan import ROWS, Row  # a sibling script: python puts this folder on sys.path

from usl.evaluation.report import COLUMNS, Column, mean_std, mean_std_cell

TABLE_COLUMNS: list[Column] = COLUMNS["scene_shapes"]  # usl-eval's Table 1 columns: titles, scales, decimals
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


def predictor_metrics(metrics_json: Path, name: str | None = None) -> dict[str, float | None]:
    """The metrics of predictor ``name`` in a usl-eval ``metrics.json`` (``None``: its only predictor)."""
    predictors = json.loads(metrics_json.read_text())["predictors"]
    chosen = [p for p in predictors if name is None or p["name"] == name]
    if len(chosen) != 1:
        names = ", ".join(p["name"] for p in predictors)
        want = repr(name) if name else "exactly one predictor"
        raise ValueError(f"{metrics_json}: expected {want}, found: {names or 'none'}")
    return chosen[0]["metrics"]


def scored_checkpoint(train_dir: Path) -> tuple[Path, int]:
    """The run folder's last checkpoint (what ``usl-eval --checkpoint RUN`` scores) and its iteration."""
    pointer = train_dir / "checkpoints" / "last_checkpoint"
    name = pointer.read_text().strip()
    match = _CHECKPOINT.match(name)
    if match is None:
        raise ValueError(f"{pointer}: {name!r} is not a checkpoint name (model_<iteration>.pt)")
    return pointer.parent / name, int(match.group(1))


def read_runs(out: Path, row: Row) -> list[Run]:
    """The row's runs that have a held-out ``metrics.json``, by seed."""
    runs = []
    for seed_dir in (out / "runs" / row.slug).glob("seed*"):
        match, metrics_json = _SEED.match(seed_dir.name), seed_dir / "eval" / "metrics.json"
        if match is None or not metrics_json.is_file():
            continue
        checkpoint, iteration = scored_checkpoint(seed_dir / "train")
        runs.append(
            Run(int(match.group(1)), str(checkpoint.relative_to(out)), iteration, predictor_metrics(metrics_json))
        )
    return sorted(runs, key=lambda r: r.seed)


def read_plan(out: Path) -> dict[str, str]:
    """slug -> status of the trained rows, from ``plan.tsv``."""
    plan = out / "plan.tsv"
    if not plan.is_file():
        raise ValueError(f"{plan}: missing (scripts/experiments/table1.sh writes it before training)")
    return {line.split("\t")[0]: line.split("\t")[2] for line in plan.read_text().splitlines() if line.strip()}


def summarize(out: Path) -> list[RowSummary]:
    plan = read_plan(out)
    baselines = out / "baselines" / "eval" / "metrics.json"
    summaries = []
    for row in ROWS:
        if not row.trained:
            if baselines.is_file():
                summaries.append(
                    RowSummary(row, "baseline", [Run(0, "–", 0, predictor_metrics(baselines, row.baseline))])
                )
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


def markdown(summaries: Sequence[RowSummary]) -> str:
    """The table (mean ± std over seeds) and, below it, every run with the checkpoint it scored."""
    header = ["Model"] + [c.title for c in TABLE_COLUMNS] + ["Seeds", "Checkpoint"]
    table = _markdown(
        header,
        [[s.row.label] + [cell(s, c) for c in TABLE_COLUMNS] + [seeds_cell(s), checkpoints_cell(s)] for s in summaries],
    )
    per_run = [
        [s.row.label, str(r.seed)] + [cell(RowSummary(s.row, s.status, [r]), c) for c in TABLE_COLUMNS] + [r.checkpoint]
        for s in summaries
        if s.status == "trained"
        for r in s.runs
    ]
    runs = _markdown(["Model", "Seed"] + [c.title for c in TABLE_COLUMNS] + ["Checkpoint scored"], per_run)
    return f"{table}\n\nEvery run:\n\n{runs}\n"


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
    """One run's held-out metrics, in the table's units, for table1.sh's progress lines."""
    metrics = predictor_metrics(eval_dir / "metrics.json")
    return ", ".join(
        f"{c.title} {'–' if metrics.get(c.metric) is None else f'{metrics[c.metric] * c.scale:.{c.decimals}f}'}"
        for c in TABLE_COLUMNS
    )


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("out", nargs="?", help="the table's output folder (scripts/experiments/table1.sh --out)")
    p.add_argument("--run", help="print one run's eval folder as a line instead")
    args = p.parse_args(argv)
    try:
        if args.run:
            print(run_line(Path(args.run)))
            return 0
        if not args.out:
            p.error("give the table's output folder, or --run EVAL_DIR")
        out = Path(args.out)
        summaries = summarize(out)
        text = markdown(summaries)
        (out / "table1.md").write_text(text)
        (out / "table1.json").write_text(json.dumps(as_json(summaries), indent=1) + "\n")
    except (OSError, ValueError, KeyError) as exc:
        print(f"table1_summary: error: {exc}", file=sys.stderr)
        return 2
    print(text, end="")
    return 0


if __name__ == "__main__":
    sys.exit(main())
