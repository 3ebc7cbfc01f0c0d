"""Ground truth for evaluation, decoded lazily from record rows.

Masks of other views are decoded only for the instances that are scored there and only for the
views of the chunk being evaluated: a Hypersim scene has ~100 views x ~50 instances of
1024x768 masks, far too many to hold at once.
"""

from __future__ import annotations

from collections.abc import Collection, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from usl.data.true_meshes import true_meshes_in_camera  # noqa: F401  (re-exported for evaluation)
from usl.records import decode_mask, decoding, frame_K, frame_pose
from usl.utils.transfer import to_device

Tensor = torch.Tensor

# Columns needed to know a scene's cameras and who is visible where (no image, no depth map).
META_COLUMNS = ("scene_id", "view_id", "height", "width", "K", "cam_to_world", "instances")


@dataclass
class ViewTargets:
    """One view's cameras and the 2D ground truth of the instances scored in it."""

    position: int  # within the scene
    view_id: int
    K: Tensor  # (3, 3) float32
    cam_to_world: Tensor  # (4, 4) float64
    height: int
    width: int
    instance_ids: Tensor  # (n,) int64
    masks: Tensor  # (n, H, W) bool
    boxes: Tensor  # (n, 4) float32 xyxy
    depth_min: Tensor  # (n,) float32, NaN unknown

    def index_of(self) -> dict[int, int]:
        return {int(i): n for n, i in enumerate(self.instance_ids.tolist())}


def decode_view_targets(
    row: dict[str, Any], position: int, wanted: Collection[int] | None = None, device: torch.device | str = "cpu"
) -> ViewTargets:
    """Decode a frames row's camera and the instances in ``wanted`` (all when None)."""
    height, width = int(row["height"]), int(row["width"])
    instances = [i for i in (row["instances"] or []) if wanted is None or int(i["instance_id"]) in wanted]
    with decoding(row):
        masks = (
            torch.from_numpy(np.stack([decode_mask(i["mask"]) for i in instances]))
            if instances
            else torch.zeros(0, height, width, dtype=torch.bool)
        )
    return ViewTargets(
        position=position,
        view_id=int(row["view_id"]),
        K=to_device(frame_K(row), device, torch.float32),
        cam_to_world=to_device(frame_pose(row), device),
        height=height,
        width=width,
        instance_ids=to_device([int(i["instance_id"]) for i in instances], device, torch.int64),
        masks=to_device(masks, device),
        boxes=to_device([list(i["box_xyxy"]) for i in instances], device, torch.float32).reshape(-1, 4),
        depth_min=to_device([float(i["depth_min"]) for i in instances], device, torch.float32),
    )


def presence(rows: Sequence[dict[str, Any]]) -> dict[int, list[int]]:
    """Instance id -> positions of the views in which it is visible (has a mask)."""
    out: dict[int, list[int]] = {}
    for position, row in enumerate(rows):
        for inst in row["instances"] or []:
            out.setdefault(int(inst["instance_id"]), []).append(position)
    return out
