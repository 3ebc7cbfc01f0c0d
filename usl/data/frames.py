"""Decoding one record row into tensors, shared by training, evaluation and visualisation.

Category ids in records are the dataset's own (data_specs); models work with contiguous indices
in the order of the spec's category list, so the mapping lives here, once.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np
import torch

from usl.records import decode_depth, decode_image, decode_mask, decoding, frame_K, frame_pose


class CategoryIndex:
    """Maps dataset category ids <-> contiguous class indices (spec order)."""

    def __init__(self, categories: Sequence[dict[str, Any]]):
        self.names = [c["name"] for c in categories]
        self.ids = [int(c["id"]) for c in categories]
        self._index = {cid: i for i, cid in enumerate(self.ids)}

    def __len__(self) -> int:
        return len(self.ids)

    def index(self, category_id: int) -> int:
        if category_id not in self._index:
            raise KeyError(f"category id {category_id} is not in the dataset spec ({self.ids})")
        return self._index[category_id]


@dataclass
class FrameData:
    """One view, decoded. Masks are full-image booleans, one per instance, in ``instance_ids`` order."""

    scene_id: str
    view_id: int
    image: torch.Tensor  # (3, H, W) float32 in [0, 1]
    K: torch.Tensor  # (3, 3) float32
    cam_to_world: torch.Tensor  # (4, 4) float64: poses compose in float64, results go to float32
    instance_ids: torch.Tensor  # (N,) int64
    labels: torch.Tensor  # (N,) int64 contiguous category index
    boxes: torch.Tensor  # (N, 4) float32 xyxy pixel frame
    masks: torch.Tensor  # (N, H, W) bool
    depth_min: torch.Tensor  # (N,) float32, NaN when unknown
    depth: torch.Tensor | None = None  # (H, W) float32 metres, NaN unknown

    @property
    def size(self) -> tuple[int, int]:
        return int(self.image.shape[1]), int(self.image.shape[2])


def decode_frame(
    row: dict[str, Any], categories: CategoryIndex, with_image: bool = True, with_depth: bool = False,
    source: str = "",
) -> FrameData:
    """Decode a frames-table row (as returned by ``RecordsDataset.read_scene``); errors name ``source``
    (the shard, ``RecordsDataset.source``), the scene and the view."""
    with decoding(row, source):
        return _decode_frame(row, categories, with_image, with_depth)


def _decode_frame(row: dict[str, Any], categories: CategoryIndex, with_image: bool, with_depth: bool) -> FrameData:
    height, width = int(row["height"]), int(row["width"])
    if with_image:
        image = torch.from_numpy(decode_image(row["image"])).permute(2, 0, 1).float().div_(255.0)
    else:
        image = torch.zeros(3, height, width)
    instances = row["instances"] or []
    masks = (
        torch.from_numpy(np.stack([decode_mask(inst["mask"]) for inst in instances]))
        if instances
        else torch.zeros(0, height, width, dtype=torch.bool)
    )
    depth = None
    if with_depth and row.get("depth") is not None:
        depth = torch.from_numpy(decode_depth(row["depth"]))
    return FrameData(
        scene_id=row["scene_id"],
        view_id=int(row["view_id"]),
        image=image,
        K=torch.from_numpy(frame_K(row)).float(),
        cam_to_world=torch.from_numpy(frame_pose(row)),
        instance_ids=torch.tensor([int(i["instance_id"]) for i in instances], dtype=torch.int64),
        labels=torch.tensor([categories.index(int(i["category_id"])) for i in instances], dtype=torch.int64),
        boxes=torch.tensor([list(i["box_xyxy"]) for i in instances], dtype=torch.float32).reshape(-1, 4),
        masks=masks,
        depth_min=torch.tensor([float(i["depth_min"]) for i in instances], dtype=torch.float32),
        depth=depth,
    )
