"""How well do a trained model's 2D features tell each object from its background?

Per object of a build's input views, given the TRUE box, the IoU with the true (visible) mask of:
the detector's mask head, the predicted mesh's own silhouette (no other object occluding it), and
the ellipse inscribed in the box (what a sphere in the box's frustum projects to). If the mask
head, trained with Mask R-CNN's dense 2D loss on the same images, does no better than the ellipse,
the image features are the limit, not the shape head or its loss.

The meshes are also scored as usl-eval scores them, all drawn together (each its visible part),
and in two orders that use the truth:

* in the true object order: each pixel goes to the covering mesh whose object is nearest by the
  records' true nearest depth (``depth_min``), a painter's algorithm (objects whose depth ranges
  interleave, a chair pushed under a table, are ordered by their nearest points). Against
  "together" this isolates what the predicted depths get wrong between objects, as far as one
  depth per object can order them (the script also counts the overlapping pairs whose predicted
  nearest depths order them rightly);
* "true owner wins": where several meshes cover a pixel of one object's true mask, that object
  wins. This is an oracle on visibility, not on depth: it also hides the pixels that an occluder's
  own mesh spills onto the visible part of the object behind it, which no order can hide. Its
  gap to the true object order bounds what the silhouettes' spill costs when drawn together (it
  also holds what the per-object order gets wrong).

    python3 scripts/experiments/mask_head_iou.py HELDOUT_BUILD RUN_OR_CHECKPOINT
        [--split train] [--input-views every:8]
"""

from __future__ import annotations

import torch
from diagnostic_inputs import input_frames, load_model, parse_args

from usl.geometry import Meshes
from usl.metrics.masks import mask_iou
from usl.model.detector.mask_head import paste_masks_in_image, select_class_masks
from usl.render import rasterize_hard

Tensor = torch.Tensor


def inscribed_ellipses(boxes: Tensor, height: int, width: int) -> Tensor:
    """(N, H, W) bool: pixel centres inside the ellipse inscribed in each xyxy box."""
    v, u = torch.meshgrid(torch.arange(height) + 0.5, torch.arange(width) + 0.5, indexing="ij")
    centre = (boxes[:, :2] + boxes[:, 2:]) / 2
    half = ((boxes[:, 2:] - boxes[:, :2]) / 2).clamp(min=1e-6)
    return ((u - centre[:, 0, None, None]) / half[:, 0, None, None]) ** 2 + (
        (v - centre[:, 1, None, None]) / half[:, 1, None, None]
    ) ** 2 <= 1


def owner_wins_masks(depth: Tensor, true_masks: Tensor) -> Tensor:
    """(N, H, W) visible masks of N meshes drawn together with the true owner winning, from their
    depth maps drawn alone (+inf where absent): where a mesh covers a pixel of its own object's true
    mask (the true masks are disjoint), it wins that pixel whatever its depth; elsewhere the nearest wins."""
    covered = torch.isfinite(depth)
    return _nearest_wins(covered, torch.where(covered & true_masks, -torch.inf, depth))


def object_order_masks(depth: Tensor, object_depth: Tensor) -> Tensor:
    """(N, H, W) visible masks of N meshes drawn with a painter's algorithm: each pixel goes to the
    covering mesh (finite ``depth``, drawn alone) with the smallest ``object_depth`` (NaN: last)."""
    covered = torch.isfinite(depth)
    # unknown depth: behind every known one, yet still ahead of "not covered" (+inf)
    rank = torch.nan_to_num(object_depth.double(), nan=torch.finfo(torch.float64).max)
    return _nearest_wins(covered, torch.where(covered, rank[:, None, None], torch.inf))


def _nearest_wins(covered: Tensor, key: Tensor) -> Tensor:
    """(N, H, W) masks: each pixel some mesh covers goes to the mesh with the smallest ``key`` there."""
    return covered.any(0) & (key.argmin(0) == torch.arange(key.shape[0])[:, None, None])


