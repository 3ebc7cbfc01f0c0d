"""Ground-truth object meshes (the Scene-Shapes objects table) in an input camera's frame.

Shared by evaluation (3D metrics, oracle baselines) and by 3D-supervised training
(``loss.supervision=3d``), so both see exactly the same true shape and layout.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Sequence

import torch

from usl.geometry.cameras import rigid_inverse, transform_points
from usl.records import object_mesh
from usl.errors import UslError

Tensor = torch.Tensor


@dataclass
class TrueMesh:
    """A ground-truth object mesh in the *input view's* camera frame (Scene-Shapes objects table)."""

    verts: Tensor  # (V, 3) float32, metres
    faces: Tensor  # (F, 3) int64

    def apply(self, fn: Callable[[Tensor], Tensor]) -> TrueMesh:
        return TrueMesh(fn(self.verts), fn(self.faces))


def true_meshes_in_camera(object_rows: Sequence[dict[str, Any]], cam_to_world: Tensor) -> dict[int, TrueMesh]:
    """Objects-table meshes (world frame) moved into a camera's frame: X_cam = inv(cam_to_world) X_world."""
    world_to_cam = rigid_inverse(cam_to_world.double().cpu())
    out = {}
    for row in object_rows:
        verts, faces = object_mesh(row)
        cam = transform_points(torch.from_numpy(verts).double(), world_to_cam).float()
        out[int(row["instance_id"])] = TrueMesh(verts=cam, faces=torch.from_numpy(faces).long())
    return out


def object_true_meshes(
    object_rows: Sequence[dict[str, Any]], instance_ids: Sequence[int], cam_to_world: Tensor, where: str
) -> list[TrueMesh]:
    """The true mesh of each of ``instance_ids``, in order; a missing or empty one is a ``UslError``
    naming ``where`` (the records folder or shard and the scene), since training on it is impossible."""
    meshes = true_meshes_in_camera(object_rows, cam_to_world)
    out = []
    for instance_id in instance_ids:
        mesh = meshes.get(int(instance_id))
        if mesh is None or len(mesh.faces) == 0:
            problem = "no row in the objects table" if mesh is None else "an empty mesh (no faces)"
            raise UslError(
                f"{where}: instance {int(instance_id)} has {problem}; loss.supervision=3d needs a true mesh per object"
            )
        out.append(mesh)
    return out
