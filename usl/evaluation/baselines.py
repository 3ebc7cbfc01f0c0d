"""Baselines of the paper's tables (Sec. 4), as predictors producing ``ObjectPredictions``.

Every baseline object is a sphere: the unit ico-sphere of the normalized cube mapped into the
object's frustum (true 2D box, K, depth z, depth extent rho) by the frustum homography of
docs/design.md §5 -- the same map the model's shape head goes through, so a baseline differs from the
model only in where z and rho come from and in not deforming the sphere.

* ``RandomDepthBaseline``: z and rho uniform in the dataset spec's ranges, drawn per object from a
  seed derived from (seed, scene, view), so scores do not depend on evaluation order.
* ``FixedDepthBaseline``: the spec's fixed z and rho.
* ``LayoutOnly(inner)``: spheres at another predictor's layout (its boxes, z, rho). The paper
  *trained* layout-only models; this row measures a trained model's layout with its shapes removed.
* ``TrueDepth(inner)``: the paper's "oracle depth" ablation (Table 3c): the inner predictor's
  objects moved to the true depth, shapes kept in normalized space (the cube coordinates are
  recovered with the inverse homography and mapped again with the true z and the inner rho).
  The true z is, per object (``source``):
  - ``"centre"``: the middle of the true mesh's depth range in the input camera (needs the
    objects table, i.e. Scene-Shapes), which is exactly the frustum's z for a tight frustum;
  - ``"nearest"``: ``depth_min + rho / 2``, i.e. the frustum's near plane placed at the object's
    true nearest visible depth (any dataset with depth);
  - ``"auto"``: ``"centre"`` where the object has a true mesh, else ``"nearest"``.
  Objects without either keep their predicted z. Depths here are homogeneous depths (K's third
  row), which equal planar z for every upper-triangular K.
  With ``extent``, rho too becomes the true mesh's depth range where the object has a true mesh:
  the whole layout true, so what is left of the error is the shape in the normalized cube.
"""

from __future__ import annotations

import zlib
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import torch

from usl.evaluation.baseline_options import DEFAULT_SPHERE_LEVEL, TRUE_DEPTH_SOURCES
from usl.evaluation.types import EvalInput, Predictor
from usl.geometry import cube_to_frustum, frustum_to_cube, ico_sphere
from usl.model.outputs import ObjectPredictions

Tensor = torch.Tensor

# The model's initial mesh is a level-3 ico-sphere (paper, Appendix tables); baselines use the same.


def stable_seed(*parts: Any) -> int:
    """A seed that depends only on ``parts`` (not on Python's per-process string hashing)."""
    return zlib.crc32(repr(parts).encode("utf-8"))


def sphere_verts(
    boxes: Tensor, K: Tensor, z: Tensor, rho: Tensor, level: int = DEFAULT_SPHERE_LEVEL
) -> tuple[Tensor, Tensor]:
    """Ico-spheres filling each object frustum: verts (N, V, 3) in the camera frame, faces (F, 3)."""
    unit, faces = ico_sphere(level, dtype=torch.float32, device=boxes.device)
    cube = unit.expand(boxes.shape[0], -1, -1)
    verts = cube_to_frustum(cube, boxes.float(), K.float(), z.float(), rho.float())
    return verts, faces


def sphere_predictions(inp: EvalInput, z: Tensor, rho: Tensor, level: int = DEFAULT_SPHERE_LEVEL) -> ObjectPredictions:
    """One sphere per ground-truth instance of the input view, at depths ``z`` with extents ``rho``."""
    frame = inp.frame
    verts, faces = sphere_verts(frame.boxes, frame.K, z, rho, level)
    return ObjectPredictions(
        boxes=frame.boxes.float().clone(),
        labels=frame.labels.clone(),
        scores=torch.ones(len(frame.instance_ids)),
        z=z.float(),
        rho=rho.float(),
        verts=verts,
        faces=faces,
        instance_ids=frame.instance_ids.clone(),
    )


@dataclass
class FixedDepthBaseline:
    """Spheres at the spec's fixed depth z with extent rho (paper: "Fixed depth")."""

    z: float
    rho: float
    level: int = DEFAULT_SPHERE_LEVEL
    name: str = "Fixed depth"
    predicts_layout: bool = field(default=False, init=False)
    predicts_shape: bool = field(default=False, init=False)
    uses_detections: bool = field(default=False, init=False)

    def __call__(self, inputs: Sequence[EvalInput]) -> list[ObjectPredictions]:
        out = []
        for inp in inputs:
            n = len(inp.frame.instance_ids)
            out.append(
                sphere_predictions(inp, torch.full((n,), float(self.z)), torch.full((n,), float(self.rho)), self.level)
            )
        return out


@dataclass
class RandomDepthBaseline:
    """Spheres at z ~ U(z_range) with extent rho ~ U(rho_range) (paper: "Random depth")."""

    z_range: tuple[float, float]
    rho_range: tuple[float, float]
    seed: int = 0
    level: int = DEFAULT_SPHERE_LEVEL
    name: str = "Random depth"
    predicts_layout: bool = field(default=False, init=False)
    predicts_shape: bool = field(default=False, init=False)
    uses_detections: bool = field(default=False, init=False)

    def __call__(self, inputs: Sequence[EvalInput]) -> list[ObjectPredictions]:
        out = []
        for inp in inputs:
            n = len(inp.frame.instance_ids)
            gen = torch.Generator().manual_seed(stable_seed(self.seed, inp.frame.scene_id, inp.frame.view_id))
            u = torch.rand(n, 2, generator=gen, dtype=torch.float64)
            (z0, z1), (r0, r1) = self.z_range, self.rho_range
            out.append(sphere_predictions(inp, z0 + u[:, 0] * (z1 - z0), r0 + u[:, 1] * (r1 - r0), self.level))
        return out


