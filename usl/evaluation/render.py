"""Rendering predictions into views and scoring (object, view) pairs (paper Sec. 4 metrics).

Each predicted mesh lives in the input camera's frame; for view j it is moved by
``R_{1->j} = inv(cam_to_world_j) @ cam_to_world_1`` and drawn with the hard z-buffer rasterizer.

Occlusion: by default all predicted objects of an input view are drawn *together* into each view,
so each object's rendered mask is its visible part, like the records' true masks (a perfect
prediction scores IoU 1 even where objects occlude each other). With ``occlusion=False`` every
object is drawn alone (its full silhouette).

Per pair we report: Mask IoU; Box gIoU between the boxes around the rendered and the true
silhouettes; the rendered nearest depth vs. the record's ``depth_min`` (Depth L1). When an object's
rendered silhouette is empty in a view (it projects outside the image or is hidden), its box and
nearest depth fall back to the projection of its vertices in front of the camera (box unclipped,
smallest depth), so misplaced objects are still scored by distance; an object wholly behind the
camera gets gIoU -1 and no depth (NaN, left out of the mean).
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import torch

from usl.evaluation.targets import ViewTargets
from usl.geometry import Meshes
from usl.geometry.cameras import project, relative_transform, transform_points
from usl.metrics import box_giou, depth_l1, mask_iou, masks_to_boxes
from usl.render import HardRender, rasterize_hard
from usl.render.screen import DEFAULT_NEAR
from usl.utils.transfer import to_device

Tensor = torch.Tensor

# Bytes the rasterizer needs per pixel of a view (float z-buffer + long face buffer), and per pixel
# of each mesh (its returned bool mask, built through a long gather of the instance map).
_VIEW_BYTES_PER_PIXEL = 12
_MESH_BYTES_PER_PIXEL = 9
DEFAULT_MAX_RENDER_BYTES = 1 << 30


@dataclass
class Group:
    """A set of objects rendered together (occluding each other) into one view."""

    view: int  # index into the views list
    objects: Tensor  # (k,) long object indices


@dataclass
class GroupRender:
    """The rasterizer's answer for a batch of groups; mesh m is object ``mesh_object[m]`` in group ``mesh_group[m]``."""

    render: HardRender
    mesh_group: Tensor  # (M,) long, index into the batch's groups
    mesh_object: Tensor  # (M,) long
    verts: Tensor  # (M, V, 3) each mesh in its view's camera frame
    K: Tensor  # (M, 3, 3) the intrinsics of each mesh's view


def render_groups(
    verts: Tensor, faces: Tensor, input_pose: Tensor, views: Sequence[ViewTargets], groups: Sequence[Group]
) -> GroupRender:
    """Render each group's objects (verts (N, V, 3) in the input camera) into its view, all at once.

    All views of the groups must share one image size.
    """
    sizes = {(views[g.view].height, views[g.view].width) for g in groups}
    if len(sizes) != 1:
        raise ValueError(f"render_groups: one image size per call, got {sorted(sizes)}")
    (height, width), device = sizes.pop(), verts.device
    mesh_group = torch.cat([torch.full((len(g.objects),), n, dtype=torch.long) for n, g in enumerate(groups)]).to(
        device
    )
    mesh_object = torch.cat([g.objects.long().cpu() for g in groups]).to(device)
    to_view = torch.stack([relative_transform(input_pose, views[g.view].cam_to_world) for g in groups]).to(device)
    view_verts = transform_points(verts.double()[mesh_object], to_view[mesh_group]).to(verts.dtype)
    meshes = Meshes.from_shared_topology(view_verts, faces)
    group_K = torch.stack([views[g.view].K for g in groups]).to(device=device, dtype=verts.dtype)
    render = rasterize_hard(
        meshes.verts_packed(),
        meshes.faces_packed(),
        meshes.faces_packed_to_mesh_idx(),
        group_K,
        height,
        width,
        mesh_view=mesh_group,
        num_meshes=len(mesh_group),
    )
    return GroupRender(render, mesh_group, mesh_object, view_verts, group_K[mesh_group])


def group_bytes(view: ViewTargets, num_objects: int) -> int:
    return view.height * view.width * (_VIEW_BYTES_PER_PIXEL + _MESH_BYTES_PER_PIXEL * num_objects)


def batch_groups(views: Sequence[ViewTargets], groups: Sequence[Group], max_bytes: int) -> Iterator[list[Group]]:
    """Consecutive runs of groups with one image size and at most ``max_bytes`` of buffers (>= 1 group)."""
    batch: list[Group] = []
    used = 0
    for g in groups:
        cost = group_bytes(views[g.view], len(g.objects))
        size = (views[g.view].height, views[g.view].width)
        if batch and (used + cost > max_bytes or size != (views[batch[0].view].height, views[batch[0].view].width)):
            yield batch
            batch, used = [], 0
        batch.append(g)
        used += cost
    if batch:
        yield batch


def projected_extent(verts: Tensor, K: Tensor, near: float = DEFAULT_NEAR) -> tuple[Tensor, Tensor]:
    """Box (n, 4) around the projections of the vertices in front of the camera, and their smallest depth (n,).

    verts (n, V, 3) camera frame, K (n, 3, 3). NaN for meshes with no vertex in front.
    """
    uv, w = project(verts, K)
    front = (w > near) & (verts[..., 2] > near)
    inf = torch.full_like(w, float("inf"))
    lo = torch.where(front.unsqueeze(-1), uv, inf.unsqueeze(-1)).amin(1)
    hi = torch.where(front.unsqueeze(-1), uv, -inf.unsqueeze(-1)).amax(1)
    depth = torch.where(front, verts[..., 2], inf).amin(1)
    any_front = front.any(1)
    box = torch.where(any_front.unsqueeze(-1), torch.cat([lo, hi], -1), float("nan"))
    return box, torch.where(any_front, depth, float("nan"))


