"""Evaluation reports: metrics JSON, per-object JSON lines, and Markdown tables laid out like the paper's.

Table layouts (rows: predictors in evaluation order):
* ``scene_shapes`` (paper Table 1): Ch. (down), F1, Mask IoU input / views -- IoU in percent.
* ``hypersim`` (Table 2): Predicts layout / shape, Box gIoU, Mask IoU, Depth L1 (down), each input / views.
* ``scannet`` (ScanNet table): Predicts, Box gIoU and Mask IoU, input / views.
Predictors that detect their own objects add a detection table (COCO AP and AP50, box and mask).
Datasets with several categories add the same columns per true category (``category_table``).
"""

from __future__ import annotations

import json
import math
import re
import statistics
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from usl.evaluation.summary import PredictorSummary
from usl.records.atomic import write_text_atomic

TABLE_LAYOUTS = ("scene_shapes", "hypersim", "scannet")


@dataclass(frozen=True)
class Column:
    title: str
    metric: str
    scale: float
    decimals: int
    lower_is_better: bool = False  # errors (Chamfer, depth): tables that order rows compare these the other way


_BOX = [Column("Box gIoU input", "box_giou_input", 1, 2), Column("Box gIoU views", "box_giou_views", 1, 2)]
_MASK = [Column("Mask IoU input", "mask_iou_input", 1, 2), Column("Mask IoU views", "mask_iou_views", 1, 2)]
_DEPTH = [
    Column("Depth L1 ↓ input", "depth_l1_input", 1, 2, lower_is_better=True),
    Column("Depth L1 ↓ views", "depth_l1_views", 1, 2, lower_is_better=True),
]
COLUMNS: dict[str, list[Column]] = {
    "scene_shapes": [
        Column("Ch. ↓", "chamfer", 1, 3, lower_is_better=True),
        Column("F1@0.1", "f1", 1, 1),
        Column("Mask IoU input", "mask_iou_input", 100, 1),
        Column("Mask IoU views", "mask_iou_views", 100, 1),
    ],
    "hypersim": _BOX + _MASK + _DEPTH,
    "scannet": _BOX + _MASK,
}
_PREDICTS_COLUMNS = {"scene_shapes": False, "hypersim": True, "scannet": True}
_BUILD = re.compile(r"^seed(\d+)$")


def choose_layout(dataset_name: str, summaries: Sequence[PredictorSummary]) -> str:
    """The paper's table for this dataset; for other datasets, the richest one its metrics fill."""
    if dataset_name in TABLE_LAYOUTS:
        return dataset_name
    has = lambda metric: any(s.metrics.get(metric) is not None for s in summaries)  # noqa: E731
    if has("chamfer"):
        return "scene_shapes"
    return "hypersim" if has("depth_l1_input") else "scannet"


def _cell(value: float | None, column: Column) -> str:
    return "–" if value is None else f"{value * column.scale:.{column.decimals}f}"


def mean_std(values: Sequence[float]) -> tuple[float | None, float | None]:
    """Mean and sample std (ddof=1) of figures over runs or builds; None where there are too few."""
    mean = statistics.fmean(values) if values else None
    return mean, statistics.stdev(values) if len(values) > 1 else None


def mean_std_cell(values: Sequence[float], column: Column) -> str:
    """A column's cell for several runs or builds: the mean ± the sample std; one value alone, "–"
    for none (tables over seeds and held-out builds print figures as usl-eval does)."""
    mean, std = mean_std(values)
    return _cell(mean, column) if std is None else f"{_cell(mean, column)} ± {std * column.scale:.{column.decimals}f}"


def read_builds(folder: Path) -> dict[int, dict[str, Any]]:
    """seed -> usl-eval's metrics.json, for every ``seed<k>`` subfolder that has one: the reports of
    one model on held-out builds made with other ``--seed`` values, which tables summarise over."""
    builds = {}
    for sub in sorted(folder.iterdir()):
        match = _BUILD.match(sub.name)
        if match and (sub / "metrics.json").is_file():
            builds[int(match.group(1))] = json.loads((sub / "metrics.json").read_text())
    if not builds:
        raise ValueError(f"{folder}: no seed<k>/metrics.json (usl-eval --out {folder}/seed<k>)")
    return builds


def row_values(builds: Mapping[int, Mapping[str, Any]], columns: Sequence[Column]) -> dict[str, dict[str, list[float]]]:
    """predictor name -> metric -> its value on each build (in seed order)."""
    values: dict[str, dict[str, list[float]]] = {}
    for report in builds.values():
        for predictor in report["predictors"]:
            row = values.setdefault(predictor["name"], {c.metric: [] for c in columns})
            for c in columns:
                if predictor["metrics"].get(c.metric) is not None:
                    row[c.metric].append(predictor["metrics"][c.metric])
    return values


