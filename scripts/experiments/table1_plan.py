"""Table 1 at CPU scale: its rows, each run's training budget, and the time it will take.

    python3 scripts/experiments/table1_plan.py --config tiny --iters 1100 --seeds 0,1,2 --jobs 2 --out runs/table1

Writes ``OUT/plan.tsv`` for ``scripts/experiments/table1.sh``, one line per trained row (slug, label, status,
the usl-train overrides of its runs), and prints the budget: iterations per run, runs, and the
estimated time. ``OUT/budget.txt`` records the budget; an output folder holding runs of another
budget is refused (more seeds are fine). A row whose config key this checkout's usl-train does not know is planned as
``skipped: key not available`` instead of failing the table.

``--iters`` other than the recipe's ``optim.max_iter`` scales the recipe's iteration-valued
schedule (LR steps, warm-up, l_dist schedule) with it, so a shorter budget keeps the recipe's shape.
"""

from __future__ import annotations

import argparse
import hashlib
import statistics
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from table1_record import finished  # a sibling script: python puts this folder on sys.path

from data_specs import load_dataset_spec
from pipelines.scene_shapes.plan import split_counts
from usl.config import Config, ConfigError, dump_config, load_config


@dataclass(frozen=True)
class Row:
    slug: str  # folder name of the row's runs
    label: str  # as the paper's Table 1 names it
    overrides: tuple[str, ...] = ()  # usl-train key=value on top of the recipe
    baseline: str | None = None  # usl-eval's predictor name for an untrained baseline row

    @property
    def trained(self) -> bool:
        return self.baseline is None


# The paper's Table 1, in its order (the config keys agreed for issue 10).
ROWS = (
    Row("fixed", "Fixed depth", baseline="Fixed depth"),
    Row("random", "Random depth", baseline="Random depth"),
    Row("usl2", "USL (2 views)", ("data.num_views=2",)),
    Row("usl5", "USL (5 views)", ("data.num_views=5",)),
    Row("usl5_vertalign", "USL (5) w/o RoIMap", ("data.num_views=5", "model.shape.sampler=vertalign")),
    Row("usl5_no_dist", "USL (5) w/o ℓ_dist", ("data.num_views=5", "loss.weights.dist=0")),
    Row("meshrcnn_3d", "Mesh R-CNN (3D sup.)", ("loss.supervision=3d",)),
)
TRAINED = tuple(r for r in ROWS if r.trained)

# CPU seconds (one thread) per iteration, usl-train's start-up and final checkpoint included,
# measured on this project's 2-core machine with two runs side by side: `bash scripts/experiments/table1.sh
# --iters 600 --seeds 0,1` with tiny's wider blur radius (runs/table1_600/progress.log,
# 2026-12-01): usl2 438-488 s CPU for 600 iterations, usl5 880 s, usl5_vertalign 764-775 s,
# usl5_no_dist 679-724 s, meshrcnn_3d 784-797 s. Runs of the output folder replace them (their
# train_time.txt).
MEASURED_SECONDS_PER_ITER = {
    "usl2": 0.76,
    "usl5": 1.47,
    "usl5_vertalign": 1.28,
    "usl5_no_dist": 1.17,
    "meshrcnn_3d": 1.32,
}
# usl-eval --rows model of one held-out build: start-up, and per input view (10k points per mesh;
# pictures, drawn of the first build only, add under 1 s); measured on this project's 2-core machine
# while two training processes shared it (2026-12-06): 15.3 s CPU for a 20-scene build's 128 input
# views, ~3.5 s for --quick's 8 (2,000 points). The periodic validation during training
# (val.period) is not counted.
EVAL_START_SECONDS, EVAL_SECONDS_PER_VIEW = 2.7, 0.095
# Each run is scored on every input view of the train split of each held-out build (8 views per scene).
VIEWS_PER_SCENE = 8


def budget_overrides(recipe: Config, iters: int) -> list[str]:
    """``optim.max_iter=iters``, and the recipe's iteration-valued schedule scaled to it."""
    out = [f"optim.max_iter={iters}"]
    if iters == recipe.optim.max_iter:
        return out
    at = lambda i: max(1, round(i * iters / recipe.optim.max_iter))  # noqa: E731
    listed = lambda values: "[" + ",".join(str(at(v)) for v in values) + "]"  # noqa: E731
    if recipe.optim.steps:
        out.append(f"optim.steps={listed(recipe.optim.steps)}")
    if recipe.optim.warmup_iters:
        out.append(f"optim.warmup_iters={at(recipe.optim.warmup_iters)}")
    if recipe.loss.dist_schedule.iters:
        out.append(f"loss.dist_schedule.iters={listed(recipe.loss.dist_schedule.iters)}")
    return out


def row_status(config: str, overrides: Sequence[str]) -> str:
    """``train``, or ``skipped: key not available (KEY)`` for overrides naming keys usl does not have."""
    try:
        load_config(config, overrides)
    except ConfigError:
        missing = [o.split("=", 1)[0] for o in overrides if _unknown_key(config, o)]
        if not missing:
            raise
        return f"skipped: key not available ({', '.join(missing)})"
    return "train"


def _unknown_key(config: str, override: str) -> bool:
    try:
        load_config(config, [override])
    except ConfigError as exc:
        return "unknown key" in str(exc)
    return False


def measured_seconds_per_iter(out: Path, row: Row, iters: int) -> float:
    """CPU seconds per iteration of this row's finished runs in ``out`` (table1.sh's
    ``train_time.txt``: wall and user CPU seconds of the run's last invocation, then the iterations
    it trained; without them, all ``iters``), else the measured constant."""
    rates = []
    for path in sorted((out / "runs" / row.slug).glob("seed*/train_time.txt")):
        fields = path.read_text().split()
        if len(fields) in (2, 3):
            trained = float(fields[2]) if len(fields) == 3 else iters
            if trained > 0:
                rates.append(float(fields[1]) / trained)
    return statistics.fmean(rates) if rates else MEASURED_SECONDS_PER_ITER[row.slug]


