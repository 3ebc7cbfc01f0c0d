"""``usl-eval``: every metric of the paper (Sec. 4) for the model and the baselines on one split.

    usl-eval DATA --split val --checkpoint runs/tiny --out eval/ --rows random,fixed,model,detections
    usl-eval DATA --checkpoint runs/hs --input-views first --max-scenes 20 --pictures 8 --pictures-by extremes
    usl-eval DATA --checkpoint runs/meshrcnn --rows model    # a loss.supervision=3d run: "Mesh R-CNN (3D sup.)"

Writes ``metrics.json`` (per-predictor means and counts, configuration, the checkpoint scored), ``objects.jsonl`` (every
scored object, for re-aggregation), ``table.md`` (the paper's table layout for the dataset, with
links to the pictures and to the training run's ``curves.png``) and ``pictures/`` with
``pictures/index.md`` (each picture with its objects' lines in ``objects.jsonl``).
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence
from pathlib import Path

from usl.cli.common import common_options, make_parser, resolve_device, warning_lines
from usl.evaluation.baseline_options import DEFAULT_SPHERE_LEVEL, TRUE_DEPTH_SOURCES
from usl.evaluation.choices import PICTURE_SELECTIONS, ROWS
from usl.evaluation.report import TABLE_LAYOUTS  # torch-free, like everything imported here

COMMAND = "usl-eval"


def parser() -> argparse.ArgumentParser:
    common = common_options(
        out="output folder",
        out_default="eval",
        device="where the model runs (auto: cuda when available)",
        seed="seed of the random baselines and of the 3D point sampling",
        quiet="no progress bar",
    )
    p = make_parser(COMMAND, __doc__, parents=[common])
    p.add_argument("root", help="dataset folder (records with manifest.json)")
    p.add_argument("--split", default="val", help="split to evaluate")
    p.add_argument(
        "--checkpoint",
        help="trained model checkpoint or run folder (its newest checkpoint; needed by the "
        "model rows); its file and iteration are recorded in metrics.json and table.md",
    )
    p.add_argument(
        "--model-name",
        help="label of the model rows (default: how the checkpoint was trained: 'USL', or "
        "'Mesh R-CNN (3D sup.)' for loss.supervision=3d); derived rows add to it, e.g. 'NAME w/ detections'",
    )
    p.add_argument(
        "--rows",
        help=f"comma-separated table rows from {', '.join(ROWS)} "
        "(default: random,fixed, plus model,layout_only with --checkpoint)",
    )
    p.add_argument(
        "--input-views",
        default="all",
        help="input views per scene: all (the paper's protocol) | first | every:K | positions:P1,P2",
    )
    p.add_argument(
        "--other-views",
        default="auto",
        help="views scoring each object: all | furthest:F | auto (ScanNet spec: furthest 20%%)",
    )
    p.add_argument("--scenes", help="comma-separated scene ids (default: all scenes of the split)")
    p.add_argument("--max-scenes", type=int, help="evaluate only the first N scenes")
    p.add_argument(
        "--no-occlusion", action="store_true", help="render each object alone instead of all objects together"
    )
    p.add_argument(
        "--true-depth-source",
        default="auto",
        choices=TRUE_DEPTH_SOURCES,
        help="the true depth the 'w/ true depth' rows use",
    )
    p.add_argument(
        "--sphere-level", type=int, default=DEFAULT_SPHERE_LEVEL, help="ico-sphere level of sphere baselines"
    )
    p.add_argument("--samples-3d", type=int, default=10_000, help="points sampled per mesh for Chamfer / F1")
    p.add_argument("--f1-threshold", type=float, default=0.1, help="F1 distance threshold in metres")
    p.add_argument("--match-iou", type=float, default=0.5, help="box IoU matching detections to true objects")
    p.add_argument(
        "--occluder-score",
        type=float,
        default=0.5,
        help="detections scoring at least this occlude each other in the masks for segm AP",
    )
    p.add_argument("--pictures", type=int, default=4, help="input views to draw (each for every predictor)")
    p.add_argument(
        "--pictures-by",
        default="spread",
        choices=PICTURE_SELECTIONS,
        help="spread: evenly over the scenes; extremes: the worst and best half by Mask IoU (views) of the first row",
    )
    p.add_argument(
        "--picture-score", type=float, default=0.5, help="detections drawn in the pictures score at least this"
    )
    p.add_argument(
        "--table-layout",
        default="auto",
        choices=("auto",) + TABLE_LAYOUTS,
        help="which paper table to lay the results out like (auto: the dataset's)",
    )
    p.add_argument("--views-per-chunk", type=int, default=8, help="views decoded and rendered together (memory)")
    p.add_argument("--batch-size", type=int, default=4, help="input views per predictor call")
    return p


def training_curves(checkpoint: str | None, out: Path) -> str | None:
    """The checkpoint's run folder's ``curves.png``, relative to ``out``, when it exists."""
    if not checkpoint:
        return None
    from usl.engine.checkpoint import CheckpointError, resolve_checkpoint
    from usl.engine.curves import CURVES_NAME

    try:
        run_dir = resolve_checkpoint(checkpoint).parent.parent
    except CheckpointError:
        return None
    curves = run_dir / CURVES_NAME
    return os.path.relpath(curves.resolve(), out.resolve()) if curves.is_file() else None


def main(argv: Sequence[str] | None = None) -> int:
    args = parser().parse_args(argv)
    args.device = resolve_device(args.device)  # torch loads from here on
    from usl.errors import UslError
    from usl.records.output_folder import output_folder

    try:
        kept = "the results of earlier runs there are kept as they were"
        with warning_lines(COMMAND), output_folder(Path(args.out), COMMAND, kept):
            paths = evaluate(args)
    except UslError as exc:
        print(f"{COMMAND}: error: {exc}", file=sys.stderr)
        return 2
    print(paths["table"].read_text())
    print(f"wrote {', '.join(str(p) for p in paths.values())}")
    return 0


def evaluate(args: argparse.Namespace) -> dict[str, Path]:
    """Score the predictors the arguments ask for and write the report; its files."""
    from usl.evaluation.evaluate import dataset_spec, run_evaluation
    from usl.evaluation.report import write_report
    from usl.evaluation.rows import RowOptions, build_predictors
    from usl.evaluation.scene import EvalConfig
    from usl.records import RecordsDataset

    dataset = RecordsDataset(args.root, args.split)
    rows = RowOptions(
        rows=tuple(r.strip() for r in args.rows.split(",") if r.strip()) if args.rows else None,
        checkpoint=args.checkpoint,
        model_name=args.model_name,
        device=args.device,
        seed=args.seed,
        sphere_level=args.sphere_level,
        true_depth_source=args.true_depth_source,
    )
    predictors, scored = build_predictors(rows, dataset_spec(dataset.manifest))
    config = EvalConfig(
        input_views=args.input_views,
        other_views=args.other_views,
        occlusion=not args.no_occlusion,
        match_iou=args.match_iou,
        occluder_score=args.occluder_score,
        num_samples_3d=args.samples_3d,
        f1_threshold=args.f1_threshold,
        views_per_chunk=args.views_per_chunk,
        batch_size=args.batch_size,
        seed=args.seed,
        device=args.device,
    )
    out = Path(args.out)
    run = run_evaluation(
        args.root,
        args.split,
        predictors,
        config,
        scene_ids=args.scenes.split(",") if args.scenes else None,
        max_scenes=args.max_scenes,
        pictures_dir=out / "pictures",
        num_pictures=args.pictures,
        table_layout=args.table_layout,
        progress=not args.quiet,
        pictures_by=args.pictures_by,
        picture_score=args.picture_score,
    )
    links = {
        "pictures": os.path.relpath(run.pictures_index, out) if run.pictures_index else None,
        "training curves": training_curves(args.checkpoint, out),
    }
    header = {**run.header, "checkpoint": scored}
    return write_report(out, header, run.summaries, run.rows, run.layout, {k: v for k, v in links.items() if v})


if __name__ == "__main__":
    sys.exit(main())
