"""The multi-view loss's former per-(sample, view) gathering, kept as a test oracle for the batched
one: a nonzero, an ``int(present.sum())`` and ~20 small ops per view of each sample."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from usl.config import LossConfig
from usl.data.samples import MultiViewSample
from usl.geometry import Meshes, sample_points_from_meshes
from usl.geometry.cameras import relative_transform, transform_points
from usl.losses import (
    l2d_loss,
    sample_mask_points,
    silhouette_bce_loss,
    silhouette_chamfer_loss,
    soft_iou_loss,
)
from usl.model.multiview_loss import SilhouetteLoss
from usl.render import PaddedMasks, render_dynamic

Tensor = torch.Tensor


@dataclass
class _Pairs:
    """(object, view) pairs of the whole batch, gathered sample by sample."""

    verts: list[Tensor]  # (n, V, 3) meshes in view j's camera frame
    points: list[Tensor]  # (n, S, 3) mesh surface points in view j's camera frame
    true_points: list[Tensor]  # (n, T, 2)
    true_lengths: list[Tensor]  # (n,)
    masks: list[Tensor]  # n masks (H_j, W_j)
    K: list[Tensor]  # (n, 3, 3)
    sizes: list[Tensor]  # (n, 2) (H, W)
    weight: list[Tensor]  # (n,) 1 / (pairs of the sample's image) / batch size
    is_input: list[Tensor]  # (n,) bool, the pair's view is the input view
    occluders: list[Tensor]  # n masks (H_j, W_j): other objects' pixels (loss.ignore_occluders)


def multiview_silhouette_loss_per_pair(
    verts_cam: Tensor,
    faces: Tensor,
    samples: list[MultiViewSample],
    counts: list[int],
    cfg: LossConfig,
    iteration: int = 0,
) -> SilhouetteLoss:
    """L_3D for a batch. ``verts_cam`` (N, V, 3) are all objects' meshes in their input camera's
    frame, sample by sample (``counts[i]`` objects for sample i, in ``object_rows`` order).
    ``iteration`` sets l_dist's factor ``cfg.weights.dist * cfg.dist_scale * cfg.dist_schedule(iteration)``.
    """
    verts_cam = verts_cam.float()
    pairs = _Pairs([], [], [], [], [], [], [], [], [], [])
    starts = torch.tensor([0] + counts).cumsum(0).tolist()
    for index, sample in enumerate(samples):
        verts = verts_cam[starts[index] : starts[index + 1]]
        if len(verts):
            _gather_pairs(verts, faces, sample, cfg, len(samples), pairs)
    if not pairs.verts:
        zero = verts_cam.sum() * 0.0
        return SilhouetteLoss(zero, zero, zero, {})
    verts, K = torch.cat(pairs.verts), torch.cat(pairs.K)
    dist_factor = cfg.weights.dist * cfg.dist_scale * cfg.dist_schedule(iteration)
    if dist_factor:
        dist = silhouette_chamfer_loss(
            torch.cat(pairs.points),
            K,
            torch.cat(pairs.sizes),
            torch.cat(pairs.true_points),
            torch.cat(pairs.true_lengths),
        )
    else:  # "w/o l_dist": not computed, so it contributes exactly no gradient (and costs nothing)
        dist = verts.new_zeros(len(verts))
    num_pairs, num_verts = verts.shape[:2]
    faces_packed = (faces[None] + num_verts * torch.arange(num_pairs, device=faces.device)[:, None, None]).reshape(
        -1, 3
    )
    face_window = torch.arange(num_pairs, device=faces.device).repeat_interleave(faces.shape[0])
    render = cfg.render
    rendered = render_dynamic(
        verts.reshape(-1, 3),
        faces_packed,
        face_window,
        K,
        PaddedMasks.of(pairs.masks),
        render.resolution,
        render.settings(),
        render.padding,
        ignore_masks=PaddedMasks.of(pairs.occluders).padded if cfg.ignore_occluders else None,
    )
    xent = silhouette_bce_loss(rendered.soft, rendered.target, rendered.valid, cfg.iou_threshold)
    is_input = torch.cat(pairs.is_input)
    others = ~is_input
    other_views = (
        {"iou_pass_views": xent.gate[others].float().mean(), "iou_views": xent.iou[others].mean()}
        if bool(others.any())
        else {}
    )
    if cfg.xent_gate == "all":  # l_xent on every pair
        xent = xent._replace(gate=torch.ones_like(xent.gate))
    elif not cfg.gate_input_view:
        xent = xent._replace(gate=xent.gate | is_input)
    weight = torch.cat(pairs.weight)
    soft_iou = soft_iou_loss(rendered.soft, rendered.target, rendered.valid) if cfg.weights.soft_iou else None
    shape_terms = xent if soft_iou is None else xent._replace(loss=xent.loss + cfg.weights.soft_iou * soft_iou)
    l3d = (l2d_loss(dist_factor * dist, shape_terms) * weight).sum()
    dist_part = (dist_factor * dist * weight).sum()  # the gated l_xent part is the rest of l_2D
    stats = {
        **({"l_dist": dist.detach().mean()} if dist_factor else {}),
        "l_xent": xent.loss.detach().mean(),
        "l_xent_reached": xent.loss_reached.mean(),
        **({"l_soft_iou": soft_iou.detach().mean()} if soft_iou is not None else {}),
        "unreached": xent.unreached.mean(),
        "xent_gate": xent.gate.float().mean(),
        "iou_input": xent.iou[is_input].mean(),
        **other_views,
        "dist_factor": torch.tensor(dist_factor),
    }
    return SilhouetteLoss(l3d, dist_part, l3d - dist_part, stats)


def _gather_pairs(
    verts: Tensor, faces: Tensor, sample: MultiViewSample, cfg: LossConfig, batch_size: int, pairs: _Pairs
) -> None:
    generator = torch.Generator(device=verts.device).manual_seed(sample.seed)
    surface = sample_points_from_meshes(Meshes.from_shared_topology(verts, faces), cfg.mesh_points, generator)
    input_pose = sample.views[0].cam_to_world
    num_pairs = sum(int(view.present.sum()) for view in sample.views)
    for position, view in enumerate(sample.views):
        present = torch.nonzero(view.present).squeeze(1)
        if len(present) == 0:
            continue
        to_view = relative_transform(input_pose, view.cam_to_world).float()
        masks = view.masks[present]
        true_points, true_lengths = sample_mask_points(masks, cfg.mesh_points, generator=generator)
        pairs.verts.append(transform_points(verts[present], to_view))
        pairs.points.append(transform_points(surface[present], to_view))
        pairs.true_points.append(true_points)
        pairs.true_lengths.append(true_lengths)
        pairs.masks.extend(masks.unbind(0))
        pairs.K.append(view.K.float().expand(len(present), 3, 3))
        pairs.sizes.append(torch.tensor(view.size, device=verts.device).expand(len(present), 2))
        pairs.weight.append(torch.full((len(present),), 1.0 / (num_pairs * batch_size), device=verts.device))
        pairs.is_input.append(torch.full((len(present),), position == 0, device=verts.device))
        if cfg.ignore_occluders:
            pairs.occluders.extend((view.masks.any(dim=0) & ~masks).unbind(0))