def heldout_input_views(scenes: int) -> int:
    """Input views of one held-out build's train split: its scenes as the builder splits them, every view."""
    splits = load_dataset_spec("scene_shapes")["splits"]
    return split_counts(scenes, list(splits.values()))[list(splits).index("train")] * VIEWS_PER_SCENE


def duration(seconds: float) -> str:
    minutes = round(seconds / 60)
    return f"{minutes // 60} h {minutes % 60:02d} min" if minutes >= 60 else f"{max(minutes, 1)} min"


def recipe_digest(config: str, overrides: Sequence[str]) -> str:
    """Short sha256 of the resolved recipe: a folder's runs are only reused for the same recipe,
    not just the same recipe name (a recipe file edited since would mix two recipes in one table)."""
    return hashlib.sha256(dump_config(load_config(config, overrides)).encode()).hexdigest()[:16]


def check_budget(out: Path, stamp: str) -> None:
    """Refuse an output folder whose runs were made with another budget (seeds may be added)."""
    path = out / "budget.txt"
    if path.is_file() and path.read_text() != stamp:
        old = path.read_text().strip().replace("\n", "; ")
        raise ValueError(f"{out} holds runs of another budget ({old}); give the same options or another --out")
    out.mkdir(parents=True, exist_ok=True)
    path.write_text(stamp)


def plan(
    config: str,
    iters: int | None,
    seeds: Sequence[int],
    jobs: int,
    out: Path,
    extra: Sequence[str] = (),
    data: str = "",
    heldout_builds: int = 3,
    heldout_scenes: int = 20,
) -> str:
    """Write ``out/plan.tsv``; return the budget text to print. ``data``: the builds and the
    evaluation protocol, recorded with the budget; each run is scored by one usl-eval per held-out
    build (``heldout_builds`` of ``heldout_scenes`` scenes: the main job's by default)."""
    eval_views = heldout_builds * heldout_input_views(heldout_scenes)
    # one usl-eval start-up per build; training start-up is in the rates
    per_run = heldout_builds * EVAL_START_SECONDS + eval_views * EVAL_SECONDS_PER_VIEW
    recipe = load_config(config)
    iters = iters or recipe.optim.max_iter
    budget = budget_overrides(recipe, iters) + list(extra)
    check_budget(
        out,
        f"config={config} (resolved sha256 {recipe_digest(config, budget)})\noverrides={' '.join(budget)}\n{data}\n",
    )
    lines, trained, cost, rates, runs_left = [], [], 0.0, [], 0
    scored = set(finished(out))
    for row in TRAINED:
        overrides = budget + list(row.overrides)
        status = row_status(config, overrides)
        lines.append("\t".join([row.slug, row.label, status, " ".join(overrides)]))
        if status == "train":
            trained.append(row)
            rate = measured_seconds_per_iter(out, row, iters)
            rates.append(f"{row.slug} {rate:.2f}")
            left = [s for s in seeds if f"runs/{row.slug}/seed{s}" not in scored]
            runs_left += len(left)
            cost += len(left) * (iters * rate + per_run)
    (out / "plan.tsv").write_text("\n".join(lines) + "\n")
    runs = len(trained) * len(seeds)
    skipped = [
        f"{label}: {status}" for _, label, status, _ in (line.split("\t") for line in lines) if status != "train"
    ]
    text = [
        f"budget: {len(trained)} trained rows x {len(seeds)} seeds ({', '.join(map(str, seeds))}) = {runs} runs of "
        f"{iters} iterations ({runs * iters:,} in all), recipe {config}, {jobs} at a time with 1 thread each",
        f"  overrides of every run: {' '.join(budget)}",
        f"  seconds per iteration: {', '.join(rates) or '-'} (measured, see scripts/experiments/table1_plan.py), "
        f"plus ~{per_run:.0f} s per run for scoring {eval_views} held-out input views ({heldout_builds} builds, every input view)",
        f"  estimated time: {duration(cost / max(jobs, 1))} on {jobs} idle cores for the {runs_left} runs not scored yet "
        "(builds not counted)"
        if runs_left
        else "  estimated time: none, every run is scored",
    ]
    text += [f"  {s}" for s in skipped]
    return "\n".join(text)


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", default="tiny", help="usl-train recipe")
    p.add_argument("--iters", type=int, help="iterations per run (default: the recipe's optim.max_iter)")
    p.add_argument("--seeds", default="0,1,2", help="comma-separated train.seed values")
    p.add_argument("--jobs", type=int, default=2, help="runs trained side by side")
    p.add_argument("--out", required=True, help="the table's output folder")
    p.add_argument("--data", default="", help="the builds and evaluation protocol, recorded with the budget")
    p.add_argument("--heldout-builds", type=int, default=3, help="held-out builds each run is scored on")
    p.add_argument("--heldout-scenes", type=int, default=20, help="scenes of each held-out build")
    p.add_argument("extra", nargs="*", metavar="key=value", help="more overrides for every run")
    args = p.parse_args(argv)
    try:
        print(
            plan(
                args.config,
                args.iters,
                [int(s) for s in args.seeds.split(",")],
                args.jobs,
                Path(args.out),
                args.extra,
                args.data,
                args.heldout_builds,
                args.heldout_scenes,
            )
        )
    except (ConfigError, ValueError) as exc:
        print(f"table1_plan: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
