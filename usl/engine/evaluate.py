"""``usl-eval``: every metric of the paper (Sec. 4) for the model and the baselines on one split.

    usl-eval DATA --split val --checkpoint run/model.pt --out eval/ --rows random,fixed,model,layout_only

Writes ``metrics.json`` (per-predictor means and counts, configuration), ``objects.jsonl`` (every
scored object, for re-aggregation), ``table.md`` (the paper's table layout for the dataset) and
``pictures/``. The metric definitions are in ``eval_render`` (pairs), ``eval_scene``
(aggregation), ``eval_views`` (which views), ``eval_detection`` (matching, AP) and ``baselines``.
"""
from __future__ import annotations

import argparse
import re
import sys
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Sequence

import torch
from tqdm import tqdm

from data_specs import DATASETS, load_dataset_spec
from usl.data.frames import CategoryIndex
from usl.engine.baselines import DEFAULT_SPHERE_LEVEL, TRUE_DEPTH_SOURCES, FixedDepthBaseline, LayoutOnly, TrueDepth, spec_baselines
from usl.engine.eval_detection import CocoDetections
from usl.engine.eval_pictures import evaluation_picture
from usl.engine.eval_scene import EvalConfig, SceneOutcome, evaluate_scene
from usl.engine.eval_summary import DetectionCounts, PredictorSummary, summarize
from usl.engine.eval_types import Predictor
from usl.engine.eval_views import view_selection
from usl.engine.report import TABLE_LAYOUTS, choose_layout, write_report
from usl.engine.visualize import write_png
from usl.records import RecordsDataset, UslError, frame_pose

ROWS = ("random", "fixed", "model", "detections", "layout_only", "sphere_true_depth", "model_true_depth")
MODEL_ROWS = ("model", "detections", "layout_only", "model_true_depth")


@dataclass
class EvalRun:
    header: dict[str, Any]
    summaries: list[PredictorSummary]
    rows: list[dict[str, Any]]
    layout: str


def dataset_spec(manifest: dict[str, Any]) -> dict[str, Any]:
    """The dataset's spec (data_specs, when it is a known dataset) overlaid with the manifest's own facts."""
    base = dict(load_dataset_spec(manifest["name"])) if manifest.get("name") in DATASETS else {}
    return {**base, **{k: v for k, v in manifest.items() if k in ("name", "categories", "layout") or (k == "baselines" and v)}}


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
) -> EvalRun:
    """Evaluate ``predictors`` on a split; pictures of the first ``num_pictures`` input views go to ``pictures_dir``."""
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
    coco = {p: CocoDetections(categories.ids, categories.names) for p, pr in enumerate(predictors) if pr.uses_detections}
    counts = {pr.name: DetectionCounts() for pr in predictors if pr.uses_detections}
    rows: list[dict[str, Any]] = []
    num_inputs, pictures_left = 0, num_pictures if pictures_dir else 0
    for scene_id in tqdm(scenes, desc=f"evaluating {dataset.manifest['name']}/{split}", unit="scene", disable=not progress):
        outcome = evaluate_scene(dataset, scene_id, predictors, categories, selection, config, coco)
        rows += outcome.rows
        num_inputs += len(outcome.inputs)
        for pr in outcome.predictions:
            if predictors[pr.predictor].uses_detections:
                frame = outcome.inputs[pr.inp].frame
                matched = int((pr.pred.instance_ids >= 0).sum())
                counts[predictors[pr.predictor].name].add(len(frame.instance_ids), len(pr.pred), matched)
        if pictures_left > 0:
            pictures_left -= _write_pictures(dataset, outcome, predictors, categories, Path(pictures_dir), pictures_left)
    if not rows:
        raise UslError(f"{root}: split {split!r}: none of its {num_inputs} input view(s) has an object to evaluate")
    average_precision = {predictors[p].name: c.evaluate() for p, c in coco.items()}
    summaries = summarize(predictors, rows, counts, average_precision)
    header = {
        "dataset": dataset.manifest["name"], "root": str(root), "split": split, "num_scenes": len(scenes),
        "num_input_views": num_inputs, "config": asdict(config),
    }
    layout = choose_layout(header["dataset"], summaries) if table_layout == "auto" else table_layout
    return EvalRun(header, summaries, rows, layout)


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", text).strip("_") or "x"


def _write_pictures(
    dataset: RecordsDataset, outcome: SceneOutcome, predictors: Sequence[Predictor], categories: CategoryIndex,
    out_dir: Path, limit: int,
) -> int:
    """Pictures for up to ``limit`` input views of this scene (one per predictor each); returns how many views."""
    if not outcome.inputs:
        return 0
    scene_id = outcome.inputs[0].frame.scene_id
    poses = [torch.from_numpy(frame_pose(r)) for r in dataset.read_scene(scene_id, columns=["cam_to_world"])]
    done = set()
    for pr in outcome.predictions:
        if pr.inp >= limit:
            continue
        inp, name = outcome.inputs[pr.inp], predictors[pr.predictor].name
        picture = evaluation_picture(dataset, inp, outcome.positions[pr.inp], pr.pred, name, categories, poses)
        write_png(out_dir / _slug(name) / f"{_slug(scene_id)}_view{inp.frame.view_id:05d}.png", picture)
        done.add(pr.inp)
    return len(done)


