"""L_3D and L_reg of the paper (Sec. 3.4, Appendix), assembled over a batch of multi-view samples.

``L_3D = 1/|O| 1/M sum_o sum_j l_2D(render(R_{1->j} T_o), S_j^o)`` per input image, then the
mean over the batch's images. Two choices the paper leaves open:

* An object not annotated in view j (out of frame, fully occluded, not tracked) has no true
  silhouette there; its (o, j) pair is dropped (weight 0) rather than compared with an empty mask, because
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

from usl.data.samples import MultiViewSample
from usl.geometry import Meshes, MeshTemplate, sample_points_in_groups
from usl.geometry.cameras import relative_transform, transform_points
from usl.losses import (
    edge_length_per_mesh,
    l2d_loss,
    laplacian_per_mesh,
    normal_consistency,
    offset_l2_per_mesh,
    sample_mask_points,
    silhouette_bce_loss,
    silhouette_chamfer_loss,
    soft_iou_loss,
)
from usl.model.config import LossConfig
from usl.render import PaddedMasks, render_dynamic
from usl.render.masks import pad_cat
from usl.utils.transfer import to_device

Tensor = torch.Tensor

# the shape regularizers' names, as LossWeights and combine_losses call them
REGULARIZERS = ("edge", "offset_l2", "laplacian", "normal")


@dataclass
class _Pairs:
    """Every (object, view) pair of the batch, sample by sample, views in order. A pair whose object
    is not annotated in that view (``present`` False) is kept, with weight 0 and out of every mean:
    shapes then depend only on the batch's object and view counts, never on the data."""

    verts: Tensor  # (P, V, 3) meshes in view j's camera frame
    points: Tensor  # (P, S, 3) mesh surface points in view j's camera frame
    true_points: Tensor  # (P, T, 2)
    true_lengths: Tensor  # (P,)
    masks: PaddedMasks  # each pair's true mask, with its view's (H, W)
    occluders: Tensor | None  # (P, H, W) other objects' pixels, padded as the masks (loss.ignore_occluders)
    K: Tensor  # (P, 3, 3)
    present: Tensor  # (P,) bool
    weight: Tensor  # (P,) 1 / (present pairs of the sample's image) / batch size; 0 where absent
    is_input: Tensor  # (P,) bool, the pair's view is the input view


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
    if not sum(counts):
        zero = verts_cam.sum() * 0.0
        return SilhouetteLoss(zero, zero, zero, {})
    pairs = _gather_pairs(verts_cam, faces, samples, counts, cfg)
    verts, K, present = pairs.verts, pairs.K, pairs.present
    dist_factor = cfg.weights.dist * cfg.dist_scale * cfg.dist_schedule(iteration)
    if dist_factor:
        dist = silhouette_chamfer_loss(pairs.points, K, pairs.masks.sizes, pairs.true_points, pairs.true_lengths)
    else:  # "w/o l_dist": not computed, so it contributes exactly no gradient (and costs nothing)
        dist = verts.new_zeros(len(verts))
    num_pairs, num_verts = verts.shape[:2]
    faces_packed = (faces[None] + num_verts * torch.arange(num_pairs, device=faces.device)[:, None, None]).reshape(
        -1, 3
    )
    face_window = torch.arange(num_pairs, device=faces.device).repeat_interleave(
        faces.shape[0], output_size=num_pairs * faces.shape[0]
    )
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
        ignore_masks=pairs.occluders,
    )
    xent = silhouette_bce_loss(rendered.soft, rendered.target, rendered.valid, cfg.iou_threshold)
    is_input = pairs.is_input
    others = present & ~is_input
    other_views = (
        {"iou_pass_views": (xent.gate, others), "iou_views": (xent.iou, others)}
        if any(len(sample.views) > 1 for sample in samples)
        else {}
    )
    if cfg.xent_gate == "all":  # l_xent on every pair
        xent = xent._replace(gate=torch.ones_like(xent.gate))
    elif not cfg.gate_input_view:
        xent = xent._replace(gate=xent.gate | is_input)
    soft_iou = soft_iou_loss(rendered.soft, rendered.target, rendered.valid) if cfg.weights.soft_iou else None
    shape_terms = xent if soft_iou is None else xent._replace(loss=xent.loss + cfg.weights.soft_iou * soft_iou)
    l3d = (l2d_loss(dist_factor * dist, shape_terms) * pairs.weight).sum()
    dist_part = (dist_factor * dist * pairs.weight).sum()  # the gated l_xent part is the rest of l_2D
    stats = _means(
        {
            **({"l_dist": (dist.detach(), present)} if dist_factor else {}),
            "l_xent": (xent.loss.detach(), present),
            "l_xent_reached": (xent.loss_reached, present),
            **({"l_soft_iou": (soft_iou.detach(), present)} if soft_iou is not None else {}),
            "unreached": (xent.unreached, present),
            "xent_gate": (xent.gate, present),
            "iou_input": (xent.iou, present & is_input),
            **other_views,
        }
    )
    stats["dist_factor"] = l3d.new_full((), dist_factor)
    return SilhouetteLoss(l3d, dist_part, l3d - dist_part, stats)


def _means(terms: dict[str, tuple[Tensor, Tensor]]) -> dict[str, Tensor]:
    """Each ``name: (values, keep)``'s mean of ``values`` over the pairs ``keep`` marks (0 if none),
    all in one stacked reduction, without reading the device."""
    values = torch.stack([value.to(torch.float32) for value, _ in terms.values()])
    keep = torch.stack([mask.to(torch.float32) for _, mask in terms.values()])
    return dict(zip(terms, ((values * keep).sum(dim=1) / keep.sum(dim=1).clamp(min=1.0)).unbind(), strict=True))


