"""How jagged are a model's meshes, and which stage of the shape head makes them so?

Per object of a build's input views, given the TRUE box, two figures of the predicted mesh in the
normalized cube after each stage of the shape head (the global stage first, where the recipe has
one), next to the ico-sphere's own:
- normal consistency, ``1 - cos`` of the angle between the normals of the two faces on each edge,
  averaged over the edges (PyTorch3D's ``mesh_normal_consistency``): folds and spikes raise it, a
  smooth mesh stays near the sphere's, however it is stretched;
- the mean length of the uniform Laplacian ``v_i - mean(neighbours of v_i)``, which curvature
  raises as well as spikes.
The pictures show the same; this puts numbers on it and says which stage to blame.

    python3 scripts/experiments/mesh_roughness.py HELDOUT_BUILD RUN_OR_CHECKPOINT
        [--split train] [--input-views every:8]
"""

from __future__ import annotations

import torch
from diagnostic_inputs import input_frames, load_model, parse_args

from usl.geometry import faces_on_each_edge, uniform_laplacian
from usl.losses import normal_consistency

Tensor = torch.Tensor


def laplacian_length(verts: Tensor, laplacian: Tensor) -> Tensor:
    """(N,): mean ‖(L v)_i‖ over the vertices of each of the (N, V, 3) meshes."""
    count, num_verts, _ = verts.shape
    columns = verts.permute(1, 0, 2).reshape(num_verts, 3 * count)  # every mesh at once: L is shared
    lap = torch.sparse.mm(laplacian, columns).view(num_verts, count, 3)
    return lap.norm(dim=-1).mean(dim=0)


def roughness(verts: Tensor, faces: Tensor, pairs: Tensor, laplacian: Tensor) -> Tensor:
    """(N, 2): normal consistency and Laplacian length of each mesh."""
    return torch.stack([normal_consistency(verts, faces, pairs), laplacian_length(verts, laplacian)], dim=1)


@torch.no_grad()
def main() -> None:
    args = parse_args(__doc__.splitlines()[0])
    model, cfg = load_model(args)
    head = model.shape_head
    pairs = faces_on_each_edge(head.faces)
    laplacian = uniform_laplacian(len(head.sphere_verts), head.edges)
    names = (["the global stage"] if head.global_mlp is not None else []) + [
        f"stage {i + 1}" for i in range(len(head.stages))
    ]
    per_stage: list[list[Tensor]] = [[] for _ in names]
    for frame, _ in input_frames(args, cfg.data.max_size):
        _, features = model._backbone([frame])
        shape = model.objects(features, [frame.boxes], [frame.labels], [frame.K]).shape
        for values, verts in zip(per_stage, shape.stage_verts, strict=True):
            values.append(roughness(verts.float(), head.faces, pairs, laplacian))
    sphere = roughness(head.sphere_verts[None], head.faces, pairs, laplacian)[0]
    header = f"| {args.data} ({args.split}, {args.input_views}), true boxes, in the cube"
    print(f"{header} | normal consistency ↓ | mean ‖Lv‖ | objects |")
    print("|:---|:---:|:---:|:---:|")
    print(f"| ico-sphere (level {cfg.model.shape.ico_level}) | {sphere[0]:.3f} | {sphere[1]:.3f} | – |")
    for name, values in zip(names, per_stage, strict=True):
        table = torch.cat(values)
        means = table.mean(dim=0)
        print(f"| after {name} | {means[0]:.3f} | {means[1]:.3f} | {len(table)} |")


if __name__ == "__main__":
    main()
