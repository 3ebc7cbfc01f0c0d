"""Synthetic multi-view samples shaped like a recipe's dataset, for benchmarks and op counts.

Images of a given size, ``objects`` objects per input view with elliptic masks, and ``views`` views
per sample whose masks sit at other places: the cost of a training step does not depend on the
masks being consistent across views, so these stand in for real records when only cost matters.
"""

from __future__ import annotations

import math

import torch

from data_specs import load_dataset_spec
from usl.config import Config, load_config
from usl.data import FrameData, MultiViewSample, TargetView
from usl.geometry.cameras import intrinsics_from_fov
from usl.model.config import LayoutRange


# the dataset each recipe trains on, whose categories and layout range a synthetic batch borrows
RECIPE_DATA = {
    "tiny": "scene_shapes",
    "tiny_long": "scene_shapes",
    "scene_shapes": "scene_shapes",
    "scene_shapes_fpn": "scene_shapes",
    "hypersim": "hypersim",
    "scannet": "scannet",
}


def synthetic_config(recipe: str, overrides: list[str] | None = None) -> Config:
    """The recipe's config with the categories and layout range of the dataset it trains on."""
    cfg = load_config(recipe, overrides or [])
    spec = load_dataset_spec(RECIPE_DATA.get(recipe, "hypersim"))
    cfg.model.categories = tuple(c["name"] for c in spec["categories"])
    cfg.model.layout_range = LayoutRange(**spec["layout"])
    return cfg


def ellipse_masks(boxes: torch.Tensor, height: int, width: int) -> torch.Tensor:
    v, u = torch.meshgrid(torch.arange(height) + 0.5, torch.arange(width) + 0.5, indexing="ij")
    centre = 0.5 * (boxes[:, :2] + boxes[:, 2:])
    half = 0.5 * (boxes[:, 2:] - boxes[:, :2])
    du = (u[None] - centre[:, 0, None, None]) / half[:, 0, None, None]
    dv = (v[None] - centre[:, 1, None, None]) / half[:, 1, None, None]
    return du.square() + dv.square() <= 1.0


def random_boxes(count: int, height: int, width: int, generator: torch.Generator) -> torch.Tensor:
    size = torch.rand(count, 2, generator=generator) * 0.3 + 0.08
    size = size * torch.tensor([width, height])
    lo = torch.rand(count, 2, generator=generator) * (torch.tensor([width, height]) - size)
    return torch.cat([lo, lo + size], dim=1).floor()


def orbit_pose(angle: float) -> torch.Tensor:
    """A camera on a 3 m circle around (0, 0, 3), looking at it (OpenCV axes, y down)."""
    pose = torch.eye(4, dtype=torch.float64)
    c, s = math.cos(angle), math.sin(angle)
    pose[:3, :3] = torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]], dtype=torch.float64)
    pose[:3, 3] = torch.tensor([-3.0 * s, 0.0, 3.0 - 3.0 * c], dtype=torch.float64)
    return pose


def synthetic_sample(index: int, height: int, width: int, objects: int, views: int, classes: int) -> MultiViewSample:
    """Sample ``index`` (its seed): one input view of ``objects`` objects and ``views - 1`` other views."""
    generator = torch.Generator().manual_seed(index)
    K = intrinsics_from_fov(math.radians(60.0), width, height).float()
    boxes = random_boxes(objects, height, width, generator)
    masks = ellipse_masks(boxes, height, width)
    frame = FrameData(
        scene_id=f"synthetic{index}",
        view_id=0,
        image=torch.rand(3, height, width, generator=generator),
        K=K,
        cam_to_world=orbit_pose(0.0),
        instance_ids=torch.arange(objects),
        labels=torch.randint(0, classes, (objects,), generator=generator),
        boxes=boxes,
        masks=masks,
        depth_min=torch.full((objects,), float("nan")),
    )
    targets = [TargetView(0, K, frame.cam_to_world, masks, torch.ones(objects, dtype=torch.bool))]
    for j in range(1, views):
        other = ellipse_masks(random_boxes(objects, height, width, generator), height, width)
        targets.append(TargetView(j, K, orbit_pose(0.3 * j), other, torch.ones(objects, dtype=torch.bool)))
    return MultiViewSample(frame, torch.arange(objects), targets, seed=index)
