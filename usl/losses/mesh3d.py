"""Mesh R-CNN's 3D mesh losses (its ``MeshLoss``), for the 3D-supervised upper bound of Table 1.

Between points sampled on a predicted and on a true mesh, as Mesh R-CNN computes them with
PyTorch3D's ``chamfer_distance``: Chamfer-L2 is the mean squared distance from each point to the
nearest point of the other set, both ways, summed; the normal term is ``1 - |cos|`` between the
normals of each point and of its nearest neighbour, averaged, both ways, summed (the absolute value
makes it blind to face winding, which the frustum map may flip). Its third term, the edge length,
is ``usl.losses.mesh_edge_loss`` on the predicted mesh.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from usl.geometry.nearest import DEFAULT_MAX_ELEMENTS, nearest_neighbors

Tensor = torch.Tensor


class ChamferNormal(NamedTuple):
    chamfer: Tensor  # (B,) Chamfer-L2, in the points' unit squared
    normals: Tensor  # (B,) 1 - |cos| between nearest points' normals, both ways (0..2)


def chamfer_normal_loss(
    pred_points: Tensor,
    pred_normals: Tensor,
    true_points: Tensor,
    true_normals: Tensor,
    max_elements: int = DEFAULT_MAX_ELEMENTS,
    backend: str = "auto",
) -> ChamferNormal:
    """Per-pair Chamfer-L2 and normal terms between (B, N, 3) and (B, M, 3) point sets with unit
    normals, differentiable w.r.t. the predicted points and normals (and the true ones).

    ``backend`` finds the neighbours (``nearest_neighbors``): "auto" uses scipy's k-d tree on CPU,
    where brute force over Mesh R-CNN's 5000 x 5000 points per object costs seconds per step."""
    pred_to_true, pred_nn = nearest_neighbors(pred_points, true_points, max_elements=max_elements, backend=backend)
    true_to_pred, true_nn = nearest_neighbors(true_points, pred_points, max_elements=max_elements, backend=backend)
    chamfer = pred_to_true.mean(1) + true_to_pred.mean(1)
    normals = _normal_term(pred_normals, true_normals, pred_nn) + _normal_term(true_normals, pred_normals, true_nn)
    return ChamferNormal(chamfer, normals)


def _normal_term(normals: Tensor, other: Tensor, nearest: Tensor) -> Tensor:
    """(B,) mean over points of 1 - |cos(normal, normal of its nearest point in the other set)|."""
    matched = torch.gather(other, 1, nearest.unsqueeze(-1).expand(-1, -1, 3))
    return (1.0 - torch.nn.functional.cosine_similarity(normals, matched, dim=-1, eps=1e-12).abs()).mean(1)
