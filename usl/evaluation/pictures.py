"""One picture per (input view, predictor) of an evaluation run.

Top row: the input with boxes and category names, the predicted meshes rendered over it, the
bird's-eye layout with every camera of the scene, and a legend (each object's colour, category,
score for detectors, and its Mask IoU in the input and other views from ``objects.jsonl``).
Bottom row: for a few other views (evenly spread over the scene), the true masks of the predicted
instances next to the rendered predictions. Detections are drawn from ``score_threshold`` up; when
none reaches it, the picture says so (and gives the best score) instead of showing empty panels.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch

from usl.data.frames import CategoryIndex, decode_frame
from usl.evaluation.types import EvalInput
from usl.geometry.cameras import relative_transform, transform_points
from usl.model.outputs import ObjectPredictions
from usl.records import RecordsDataset
from usl.vis.visualize import (
    GRAY,
    birds_eye,
    compose_rows,
    draw_boxes,
    label,
    legend,
    mask_pair,
    palette,
    render_meshes,
    render_overlay,
    to_uint8,
)


def spread_positions(num_views: int, exclude: int, count: int) -> list[int]:
    """Up to ``count`` positions evenly spread over the scene, leaving out ``exclude``."""
    others = [p for p in range(num_views) if p != exclude]
    if len(others) <= count:
        return others
    return [others[int(round(i))] for i in np.linspace(0, len(others) - 1, count)]


def _legend_line(name: str, score: float | None, row: Mapping[str, Any] | None, matched: bool) -> str:
    text = name + (f" {score:.2f}" if score is not None else "")
    if row is not None:
        views = row.get("mask_iou_views")
        views_text = "-" if views is None or views != views else f"{views:.2f}"
        return f"{text}: Mask IoU input {row['mask_iou_input']:.2f}, views {views_text}"
    return text + ("" if matched else ": no true object matched")


def evaluation_picture(
    dataset: RecordsDataset,
    inp: EvalInput,
    position: int,
    pred: ObjectPredictions,
    title: str,
    categories: CategoryIndex,
    all_poses: Sequence[torch.Tensor],
    rows: Mapping[int, Mapping[str, Any]],
    uses_detections: bool = False,
    score_threshold: float = 0.5,
    num_views: int = 3,
) -> np.ndarray:
    """The picture of one prediction; ``rows``: instance id -> its ``objects.jsonl`` row.

    Images are read again (the evaluator keeps no pixels)."""
    source = dataset.source(inp.frame.scene_id)
    frame = decode_frame(
        dataset.read_scene(inp.frame.scene_id, views=[position])[0], categories, with_image=True, source=source
    )
    pred = pred.to("cpu")
    best = float(pred.scores.max()) if len(pred) else None
    if uses_detections:
        pred = pred.select(pred.scores >= score_threshold)
    colors = palette(len(pred))
    image = to_uint8(frame.image)
    scores = pred.scores.tolist() if uses_detections else [None] * len(pred)
    names = [categories.names[int(l)] for l in pred.labels.tolist()]
    texts = [n + (f" {s:.2f}" if s is not None else "") for n, s in zip(names, scores, strict=True)]
    overlay = render_overlay(image, pred.verts, pred.faces, frame.K, colors)
    if not len(pred):
        found = "no detection at all" if best is None else f"best score {best:.2f}"
        overlay = label(overlay, f"no detection >= {score_threshold:g} ({found})" if uses_detections else "no objects")
    order = [position] + [k for k in range(len(all_poses)) if k != position]  # the input camera first
    cameras = [relative_transform(all_poses[k], frame.cam_to_world) for k in order]
    truth = [inp.true_meshes[i].verts for i in pred.instance_ids.tolist() if i in inp.true_meshes]
    ids = pred.instance_ids.tolist()
    key = [(c, _legend_line(n, s, rows.get(i), i >= 0)) for c, n, s, i in zip(colors, names, scores, ids, strict=True)]
    notes = [
        (None, f"{frame.scene_id}, view {frame.view_id}"),
        (None, "panels: input + boxes | prediction | top view (white: truth)"),
        (None, "below: true masks | prediction, in other views"),
    ]
    if uses_detections:
        notes.append((None, f"detections scoring >= {score_threshold:g}"))
    top = [
        label(draw_boxes(image, pred.boxes, texts, colors), title),
        overlay,
        birds_eye(pred.verts, colors, truth, cameras),
        legend(notes + key, title=title),
    ]

    bottom = []
    positions = spread_positions(dataset.num_views(frame.scene_id), position, num_views) if len(pred) else []
    color_of = {int(i): colors[n] for n, i in enumerate(ids) if i >= 0}
    for row in dataset.read_scene(frame.scene_id, views=positions) if positions else []:
        view = decode_frame(row, categories, with_image=True, source=source)
        keep = [n for n, i in enumerate(view.instance_ids.tolist()) if i in color_of]
        verts = transform_points(pred.verts.double(), relative_transform(frame.cam_to_world, view.cam_to_world)).float()
        height, width = view.size
        rendered = render_meshes(verts, pred.faces, view.K, height, width).masks.numpy()
        panel = mask_pair(
            to_uint8(view.image),
            view.masks[keep].numpy(),
            [color_of.get(int(view.instance_ids[n]), GRAY) for n in keep],
            rendered,
            colors,
            title=f"view {view.view_id}:",
        )
        bottom.append(panel)
    return compose_rows([top] + ([bottom] if bottom else []))
