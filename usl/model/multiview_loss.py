"""L_3D and L_reg of the paper (Sec. 3.4, Appendix), assembled over a batch of multi-view samples.

``L_3D = 1/|O| 1/M sum_o sum_j l_2D(render(R_{1->j} T_o), S_j^o)`` per input image, then the
mean over the batch's images. Two choices the paper leaves open:

* An object not annotated in view j (out of frame, fully occluded, not tracked) has no true
  silhouette there; its (o, j) pair is dropped rather than compared with an empty mask, because
  our renderer draws each object alone (no occluders) and an empty target would push an
  occluded object out of the view. The per-image mean runs over the remaining pairs; the
  input view always has every object.
* Every loss term is normalised per image and then averaged over the batch (images without
  objects count as 0), so a batch split over GPUs (DDP averages per-GPU losses) gives exactly
  the gradient of the whole batch on one GPU.

All geometry here runs in float32 with autocast off: squared pixel distances and soft
silhouettes with sigma ~ 1e-4 are not safe in half precision.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import torch

from usl.model.config import LossConfig
from usl.data.samples import MultiViewSample
from usl.geometry import Meshes, faces_on_each_edge, sample_points_from_meshes
from usl.geometry.cameras import relative_transform, transform_points
from usl.losses import (
    l2d_loss,
    laplacian_smoothing_loss,
    mesh_edge_loss,
    normal_consistency,
    offset_l2_loss,
    sample_mask_points,
    silhouette_bce_loss,
    silhouette_chamfer_loss,
    soft_iou_loss,
)
from usl.render import render_dynamic

Tensor = torch.Tensor

# the shape regularizers' names, as LossWeights and combine_losses call them
REGULARIZERS = ("edge", "offset_l2", "laplacian", "normal")


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


class SilhouetteLoss(NamedTuple):
    """L_3D = dist + xent, its two weighted parts (kept apart for gradient diagnostics), and
    detached statistics: mean l_dist, mean l_xent, l_xent without BCE's clamp mass
    (``l_xent_reached``), the fraction of true pixels no face reaches (``unreached``), the
    fraction of pairs the IoU gate lets into l_xent (``xent_gate``), the fraction of other-view
    pairs above the IoU threshold whatever the gate mode (``iou_pass_views``: the pairs a gated
    l_xent can reach, hence the only ones that move z and rho without l_dist), the soft
    silhouettes' mean IoU in the input view and in the other views (``iou_input``,
    ``iou_views``: the training-side counterparts of usl-eval's Mask IoU without occlusion) and
    l_dist's current factor. ``xent`` is the gated shape part: l_xent's BCE plus, with
    ``loss.weights.soft_iou``, the soft-IoU term (``l_soft_iou`` in the stats: its mean over all pairs)."""

    l3d: Tensor
    dist: Tensor
    xent: Tensor
    stats: dict[str, Tensor]


def multiview_silhouette_loss(
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
        pairs.masks,
        render.resolution,
        render.settings(),
        render.padding,
        ignore_masks=pairs.occluders if cfg.ignore_occluders else None,
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
        true_points, true_lengths = sample_mask_points(masks, cfg.mask_points, generator=generator)
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


def shape_regularizers(
    verts_cube: Tensor, offsets: list[Tensor], faces: Tensor, counts: list[int], need: dict[str, bool]
) -> dict[str, Tensor | None]:
    """Edge, ½‖dV‖² (summed over stages, pre-tanh), Laplacian and normal-consistency terms, each a
    per-image mean over objects averaged over the batch. Terms not in ``need`` are None (not computed).

    Regularizers act on the normalized-cube meshes, so their scale does not depend on layout.
    """
    zero = verts_cube.sum() * 0.0
    result: dict[str, Tensor | None] = {name: (zero.clone() if need.get(name) else None) for name in REGULARIZERS}
    pairs = faces_on_each_edge(faces) if need.get("normal") else None
    starts = torch.tensor([0] + counts).cumsum(0).tolist()
    batch = len(counts)
    for index in range(batch):
        rows = slice(starts[index], starts[index + 1])
        if starts[index + 1] == starts[index]:
            continue
        if need.get("edge") or need.get("laplacian"):
            meshes = Meshes.from_shared_topology(verts_cube[rows].float(), faces)
        if need.get("edge"):
            result["edge"] = result["edge"] + mesh_edge_loss(meshes) / batch
        if need.get("laplacian"):
            result["laplacian"] = result["laplacian"] + laplacian_smoothing_loss(meshes) / batch
        if need.get("normal"):
            result["normal"] = (
                result["normal"] + normal_consistency(verts_cube[rows].float(), faces, pairs).mean() / batch
            )
        if need.get("offset_l2"):
            result["offset_l2"] = result["offset_l2"] + sum(offset_l2_loss(o[rows]) for o in offsets) / batch
    return result