@dataclass
class LayoutOnly:
    """Spheres at ``inner``'s predicted layout (boxes, z, rho): its shapes are thrown away."""

    inner: Predictor
    level: int = DEFAULT_SPHERE_LEVEL
    name: str = ""

    def __post_init__(self) -> None:
        self.name = self.name or f"Layout-only ({self.inner.name})"
        self.predicts_layout = self.inner.predicts_layout
        self.predicts_shape = False
        self.uses_detections = self.inner.uses_detections

    def __call__(self, inputs: Sequence[EvalInput]) -> list[ObjectPredictions]:
        out = []
        for inp, pred in zip(inputs, self.inner(inputs), strict=True):
            K = inp.frame.K.to(pred.boxes.device)
            verts, faces = sphere_verts(pred.boxes, K, pred.z, pred.rho, self.level)
            out.append(replace(pred, verts=verts, faces=faces))
        return out


@dataclass
class TrueDepth:
    """``inner``'s objects moved to the true depth (paper Table 3c, "oracle depth"), and with
    ``extent`` given the true depth extent too."""

    inner: Predictor
    source: str = "auto"
    name: str = ""
    extent: bool = False

    def __post_init__(self) -> None:
        if self.source not in TRUE_DEPTH_SOURCES:
            raise ValueError(f"true depth source must be one of {TRUE_DEPTH_SOURCES}, got {self.source!r}")
        if self.inner.uses_detections:
            raise ValueError(
                f"TrueDepth needs one prediction per ground-truth object; {self.inner.name!r} detects its own"
            )
        self.name = self.name or f"{self.inner.name} w/ true depth{' and extent' if self.extent else ''}"
        self.predicts_layout = False
        self.predicts_shape = self.inner.predicts_shape
        self.uses_detections = False

    def __call__(self, inputs: Sequence[EvalInput]) -> list[ObjectPredictions]:
        out = []
        for inp, pred in zip(inputs, self.inner(inputs), strict=True):
            K = inp.frame.K.to(pred.verts.device).float()
            z_true = true_depth(inp, pred.instance_ids, pred.rho, self.source).to(pred.z.device)
            z_new = torch.where(torch.isfinite(z_true), z_true, pred.z)
            rho_new = pred.rho
            if self.extent:
                rho_true = true_extent(inp, pred.instance_ids).to(pred.rho.device)
                rho_new = torch.where(torch.isfinite(rho_true), rho_true, pred.rho)
            cube = frustum_to_cube(pred.verts, pred.boxes, K, pred.z, pred.rho)
            verts = cube_to_frustum(cube, pred.boxes, K, z_new, rho_new)
            out.append(replace(pred, z=z_new, rho=rho_new, verts=verts))
        return out


def true_extent(inp: EvalInput, instance_ids: Tensor) -> Tensor:
    """True depth extent rho of each object: its true mesh's range of homogeneous depth in the input
    camera (NaN for an object without a true mesh)."""
    near, far = _mesh_depth_range(inp, instance_ids)
    return (far - near).float()


def _mesh_depth_range(inp: EvalInput, instance_ids: Tensor) -> tuple[Tensor, Tensor]:
    """(N,) float64 nearest and farthest homogeneous depth (K's third row) of each object's true mesh
    in the input camera, NaN for an object without one."""
    K = inp.frame.K.double()
    near = torch.full((len(instance_ids),), float("nan"), dtype=torch.float64)
    far = near.clone()
    for n, iid in enumerate(instance_ids.tolist()):
        mesh = inp.true_meshes.get(int(iid))
        if mesh is not None:
            depth = (mesh.verts.double() @ K[2]).cpu()
            near[n], far[n] = depth.min(), depth.max()
    return near, far


def true_depth(inp: EvalInput, instance_ids: Tensor, rho: Tensor, source: str = "auto") -> Tensor:
    """True frustum depth z of each object (NaN where the source has no answer); see module doc."""
    frame = inp.frame
    position = {int(i): p for p, i in enumerate(frame.instance_ids.tolist())}
    near, far = _mesh_depth_range(inp, instance_ids)
    z = torch.full((len(instance_ids),), float("nan"), dtype=torch.float64)
    for n, iid in enumerate(instance_ids.tolist()):
        if source in ("auto", "centre") and not near[n].isnan():
            z[n] = 0.5 * (near[n] + far[n])
        elif source in ("auto", "nearest") and int(iid) in position:
            z[n] = float(frame.depth_min[position[int(iid)]]) + 0.5 * float(rho[n])
    return z.float()


def spec_baselines(baselines: dict[str, Any], seed: int = 0, level: int = DEFAULT_SPHERE_LEVEL) -> dict[str, Predictor]:
    """The random- and fixed-depth baselines of a dataset spec's ``baselines`` entry."""
    out: dict[str, Predictor] = {}
    if "random_depth" in baselines:
        r = baselines["random_depth"]
        out["random"] = RandomDepthBaseline(tuple(r["z"]), tuple(r["rho"]), seed=seed, level=level)
    if "fixed_depth" in baselines:
        f = baselines["fixed_depth"]
        out["fixed"] = FixedDepthBaseline(float(f["z"]), float(f["rho"]), level=level)
    return out
