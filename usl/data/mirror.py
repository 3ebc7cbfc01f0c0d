"""Left-right mirroring of a multi-view sample as ONE reflection of the world (``data.flip_prob``).

Flipping each image on its own would break the multi-view geometry: the views' poses would no
longer describe the flipped images. Instead the whole scene is reflected by ``M = diag(-1, 1, 1)``
in world coordinates and every camera is re-posed as ``cam_to_world' = M cam_to_world S`` with
``S = diag(-1, 1, 1)`` in camera coordinates. Then a world point ``M X`` lands in every view at
``u' = W - u`` (pixel frame [0, W], docs/design.md §2), with ``K' = F K S`` where ``F`` is
``u -> W - u`` (``cx' = W - cx``, skew negated). Both ``M`` and ``S`` are reflections, so every
new pose is a proper rigid transform, and the relative poses the loss uses become ``S R S``:
all views stay consistent. Camera-frame true meshes reflect by ``S`` with their face winding
reversed, so normals still point outwards.
"""
from __future__ import annotations

from dataclasses import replace

import torch

from .frames import FrameData
from .samples import MultiViewSample, TargetView
from .true_meshes import TrueMesh

Tensor = torch.Tensor


def mirror_intrinsics(K: Tensor, width: int) -> Tensor:
    """``F K S``: the intrinsics that image a camera-frame point ``S X`` at ``W - u``."""
    mirrored = K.clone()
    mirrored[0, 1] = -K[0, 1]
    mirrored[0, 2] = width - K[0, 2]
    return mirrored


def mirror_pose(cam_to_world: Tensor) -> Tensor:
    """``M cam_to_world S``: the pose of the same camera in the reflected world (still rigid)."""
    mirrored = cam_to_world.clone()
    mirrored[0, :] = -mirrored[0, :]  # M: the world x of every camera axis and of the centre
    mirrored[:, 0] = -mirrored[:, 0]  # S: the camera's own x axis
    return mirrored


def mirror_boxes(boxes: Tensor, width: int) -> Tensor:
    """xyxy boxes under ``u -> W - u`` (x0 and x1 swap)."""
    return torch.stack([width - boxes[:, 2], boxes[:, 1], width - boxes[:, 0], boxes[:, 3]], dim=1)


def mirror_frame(frame: FrameData) -> FrameData:
    width = frame.size[1]
    return replace(
        frame,
        image=frame.image.flip(-1),
        K=mirror_intrinsics(frame.K, width),
        cam_to_world=mirror_pose(frame.cam_to_world),
        boxes=mirror_boxes(frame.boxes, width),
        masks=frame.masks.flip(-1),
        depth=None if frame.depth is None else frame.depth.flip(-1),
    )


def mirror_target_view(view: TargetView) -> TargetView:
    return replace(
        view,
        K=mirror_intrinsics(view.K, view.size[1]),
        cam_to_world=mirror_pose(view.cam_to_world),
        masks=view.masks.flip(-1),
    )


def mirror_true_mesh(mesh: TrueMesh) -> TrueMesh:
    """A camera-frame mesh reflected by ``S``, winding reversed (outward normals stay outward)."""
    verts = mesh.verts.clone()
    verts[:, 0] = -verts[:, 0]
    return TrueMesh(verts=verts, faces=mesh.faces[:, [0, 2, 1]])


def mirror_sample(sample: MultiViewSample) -> MultiViewSample:
    """Every view of the sample, and its true meshes, in the reflected world."""
    meshes = None if sample.true_meshes is None else [mirror_true_mesh(m) for m in sample.true_meshes]
    return replace(
        sample,
        frame=mirror_frame(sample.frame),
        views=[mirror_target_view(v) for v in sample.views],
        true_meshes=meshes,
    )
