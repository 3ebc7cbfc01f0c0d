"""The weighted training objective ``L = mu_2d L_2D + mu_3D L_3D + mu_reg L_reg`` (paper, Appendix).

Here L_2D is Mask R-CNN's detection losses (RPN and box head), L_3D the mean of the
per-pair ``l2d_loss`` over objects and views, and
``mu_reg L_reg = edge * L_edge + offset_l2 * ½‖dV‖² + laplacian * L_laplac + normal * L_normal``
(normal consistency is not in the paper: an option). Inside L_3D,
``dist`` weighs l_dist (``l_2D = dist * l_dist + 1[IoU > t] l_xent``): 0 is Table 1's "w/o l_dist".

The paper's recipes (``LossWeights.recipe(name)``):

* Scene-Shapes: ``L = L_3D + 0.1 L_edge`` (no detection losses, as Mesh R-CNN on ShapeNet);
* Hypersim:     ``L = L_2D + 1.0 L_3D + 0.05 ½‖dV‖²`` (dV before the tanh);
* ScanNet:      ``L = L_2D + 1.0 L_3D + 0.05 ½‖dV‖² + 0.1 L_laplac``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

import torch

Tensor = torch.Tensor


@dataclasses.dataclass(frozen=True)
class LossWeights:
    """Weights of L = mu_2d L_2D + mu_3d L_3D + the regularizers. The defaults are the paper's Hypersim
    weights (its Appendix C); the recipes (``usl/configs``) set what differs from them."""

    mu_2d: float = 1.0  # Mask R-CNN detection losses (summed); 0 leaves the RPN and RoI heads untrained
    mu_3d: float = 1.0  # multi-view silhouette loss L_3D, against the detection losses
    edge: float = 0.0  # L_edge, Mesh R-CNN's edge length (paper: 0.1 on Scene-Shapes)
    offset_l2: float = 0.05  # ½‖dV‖² on the pre-tanh offsets (paper: 0.05 on Hypersim and ScanNet)
    laplacian: float = 0.0  # uniform Laplacian smoothing (paper: 0.1 on ScanNet)
    normal: float = 0.0  # normal consistency between neighbouring faces: against folds, for smoother meshes
    dist: float = 1.0  # l_dist in L_3D (x loss.dist_scale); 0: Table 1's "w/o l_dist", not computed at all
    # SoftRas's soft IoU next to l_xent, under its gate: each pair counts by its own union, so thin parts
    # weigh as much as bulky ones
    soft_iou: float = 0.0


def combine_losses(
    weights: LossWeights,
    l3d: Tensor,
    detection: Mapping[str, Tensor] | None = None,
    edge: Tensor | None = None,
    offset_l2: Tensor | None = None,
    laplacian: Tensor | None = None,
    normal: Tensor | None = None,
) -> tuple[Tensor, dict[str, Tensor]]:
    """Weighted sum of the objective's terms.

    A term may be None only if its weight is zero (the caller then need not compute it);
    a non-zero weight without its term is an error, so a recipe cannot silently lose a term.
    Returns the total and a dict of the weighted parts (for logging), keyed
    ``"det/<name>"``, ``"l3d"``, ``"edge"``, ``"offset_l2"``, ``"laplacian"``, ``"normal"``.
    """
    parts: dict[str, Tensor] = {}
    if weights.mu_2d:
        if detection is None:
            raise ValueError("combine_losses: mu_2d is non-zero but no detection losses were given")
        for name, value in detection.items():
            parts[f"det/{name}"] = weights.mu_2d * value
    parts["l3d"] = weights.mu_3d * l3d
    regularizers = {
        "edge": edge,
        "offset_l2": offset_l2,
        "laplacian": laplacian,
        "normal": normal,
    }
    for name, term in regularizers.items():
        weight = getattr(weights, name)
        if not weight:
            continue
        if term is None:
            raise ValueError(f"combine_losses: weight {name}={weight} is non-zero but the term was not given")
        parts[name] = weight * term
    return sum(parts.values()), parts
