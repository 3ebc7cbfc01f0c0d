"""How much of a model's 3D error is placement, and how much is shape?

Per object of a build's input views, given the TRUE box, Mesh R-CNN's Chamfer-L2 and F1@0.1 between
the predicted and the true mesh in the input camera's frame (usl-eval's figures), then the same after
moving the prediction so that the centroids of the two point samples coincide (shape alone), and
after moving it along the camera's z axis only (shape and image-plane placement, with the depth
error removed). A large drop from the first to the second says the layout, not the shape head,
holds the Chamfer back.

    python3 scripts/experiments/placement_chamfer.py HELDOUT_BUILD RUN_OR_CHECKPOINT
        [--split train] [--input-views every:8]
"""

from __future__ import annotations

import torch
from diagnostic_inputs import input_frames, load_model, parse_args

from usl.evaluation.targets import true_meshes_in_camera
from usl.geometry import Meshes
from usl.geometry.sampling import sample_points_from_meshes
from usl.metrics.shape3d import NUM_EVAL_SAMPLES, chamfer_f1

Tensor = torch.Tensor


def aligned_scores(pred: Tensor, true: Tensor) -> dict[str, tuple[Tensor, Tensor]]:
    """(Chamfer-L2, F1@0.1) per pair of (B, N, 3) point samples: as they are, centroid-aligned, and
    aligned in camera z only."""
    shift = true.mean(1, keepdim=True) - pred.mean(1, keepdim=True)
    depth_only = shift * torch.tensor([0.0, 0.0, 1.0])
    out = {}
    for name, moved in (
        ("as predicted", pred),
        ("centroids aligned", pred + shift),
        ("depth aligned", pred + depth_only),
    ):
        scores = chamfer_f1(moved, true, thresholds=0.1)
        out[name] = (scores["Chamfer-L2"], scores["F1@0.1"])
    return out


@torch.no_grad()
def frame_scores(model, frame, objects, generator: torch.Generator) -> dict[str, tuple[Tensor, Tensor]]:
    true_meshes = true_meshes_in_camera(objects, frame.cam_to_world)
    keep = [i for i, iid in enumerate(frame.instance_ids.tolist()) if iid in true_meshes]
    if not keep:
        return {}
    _, features = model._backbone([frame])
    verts = model.objects(features, [frame.boxes[keep]], [frame.labels[keep]], [frame.K]).verts_cam
    pred = Meshes.from_shared_topology(verts, model.faces)
    chosen = [true_meshes[int(frame.instance_ids[i])] for i in keep]
    true = Meshes([m.verts for m in chosen], [m.faces for m in chosen])
    return aligned_scores(
        sample_points_from_meshes(pred, NUM_EVAL_SAMPLES, generator),
        sample_points_from_meshes(true, NUM_EVAL_SAMPLES, generator),
    )


def main() -> None:
    args = parse_args(__doc__.splitlines()[0])
    model, cfg = load_model(args)
    generator = torch.Generator().manual_seed(0)
    totals: dict[str, list[Tensor]] = {}
    for frame, objects in input_frames(args, cfg.data.max_size):
        if objects:
            for name, (chamfer, f1) in frame_scores(model, frame, objects, generator).items():
                totals.setdefault(name, []).append(torch.stack([chamfer, f1], dim=1))
    print(f"| {args.data} ({args.split}, {args.input_views}), true boxes | Ch. ↓ | F1@0.1 | objects |")
    print("|:---|:---:|:---:|:---:|")
    for name, values in totals.items():
        table = torch.cat(values)
        print(f"| {name} | {table[:, 0].mean():.3f} | {table[:, 1].mean():.1f} | {len(table)} |")


if __name__ == "__main__":
    main()
