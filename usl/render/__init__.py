"""Pure-torch rasterizers: sparse soft silhouettes, dynamic (per-object window) rendering,
and a z-buffer for evaluation. Camera conventions: ``usl.geometry.cameras`` (docs/design.md §2).

Inputs are packed tensors, so a ``usl.geometry.meshes.Meshes`` batch plugs in as
``(meshes.verts_packed(), meshes.faces_packed(), meshes.faces_packed_to_mesh_idx())``.
"""

from usl.render.dynamic import DynamicRender, render_dynamic
from usl.render.hard import HardRender, rasterize_hard
from usl.render.masks import PaddedMasks
from usl.render.resample import resample_masks_area
from usl.render.soft import SoftRasterSettings, rasterize_soft, rasterize_soft_dense

__all__ = [
    "DynamicRender",
    "HardRender",
    "PaddedMasks",
    "SoftRasterSettings",
    "rasterize_hard",
    "rasterize_soft",
    "rasterize_soft_dense",
    "render_dynamic",
    "resample_masks_area",
]