def ordered_pairs(alone_masks: Tensor, predicted_depth: Tensor, true_depth: Tensor) -> tuple[int, int]:
    """(right, total) over the pairs of meshes whose silhouettes (drawn alone) overlap and whose
    objects both have a true nearest depth: right when their predicted nearest depths order them as
    the true ones do."""
    i, j = torch.triu_indices(len(alone_masks), len(alone_masks), offset=1)
    counted = (
        (alone_masks[i] & alone_masks[j]).flatten(1).any(1)
        & torch.isfinite(true_depth[i])
        & torch.isfinite(true_depth[j])
    )
    agree = (predicted_depth[i] < predicted_depth[j]) == (true_depth[i] < true_depth[j])
    return int((counted & agree).sum()), int(counted.sum())


def draw(verts: Tensor, faces: Tensor, K: Tensor, height: int, width: int, together: bool):
    """The z-buffer of N meshes (N, V, 3) in one view: all together (usl-eval's render) or each alone."""
    meshes, n = Meshes.from_shared_topology(verts, faces), len(verts)
    mesh_view = torch.zeros(n, dtype=torch.long) if together else torch.arange(n)
    return rasterize_hard(
        meshes.verts_packed(),
        meshes.faces_packed(),
        meshes.faces_packed_to_mesh_idx(),
        K.expand(int(mesh_view.max()) + 1, 3, 3),
        height,
        width,
        mesh_view=mesh_view,
    )


@torch.no_grad()
def frame_ious(model, frame) -> tuple[dict[str, list[float]], tuple[int, int]]:
    """Each column's IoUs for the frame's objects, and ``ordered_pairs`` of its meshes."""
    _, features = model._backbone([frame])
    heads = model.detector.roi_heads
    logits = heads.mask_head(heads.mask_pooler(features, [frame.boxes]))
    mask_head = paste_masks_in_image(
        select_class_masks(logits, frame.labels), frame.boxes, frame.size, heads.cfg.mask_threshold
    )
    verts = model.objects(features, [frame.boxes], [frame.labels], [frame.K]).verts_cam
    height, width = frame.size
    alone = draw(verts, model.faces, frame.K, height, width, together=False)  # one view per mesh
    together = draw(verts, model.faces, frame.K, height, width, together=True)
    true, nan = frame.masks.bool(), float("nan")
    pairs = ordered_pairs(alone.masks, alone.nearest_depth, frame.depth_min)
    return {
        "mask head": mask_iou(mask_head.bool(), true, nan).tolist(),
        "mesh (no occlusion)": mask_iou(alone.masks, true, nan).tolist(),
        "meshes together (usl-eval)": mask_iou(together.masks, true, nan).tolist(),
        "meshes together, true object order": mask_iou(
            object_order_masks(alone.depth_map, frame.depth_min), true, nan
        ).tolist(),
        "meshes together, true owner wins": mask_iou(owner_wins_masks(alone.depth_map, true), true, nan).tolist(),
        "inscribed ellipse": mask_iou(inscribed_ellipses(frame.boxes, height, width), true, nan).tolist(),
    }, pairs


def main() -> None:
    args = parse_args(__doc__.splitlines()[0])
    model, cfg = load_model(args)
    totals: dict[str, list[float]] = {}
    right = total = 0
    for frame, _ in input_frames(args, cfg.data.max_size):
        ious, (frame_right, frame_total) = frame_ious(model, frame)
        right, total = right + frame_right, total + frame_total
        for name, values in ious.items():
            totals.setdefault(name, []).extend(values)
    print(f"| {args.data} ({args.split}, {args.input_views}) | mean mask IoU given the true box | objects |")
    print("|:---|:---:|:---:|")
    for name, values in totals.items():
        kept = torch.tensor(values)
        kept = kept[~kept.isnan()]
        print(f"| {name} | {100 * kept.mean():.1f} | {len(kept)} |")
    print(
        f"\nPairs of overlapping meshes whose predicted nearest depths order them as the true ones do: {right} of {total}"
    )


if __name__ == "__main__":
    main()