@dataclass
class PairScores:
    """Metrics of P (object, view) pairs; NaN where a value is undefined."""

    iou: Tensor
    giou: Tensor
    depth_pred: Tensor
    depth_true: Tensor

    @property
    def depth_l1(self) -> Tensor:
        return depth_l1(self.depth_pred, self.depth_true)


def score_pairs(
    verts: Tensor,
    faces: Tensor,
    input_pose: Tensor,
    views: Sequence[ViewTargets],
    pairs: Tensor,
    occlusion: bool = True,
    max_bytes: int = DEFAULT_MAX_RENDER_BYTES,
) -> PairScores:
    """Score pairs ``(object index, view index, target index in that view)`` given as a (P, 3) long tensor."""
    num_pairs = pairs.shape[0]
    out = PairScores(*(torch.full((num_pairs,), float("nan")) for _ in range(4)))
    if num_pairs == 0:
        return out
    pair_list = pairs.tolist()
    view_order = sorted({v for _, v, _ in pair_list}, key=lambda v: (views[v].height, views[v].width, v))
    all_objects = torch.arange(verts.shape[0])
    if occlusion:
        groups = [Group(v, all_objects) for v in view_order]
    else:
        rank = {v: r for r, v in enumerate(view_order)}
        needed = sorted({(v, o) for o, v, _ in pair_list}, key=lambda vo: (rank[vo[0]], vo[1]))
        groups = [Group(v, torch.tensor([o])) for v, o in needed]
    mesh_of: dict[tuple[int, int], int] = {}
    for batch in batch_groups(views, groups, max_bytes):
        result = render_groups(verts, faces, input_pose, views, batch)
        mesh_of.clear()
        for m, (g, o) in enumerate(zip(result.mesh_group.tolist(), result.mesh_object.tolist(), strict=True)):
            mesh_of[(batch[g].view, o)] = m
        todo = [(p, mesh_of[(v, o)], v, t) for p, (o, v, t) in enumerate(pair_list) if (v, o) in mesh_of]
        if todo:
            _score_rendered(result, views, todo, out)
    return out


def _score_rendered(
    result: GroupRender, views: Sequence[ViewTargets], todo: list[tuple[int, int, int, int]], out: PairScores
) -> None:
    device = result.verts.device
    index = torch.tensor([p for p, _, _, _ in todo])
    mesh = to_device([m for _, m, _, _ in todo], device)
    pred_masks = result.render.masks[mesh]
    true_masks = torch.stack([views[v].masks[t] for _, _, v, t in todo])
    true_boxes = torch.stack([views[v].boxes[t] for _, _, v, t in todo])
    true_depth = torch.stack([views[v].depth_min[t] for _, _, v, t in todo])
    fallback_box, fallback_depth = projected_extent(result.verts[mesh], result.K[mesh])
    pred_boxes = masks_to_boxes(pred_masks)
    pred_boxes = torch.where(torch.isnan(pred_boxes), fallback_box, pred_boxes)
    giou = box_giou(pred_boxes, true_boxes)
    pred_depth = result.render.nearest_depth[mesh].float()
    pred_depth = torch.where(torch.isnan(pred_depth), fallback_depth, pred_depth)
    out.iou[index] = mask_iou(pred_masks, true_masks).cpu()
    out.giou[index] = torch.where(torch.isnan(pred_boxes).any(-1), -1.0, giou).float().cpu()
    out.depth_pred[index] = pred_depth.float().cpu()
    out.depth_true[index] = true_depth.float().cpu()


def detection_masks(
    verts: Tensor,
    faces: Tensor,
    scores: Tensor,
    view: ViewTargets,
    min_occluder_score: float = 0.5,
    max_bytes: int = DEFAULT_MAX_RENDER_BYTES,
) -> Tensor:
    """(N, H, W) masks of N detections (meshes in ``view``'s own camera frame) for segm AP.

    The true masks are visible parts, so each detection's mask is its visible part in the scene of
    the *confident* detections (score >= ``min_occluder_score``, the scene a user would look at):
    confident detections are z-buffered together; the others are occluded by that scene but occlude
    nothing themselves, so low-scoring clutter in front cannot eat into confident detections.
    """
    n = verts.shape[0]
    masks = torch.zeros(n, view.height, view.width, dtype=torch.bool, device=verts.device)
    nearest = torch.full((view.height, view.width), float("inf"), device=verts.device)
    confident = (scores >= min_occluder_score).nonzero().flatten().cpu()
    if len(confident):
        result = render_groups(verts, faces, view.cam_to_world, [view], [Group(0, confident)])
        masks[result.mesh_object] = result.render.masks
        nearest = result.render.depth_map[0].float()
    others = (scores < min_occluder_score).nonzero().flatten().cpu()
    for batch in batch_groups([view], [Group(0, others[k : k + 1]) for k in range(len(others))], max_bytes):
        result = render_groups(verts, faces, view.cam_to_world, [view], batch)
        depth = result.render.depth_map.float()  # (B, H, W), one detection each, +inf background
        masks[result.mesh_object] = torch.isfinite(depth) & (depth < nearest)
    return masks