def builds_summary(
    builds: Mapping[int, Mapping[str, Any]], values: Mapping[str, Mapping[str, list[float]]]
) -> dict[str, Any]:
    """The figures over held-out builds as ``summary.json`` records them: each row's mean, sample
    std and per-build values, with the builds and the checkpoint scored (one format for every
    table over builds, so their readers share it)."""
    return {
        "seeds": list(builds),
        "num_input_views": {str(s): b["num_input_views"] for s, b in builds.items()},
        "checkpoint": next(iter(builds.values())).get("checkpoint"),
        "rows": {
            name: {
                metric: dict(zip(("mean", "std"), mean_std(v), strict=True), values=v) for metric, v in row.items() if v
            }
            for name, row in values.items()
        },
    }


def _markdown(header: list[str], rows: list[list[str]], align: list[str]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join(align) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def markdown_table(summaries: Sequence[PredictorSummary], layout: str) -> str:
    """The main results table (plus a detection table when a predictor detects its own objects)."""
    if layout not in COLUMNS:
        raise ValueError(f"unknown table layout {layout!r}; known: {', '.join(TABLE_LAYOUTS)}")
    columns = COLUMNS[layout]
    predicts = _PREDICTS_COLUMNS[layout]
    header = ["Model"] + (["Layout", "Shape"] if predicts else []) + [c.title for c in columns]
    rows = []
    for s in summaries:
        marks = [("✓" if s.predicts_layout else "✗"), ("✓" if s.predicts_shape else "✗")] if predicts else []
        rows.append([s.name] + marks + [_cell(s.metrics.get(c.metric), c) for c in columns])
    align = [":---"] + [":---:"] * (len(header) - 1)
    text = _markdown(header, rows, align)
    detectors = [s for s in summaries if s.uses_detections]
    if detectors:
        det_header = ["Model", "AP box", "AP50 box", "AP mask", "AP50 mask", "matched / true objects", "detections"]
        det_rows = [
            [s.name]
            + [f"{s.detection.get(k, 0.0):.1f}" for k in ("bbox/AP", "bbox/AP50", "segm/AP", "segm/AP50")]
            + [
                f"{s.detection.get('matched', 0)} / {s.detection.get('ground_truth', 0)}",
                str(s.detection.get("detections", 0)),
            ]
            for s in detectors
        ]
        text += "\n\n" + _markdown(det_header, det_rows, [":---"] + [":---:"] * 6)
    per_category = category_table(summaries, layout)
    return text + ("\n\nPer true category:\n\n" + per_category if per_category else "") + "\n"


def category_table(summaries: Sequence[PredictorSummary], layout: str) -> str:
    """The layout's columns per (predictor, true category), or "" when the objects are of one category."""
    names = sorted({name for s in summaries for name in s.categories})
    if len(names) < 2:
        return ""
    columns = COLUMNS[layout]
    rows = [
        [s.name, name, str(s.categories[name]["num_objects"])]
        + [_cell(s.categories[name]["metrics"].get(c.metric), c) for c in columns]
        for s in summaries
        for name in names
        if name in s.categories
    ]
    header = ["Model", "Category", "Objects"] + [c.title for c in columns]
    return _markdown(header, rows, [":---", ":---"] + [":---:"] * (len(header) - 2))


def json_safe(value: Any) -> Any:
    """NaN / inf become null so the file is strict JSON."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    return value


def checkpoint_line(scored: Mapping[str, Any] | None) -> str:
    """Which trained model the model rows score, so a table is never separated from its checkpoint."""
    if not scored:
        return ""
    return f"{scored['name']}: checkpoint `{scored['path']}`, iteration {scored['iteration']}\n\n"


def write_report(
    out_dir: str | Path,
    header: dict[str, Any],
    summaries: Sequence[PredictorSummary],
    rows: Sequence[dict[str, Any]],
    layout: str,
    links: Mapping[str, str] | None = None,
) -> dict[str, Path]:
    """Write ``metrics.json``, ``objects.jsonl`` and ``table.md`` into ``out_dir``; returns their paths.

    ``links``: title -> path relative to ``out_dir`` (pictures index, training curves), listed under
    the table and in ``metrics.json``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"metrics": out / "metrics.json", "objects": out / "objects.jsonl", "table": out / "table.md"}
    links = dict(links or {})
    document = {**header, "table_layout": layout, "links": links, "predictors": [s.as_dict() for s in summaries]}
    # Atomic, like every usl output: a full disk keeps the report of an earlier run whole.
    write_text_atomic(paths["metrics"], json.dumps(json_safe(document), indent=1) + "\n")
    write_text_atomic(paths["objects"], "".join(json.dumps(json_safe(row)) + "\n" for row in rows))
    title = f"# {header.get('dataset', 'dataset')} / {header.get('split', '')}: {header.get('num_input_views', 0)} input views\n\n"
    footer = "".join(f"\n{name.capitalize()}: [{target}]({target})\n" for name, target in links.items())
    write_text_atomic(
        paths["table"], title + checkpoint_line(header.get("checkpoint")) + markdown_table(summaries, layout) + footer
    )
    return paths
