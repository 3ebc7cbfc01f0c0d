"""The table rows ``usl-eval`` scores: a registry from each row's name to the builder of its predictor,
and the typed options the builders read (``usl.cli.evaluate`` fills them once from its arguments).

``usl.evaluation.choices.ROWS`` lists the same names in the same order without importing torch, for
``--help``. A builder takes the row's :class:`Sources`, so the checkpoint is loaded once, and only
when a row asks for it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from typing import Any

from usl.errors import UslError
from usl.evaluation.baseline_options import DEFAULT_SPHERE_LEVEL
from usl.evaluation.baselines import FixedDepthBaseline, LayoutOnly, TrueDepth, spec_baselines
from usl.evaluation.choices import ROWS
from usl.evaluation.types import Predictor

DEFAULT_ROWS = ("random", "fixed")  # without --rows; a checkpoint adds MODEL_DEFAULT_ROWS
MODEL_DEFAULT_ROWS = ("model", "layout_only")


@dataclass(frozen=True)
class RowOptions:
    """What the rows are built from: ``usl-eval``'s options of the same names."""

    rows: tuple[str, ...] | None = None  # rows in table order; None: DEFAULT_ROWS (and MODEL_DEFAULT_ROWS)
    checkpoint: str | None = None  # trained model checkpoint or run folder, which the model rows score
    model_name: str | None = None  # label of the model rows (None: how the checkpoint was trained)
    device: str = "cpu"  # where the model runs
    seed: int = 0  # seed of the random-depth baseline
    sphere_level: int = DEFAULT_SPHERE_LEVEL  # ico-sphere level of the sphere baselines
    true_depth_source: str = "auto"  # where the "w/ true depth" rows read an object's depth


@dataclass
class Sources:
    """What the rows' predictors are made of: the options, the dataset's sphere baselines and, when a
    row needs it, the checkpoint's model with true boxes and with its own detections."""

    options: RowOptions
    baselines: dict[str, Predictor]
    model: Predictor | None = None
    detections: Predictor | None = None


@dataclass(frozen=True)
class Row:
    """A table row: the builder of its predictor and what the builder needs."""

    build: Callable[[Sources], Predictor]
    needs_model: bool = False  # a checkpoint
    baseline: str | None = None  # the dataset spec's ``<baseline>_depth`` parameters


def _layout_only(sources: Sources) -> Predictor:
    model = sources.model
    return LayoutOnly(model, level=sources.options.sphere_level, name=f"Layout-only ({model.name})")


def _sphere_true_layout(sources: Sources, extent: bool) -> Predictor:
    fixed = sources.baselines["fixed"]
    sphere = FixedDepthBaseline(fixed.z, fixed.rho, level=sources.options.sphere_level, name="Sphere-only")
    return TrueDepth(sphere, sources.options.true_depth_source, extent=extent)


ROW_BUILDERS: dict[str, Row] = {
    "random": Row(lambda sources: sources.baselines["random"], baseline="random"),
    "fixed": Row(lambda sources: sources.baselines["fixed"], baseline="fixed"),
    "model": Row(lambda sources: sources.model, needs_model=True),
    "detections": Row(lambda sources: sources.detections, needs_model=True),
    "layout_only": Row(_layout_only, needs_model=True),
    "sphere_true_depth": Row(partial(_sphere_true_layout, extent=False), baseline="fixed"),
    "model_true_depth": Row(
        lambda sources: TrueDepth(sources.model, sources.options.true_depth_source), needs_model=True
    ),
    # the whole layout true (depth and extent, objects with a true mesh): what is left is the shape
    "sphere_true_layout": Row(partial(_sphere_true_layout, extent=True), baseline="fixed"),
    "model_true_layout": Row(
        lambda sources: TrueDepth(sources.model, sources.options.true_depth_source, extent=True), needs_model=True
    ),
}


def build_predictors(options: RowOptions, spec: dict[str, Any]) -> tuple[list[Predictor], dict[str, Any] | None]:
    """The rows ``options`` ask for, in their order (each once), and the checkpoint the model rows
    score (path, iteration, supervision, row name; None without model rows)."""
    wanted = (
        list(options.rows)
        if options.rows is not None
        else [*DEFAULT_ROWS, *(MODEL_DEFAULT_ROWS if options.checkpoint else ())]
    )
    unknown = [name for name in wanted if name not in ROW_BUILDERS]
    if unknown:
        raise UslError(f"--rows: unknown row(s) {unknown}; choose from {', '.join(ROWS)}")
    needs_model = [name for name in wanted if ROW_BUILDERS[name].needs_model]
    if needs_model and not options.checkpoint:
        raise UslError(f"--rows {','.join(needs_model)} need a --checkpoint")
    sources = Sources(
        options, spec_baselines(spec.get("baselines") or {}, seed=options.seed, level=options.sphere_level)
    )
    for name, row in ROW_BUILDERS.items():
        if name in wanted and row.baseline is not None and row.baseline not in sources.baselines:
            raise UslError(
                f"--rows {name}: the dataset spec of {spec.get('name')!r} has no {row.baseline}_depth baseline parameters"
            )
    scored = None
    if needs_model:
        from usl.evaluation.model import model_predictors  # imports the model only when it is used

        sources.model, sources.detections, scored = model_predictors(
            options.checkpoint, options.device, [c["name"] for c in spec["categories"]], options.model_name
        )
    made = {name: ROW_BUILDERS[name].build(sources) for name in wanted}
    return list(made.values()), scored
