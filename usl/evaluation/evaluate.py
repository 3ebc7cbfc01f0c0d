"""The evaluation behind ``usl-eval`` (command line: ``usl.cli.evaluate``): every predictor on
the input views of a split, scene by scene, into per-object rows, summaries and pictures.

The metric definitions are in ``usl.evaluation.render`` (pairs), ``scene`` (one scene's rows),
``summary`` (aggregation), ``views`` (which views), ``detection`` (matching, AP) and ``baselines``;
the table rows' predictors in ``rows``; the pictures in ``pictures`` and their choice and index in
``gallery``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from tqdm import tqdm

from data_specs import DATASETS, load_dataset_spec
from usl.data.frames import CategoryIndex
from usl.errors import UslError
from usl.evaluation.detection import CocoDetections
from usl.evaluation.gallery import Gallery
from usl.evaluation.report import choose_layout
from usl.evaluation.scene import EvalConfig, evaluate_scene
from usl.evaluation.summary import DetectionCounts, PredictorSummary, summarize
from usl.evaluation.types import Predictor
from usl.evaluation.views import view_selection
from usl.records import RecordsDataset


@dataclass
class EvalRun:
    header: dict[str, Any]
    summaries: list[PredictorSummary]
    rows: list[dict[str, Any]]
    layout: str
    pictures_index: Path | None = None


def dataset_spec(manifest: dict[str, Any]) -> dict[str, Any]:
    """The dataset's spec (data_specs, when it is a known dataset) overlaid with the manifest's own facts."""
    base = dict(load_dataset_spec(manifest["name"])) if manifest.get("name") in DATASETS else {}
    return {
        **base,
        **{k: v for k, v in manifest.items() if k in ("name", "categories", "layout") or (k == "baselines" and v)},
    }


def run_evaluation(
    root: str | Path,
    split: str,
    predictors: Sequence[Predictor],
    config: EvalConfig,
    scene_ids: Sequence[str] | None = None,
    max_scenes: int | None = None,
    pictures_dir: str | Path | None = None,
    num_pictures: int = 0,
    table_layout: str = "auto",
    progress: bool = True,
    pictures_by: str = "spread",
    picture_score: float = 0.5,
) -> EvalRun:
    """Evaluate ``predictors`` on a split; ``num_pictures`` input views chosen ``pictures_by`` (see
    ``usl.evaluation.gallery``) are drawn into ``pictures_dir`` with an ``index.md``."""
    names = [p.name for p in predictors]
    if len(set(names)) != len(names):
        raise UslError(f"predictor names must be unique, got {names}")
    dataset = RecordsDataset(root, split)
    categories = CategoryIndex(dataset.categories)
    spec = dataset_spec(dataset.manifest)
    selection = view_selection(config.other_views, spec)
    scenes = list(scene_ids) if scene_ids else list(dataset.scene_ids)
    missing = [s for s in scenes if s not in dataset.locations]
    if missing:
        raise UslError(f"{root}: split {split!r} has no scene(s) {missing[:5]}")
    scenes = scenes[:max_scenes] if max_scenes else scenes
    if not scenes:
        raise UslError(f"{root}: split {split!r} has no scenes to evaluate")
    coco = {
        p: CocoDetections(categories.ids, categories.names) for p, pr in enumerate(predictors) if pr.uses_detections
    }
    counts = {pr.name: DetectionCounts() for pr in predictors if pr.uses_detections}
    rows: list[dict[str, Any]] = []
    num_inputs = 0
    gallery = Gallery(
        Path(pictures_dir or "."),
        num_pictures if pictures_dir else 0,
        pictures_by,
        predictors,
        categories,
        picture_score,
    )
    gallery.start(len(scenes))
    bar = tqdm(scenes, desc=f"evaluating {dataset.manifest['name']}/{split}", unit="scene", disable=not progress)
    for scene_index, scene_id in enumerate(bar):
        outcome = evaluate_scene(dataset, scene_id, predictors, categories, selection, config, coco)
        rows += outcome.rows
        num_inputs += len(outcome.inputs)
        for pr in outcome.predictions:
            if predictors[pr.predictor].uses_detections:
                frame = outcome.inputs[pr.inp].frame
                matched = int((pr.pred.instance_ids >= 0).sum())
                counts[predictors[pr.predictor].name].add(len(frame.instance_ids), len(pr.pred), matched)
        gallery.scene_done(dataset, scene_index, outcome)
    if not rows:
        raise UslError(f"{root}: split {split!r}: none of its {num_inputs} input view(s) has an object to evaluate")
    gallery.finish(dataset, rows, selection, config)
    average_precision = {predictors[p].name: c.evaluate() for p, c in coco.items()}
    summaries = summarize(predictors, rows, counts, average_precision)
    header = {
        "dataset": dataset.manifest["name"],
        "root": str(root),
        "split": split,
        "num_scenes": len(scenes),
        "num_input_views": num_inputs,
        "config": asdict(config),
    }
    layout = choose_layout(header["dataset"], summaries) if table_layout == "auto" else table_layout
    return EvalRun(header, summaries, rows, layout, gallery.write_index(rows))