def _gather_pairs(
    verts_cam: Tensor, faces: Tensor, samples: list[MultiViewSample], counts: list[int], cfg: LossConfig
) -> _Pairs:
    """All pairs, one block per sample: its N objects in each of its M views (view-major). The
    random draws go sample by sample (each keyed by its sample); the cameras and the transforms
    into every view run once for the batch."""
    device, batch_size = verts_cam.device, len(samples)
    parts: dict[str, list] = {name: [] for name in ("true_points", "true_lengths", "masks", "occluders")}
    poses, input_views, intrinsics, present, sizes = [], [], [], [], []
    # each sample's generator keys its draws: the same points whatever batch it lands in
    generators = [torch.Generator(device=device).manual_seed(sample.seed) for sample in samples]
    drawing = [index for index, count in enumerate(counts) if count]
    surfaces = sample_points_in_groups(
        Meshes.from_shared_topology(verts_cam, faces),
        cfg.mesh_points,
        [counts[index] for index in drawing],
        [generators[index] for index in drawing],
    )
    pair_rows: list[tuple[int, int, int, int]] = []  # per pair: object row, view row, sample, is input view
    first_row = 0
    for index, (sample, num_objects) in enumerate(zip(samples, counts, strict=True)):
        num_views, start = len(sample.views), first_row
        first_row += num_objects
        if not num_objects:
            continue
        masks = pad_cat([view.masks for view in sample.views])  # (M N, H, W), view by view
        true_points, true_lengths = sample_mask_points(masks, cfg.mesh_points, generator=generators[index])
        parts["true_points"].append(true_points)
        parts["true_lengths"].append(true_lengths)
        parts["masks"].append(masks)
        if cfg.ignore_occluders:
            parts["occluders"].append(_occluders(masks, num_views))
        pair_rows += [(start + o, len(poses) + j, index, j == 0) for j in range(num_views) for o in range(num_objects)]
        input_views += [len(poses)] * num_views
        poses += [view.cam_to_world for view in sample.views]
        intrinsics += [view.K for view in sample.views]
        present += [view.present for view in sample.views]
        sizes += [view.size for view in sample.views]
    pair_object, pair_view, pair_sample, is_input = to_device(pair_rows, device).T
    poses, input_views = torch.stack(poses), to_device(input_views, device)
    to_view = relative_transform(poses[input_views], poses).float()[pair_view]  # (P, 4, 4)
    present = torch.cat(present).bool()
    per_sample = torch.zeros(batch_size, dtype=torch.long, device=device).index_add(0, pair_sample, present.long())
    masks, occluders = parts.pop("masks"), parts.pop("occluders")
    return _Pairs(
        verts=transform_points(verts_cam[pair_object], to_view),
        points=transform_points(surfaces[pair_object], to_view),
        masks=PaddedMasks(pad_cat(masks), to_device(sizes, device)[pair_view]),
        occluders=pad_cat(occluders) if cfg.ignore_occluders else None,
        K=torch.stack(intrinsics).float()[pair_view],
        present=present,
        weight=present.float() / (per_sample[pair_sample].clamp(min=1) * batch_size),
        is_input=is_input.bool(),
        **{name: torch.cat(values) for name, values in parts.items()},
    )


def _occluders(masks: Tensor, num_views: int) -> Tensor:
    """Each pair's pixels of the other objects in that view, from a sample's (M N, H, W) masks (view
    by view; padding is False in every mask, so in every occluder)."""
    by_view = masks.unflatten(0, (num_views, -1))  # (M, N, H, W)
    return (by_view.any(dim=1, keepdim=True) & ~by_view).flatten(0, 1)


def shape_regularizers(
    verts_cube: Tensor, offsets: list[Tensor], template: MeshTemplate, counts: list[int], need: dict[str, bool]
) -> dict[str, Tensor | None]:
    """Edge, ½‖dV‖² (summed over stages, pre-tanh), Laplacian and normal-consistency terms, each a
    per-image mean over objects averaged over the batch. Terms not in ``need`` are None (not computed).

    Regularizers act on the normalized-cube meshes, so their scale does not depend on layout. All
    objects are computed at once (they share the template), then averaged image by image.
    """
    per_object: dict[str, Tensor] = {}
    if verts_cube.shape[0]:
        verts = verts_cube.float()
        if need.get("edge") or need.get("laplacian"):
            meshes = Meshes.from_shared_topology(verts, template.faces, template.edges)
        if need.get("edge"):
            per_object["edge"] = edge_length_per_mesh(meshes)
        if need.get("laplacian"):
            per_object["laplacian"] = laplacian_per_mesh(meshes)
        if need.get("normal"):
            per_object["normal"] = normal_consistency(verts, template.faces, template.edge_faces)
        if need.get("offset_l2") and offsets:
            per_object["offset_l2"] = offset_l2_per_mesh(torch.stack(offsets)).sum(dim=0)  # summed over stages
    zero = verts_cube.sum() * 0.0
    batch = len(counts)
    per_image = to_device(counts, verts_cube.device)
    image = torch.repeat_interleave(
        torch.arange(batch, device=verts_cube.device), per_image, output_size=verts_cube.shape[0]
    )
    objects = per_image.to(torch.float32).clamp(min=1)
    result: dict[str, Tensor | None] = {}
    for name in REGULARIZERS:
        if not need.get(name):
            result[name] = None
        elif name in per_object:  # per-image means (an image without objects adds 0), over the batch
            result[name] = (zero.new_zeros(batch).index_add(0, image, per_object[name]) / objects).sum() / batch
        else:
            result[name] = zero.clone()
    return result
