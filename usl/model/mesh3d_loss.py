"""L_3D of the 3D-supervised baseline (``loss.supervision=3d``): Mesh R-CNN's losses against the
objects table's true meshes instead of the multi-view silhouette loss.

Each refinement stage's mesh is cast into the input camera's frame by the same frustum map as the
prediction and compared with the object's true mesh in that frame, so the layout (z, rho) is
supervised together with the shape. As in Mesh R-CNN, the terms are averaged over the stages and
weighted by its ShapeNet config (``MESH_RCNN_SHAPENET``). Normalised like the 2D L_3D: a mean
over each image's objects, then over the batch (images without objects count 0), so DDP's
averaging of per-GPU losses gives exactly the whole batch's gradient.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from usl.data.samples import MultiViewSample
from usl.geometry import Meshes, sample_points_from_meshes
from usl.losses import chamfer_normal_loss, mesh_edge_loss

Tensor = torch.Tensor


@dataclass(frozen=True)
class Mesh3DLossWeights:
    chamfer: float  # Chamfer-L2 between points on the predicted and the true mesh (m^2)
    normals: float  # 1 - |cos| between the normals of nearest point pairs, both ways
    edge: float  # squared edge length of the predicted mesh in the camera frame (m^2)
    num_samples: int  # points sampled on each predicted and each true mesh


# Mesh R-CNN's configs/shapenet: CHAMFER_LOSS_WEIGHT 1.0, NORMALS_LOSS_WEIGHT 0.0, EDGE_LOSS_WEIGHT 0.2,
# GT_NUM_SAMPLES = PRED_NUM_SAMPLES = 5000: the baseline is that model's losses, so they are fixed
MESH_RCNN_SHAPENET = Mesh3DLossWeights(chamfer=1.0, normals=0.0, edge=0.2, num_samples=5000)


def mesh_supervision_loss(
    stage_verts_cam: list[Tensor],
    faces: Tensor,
    samples: list[MultiViewSample],
    counts: list[int],
    cfg: Mesh3DLossWeights = MESH_RCNN_SHAPENET,
) -> tuple[Tensor, dict[str, Tensor]]:
    """``(L_3D, stats)`` for a batch. ``stage_verts_cam[s]`` (N, V, 3) holds stage s's meshes of all
    objects in their input camera's frame, sample by sample (``counts[i]`` objects of sample i, in
    the order of its ``true_meshes``). Stats: the unweighted ``chamfer3d``, ``normals3d``, ``edge3d``."""
    zero = stage_verts_cam[-1].sum() * 0.0
    terms = {"chamfer3d": zero, "normals3d": zero, "edge3d": zero}
    starts = torch.tensor([0] + counts).cumsum(0).tolist()
    scale = 1.0 / (len(stage_verts_cam) * len(samples))
    for index, sample in enumerate(samples):
        rows = slice(starts[index], starts[index + 1])
        if counts[index] == 0:
            continue
        if sample.true_meshes is None or len(sample.true_meshes) != counts[index]:
            raise ValueError(
                "mesh_supervision_loss: samples need one true mesh per object (MultiViewDataset(with_true_meshes=True))"
            )
        generator = torch.Generator(device=zero.device).manual_seed(sample.seed)
        true = Meshes([m.verts.float() for m in sample.true_meshes], [m.faces for m in sample.true_meshes])
        with torch.no_grad():
            true_points, true_normals = sample_points_from_meshes(true, cfg.num_samples, generator, return_normals=True)
        for verts in stage_verts_cam:
            meshes = Meshes.from_shared_topology(verts[rows].float(), faces)
            points, normals = sample_points_from_meshes(meshes, cfg.num_samples, generator, return_normals=True)
            chamfer, normal = chamfer_normal_loss(points, normals, true_points, true_normals)
            terms["chamfer3d"] = terms["chamfer3d"] + chamfer.mean() * scale
            terms["normals3d"] = terms["normals3d"] + normal.mean() * scale
            terms["edge3d"] = terms["edge3d"] + mesh_edge_loss(meshes) * scale
    l3d = cfg.chamfer * terms["chamfer3d"] + cfg.normals * terms["normals3d"] + cfg.edge * terms["edge3d"]
    return l3d, {name: value.detach() for name, value in terms.items()}
