"""One picture per (input view, predictor) of an evaluation run.

Top row: the input with boxes and category names, the predicted meshes rendered over it, and the
bird's-eye layout with every camera of the scene. Bottom row: for a few other views (evenly spread
over the scene), the true masks of the predicted instances next to the rendered predictions.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np
import torch

from usl.data.frames import CategoryIndex, decode_frame
from usl.engine.eval_types import EvalInput
from usl.engine.visualize import (
    GRAY, birds_eye, compose_rows, draw_boxes, label, mask_pair, palette, render_meshes, render_overlay, to_uint8,
)
from usl.geometry.cameras import relative_transform, transform_points
from usl.model.outputs import ObjectPredictions
from usl.records import RecordsDataset


def spread_positions(num_views: int, exclude: int, count: int) -> list[int]:
    """Up to ``count`` positions evenly spread over the scene, leaving out ``exclude``."""
    others = [p for p in range(num_views) if p != exclude]
    if len(others) <= count:
        return others
    return [others[int(round(i))] for i in np.linspace(0, len(others) - 1, count)]


def evaluation_picture(
    dataset: RecordsDataset, inp: EvalInput, position: int, pred: ObjectPredictions, title: str,
    categories: CategoryIndex, all_poses: Sequence[torch.Tensor], num_views: int = 3,
) -> np.ndarray:
    """The picture of one prediction; images are read again (the evaluator keeps no pixels)."""
    source = dataset.source(inp.frame.scene_id)
    frame = decode_frame(dataset.read_scene(inp.frame.scene_id, views=[position])[0], categories, with_image=True,
                         source=source)
    pred = pred.to("cpu")
    colors = palette(len(pred))
    image = to_uint8(frame.image)
    texts = [
        categories.names[int(l)] + (f" {float(s):.2f}" if float(s) < 1.0 else "")
        for l, s in zip(pred.labels.tolist(), pred.scores.tolist())
    ]
    overlay = render_overlay(image, pred.verts, pred.faces, frame.K, colors)
    order = [position] + [k for k in range(len(all_poses)) if k != position]  # the input camera first
    cameras = [relative_transform(all_poses[k], frame.cam_to_world) for k in order]
    truth = [inp.true_meshes[i].verts for i in pred.instance_ids.tolist() if i in inp.true_meshes]
    top = [label(draw_boxes(image, pred.boxes, texts, colors), title), overlay, birds_eye(pred.verts, colors, truth, cameras)]

    bottom = []
    positions = spread_positions(dataset.num_views(frame.scene_id), position, num_views)
    color_of = {int(i): colors[n] for n, i in enumerate(pred.instance_ids.tolist()) if i >= 0}
    for row in dataset.read_scene(frame.scene_id, views=positions):
        view = decode_frame(row, categories, with_image=True, source=source)
        keep = [n for n, i in enumerate(view.instance_ids.tolist()) if i in color_of]
        verts = transform_points(pred.verts.double(), relative_transform(frame.cam_to_world, view.cam_to_world)).float()
        height, width = view.size
        rendered = render_meshes(verts, pred.faces, view.K, height, width).masks.numpy() if len(pred) else np.zeros((0, height, width), bool)
        panel = mask_pair(
            to_uint8(view.image), view.masks[keep].numpy(), [color_of.get(int(view.instance_ids[n]), GRAY) for n in keep],
            rendered, colors, title=f"view {view.view_id}:",
        )
        bottom.append(panel)
    return compose_rows([top] + ([bottom] if bottom else []))