def build_predictors(args: argparse.Namespace, spec: dict[str, Any]) -> list[Predictor]:
    """The table rows asked for on the command line, in the paper's order."""
    wanted = [r.strip() for r in args.rows.split(",") if r.strip()] if args.rows else (
        ["random", "fixed"] + (["model", "layout_only"] if args.checkpoint else [])
    )
    unknown = [r for r in wanted if r not in ROWS]
    if unknown:
        raise UslError(f"--rows: unknown row(s) {unknown}; choose from {', '.join(ROWS)}")
    needs_model = [r for r in wanted if r in MODEL_ROWS]
    if needs_model and not args.checkpoint:
        raise UslError(f"--rows {','.join(needs_model)} need a --checkpoint")
    baselines = spec_baselines(spec.get("baselines") or {}, seed=args.seed, level=args.sphere_level)
    for row in ("random", "fixed", "sphere_true_depth"):
        key = "fixed" if row == "sphere_true_depth" else row
        if row in wanted and key not in baselines:
            raise UslError(f"--rows {row}: the dataset spec of {spec.get('name')!r} has no {key}_depth baseline parameters")
    model = detector = None
    if needs_model:
        from usl.engine.eval_model import model_predictors  # imports the model only when it is used

        model, detector = model_predictors(args.checkpoint, args.device, [c["name"] for c in spec["categories"]])
    made: dict[str, Predictor] = {}
    for row in wanted:
        if row in ("random", "fixed"):
            made[row] = baselines[row]
        elif row == "model":
            made[row] = model
        elif row == "detections":
            made[row] = detector
        elif row == "layout_only":
            made[row] = LayoutOnly(model, level=args.sphere_level, name=f"Layout-only ({model.name})")
        elif row == "sphere_true_depth":
            fixed = baselines["fixed"]
            sphere = FixedDepthBaseline(fixed.z, fixed.rho, level=args.sphere_level, name="Sphere-only")
            made[row] = TrueDepth(sphere, args.true_depth_source, name="Sphere-only w/ true depth")
        elif row == "model_true_depth":
            made[row] = TrueDepth(model, args.true_depth_source)
    return list(made.values())


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="usl-eval", description=__doc__.split("\n\n")[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("root", help="dataset folder (records with manifest.json)")
    p.add_argument("--split", default="val")
    p.add_argument("--checkpoint", help="trained model checkpoint (needed by the model rows)")
    p.add_argument("--rows", help=f"comma-separated table rows from {', '.join(ROWS)} "
                   "(default: random,fixed, plus model,layout_only with --checkpoint)")
    p.add_argument("--out", default="eval", help="output folder")
    p.add_argument("--input-views", default="all",
                   help="input views per scene: all (the paper's protocol) | first | every:K | positions:P1,P2")
    p.add_argument("--other-views", default="auto", help="views scoring each object: all | furthest:F | auto (ScanNet spec: furthest 20%%)")
    p.add_argument("--scenes", help="comma-separated scene ids (default: all scenes of the split)")
    p.add_argument("--max-scenes", type=int, help="evaluate only the first N scenes")
    p.add_argument("--no-occlusion", action="store_true", help="render each object alone instead of all objects together")
    p.add_argument("--true-depth-source", default="auto", choices=TRUE_DEPTH_SOURCES)
    p.add_argument("--sphere-level", type=int, default=DEFAULT_SPHERE_LEVEL, help="ico-sphere level of sphere baselines")
    p.add_argument("--samples-3d", type=int, default=10_000, help="points sampled per mesh for Chamfer / F1")
    p.add_argument("--f1-threshold", type=float, default=0.1, help="F1 distance threshold in metres")
    p.add_argument("--match-iou", type=float, default=0.5, help="box IoU matching detections to true objects")
    p.add_argument("--occluder-score", type=float, default=0.5,
                   help="detections scoring at least this occlude each other in the masks for segm AP")
    p.add_argument("--pictures", type=int, default=4, help="input views to draw (per predictor)")
    p.add_argument("--table-layout", default="auto", choices=("auto",) + TABLE_LAYOUTS)
    p.add_argument("--views-per-chunk", type=int, default=8)
    p.add_argument("--batch-size", type=int, default=4)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--quiet", action="store_true")
    return p.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        dataset = RecordsDataset(args.root, args.split)
        predictors = build_predictors(args, dataset_spec(dataset.manifest))
        config = EvalConfig(
            input_views=args.input_views, other_views=args.other_views, occlusion=not args.no_occlusion,
            match_iou=args.match_iou, occluder_score=args.occluder_score, num_samples_3d=args.samples_3d, f1_threshold=args.f1_threshold,
            views_per_chunk=args.views_per_chunk, batch_size=args.batch_size, seed=args.seed, device=args.device,
        )
        out = Path(args.out)
        run = run_evaluation(
            args.root, args.split, predictors, config,
            scene_ids=args.scenes.split(",") if args.scenes else None, max_scenes=args.max_scenes,
            pictures_dir=out / "pictures", num_pictures=args.pictures, table_layout=args.table_layout,
            progress=not args.quiet,
        )
        paths = write_report(out, run.header, run.summaries, run.rows, run.layout)
    except UslError as exc:
        print(f"usl-eval: error: {exc}", file=sys.stderr)
        return 2
    print(paths["table"].read_text())
    print(f"wrote {', '.join(str(p) for p in paths.values())}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
