"""Shape models from a user's folder of meshes (ShapeNet-style ``<category folder>/<model>/...``).

Layout: every top-level folder of the root named in the category map holds that category's
models; each mesh file found under it (any depth) is one model whose ``source_id`` is its path
relative to the root, e.g. ``03001627/1a6f615e8b1b5ae4dbbc9440457e303e/models/model_normalized.obj``.
Top-level folders that the map does not name are not used and are reported.

Normalisation, applied in this order (documented in the CLI help):
1. up axis: the mesh's ``--up-axis`` (default +y) is rotated onto +Y;
2. scale (``--mesh-scale``): "category" (default) scales uniformly so the bounding-box diagonal
   equals a plausible metric size for the category (``DEFAULT_DIAGONAL_M``, overridable in the
   map file), which suits unit-normalised sets such as ShapeNet; "none" keeps metric meshes as is;
3. grounding: lowest point on y = 0, bounding box centred on x = z = 0.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np
import trimesh
import yaml

from usl.errors import UslError

from .primitives import BODY
from .shapes import CATEGORIES, ModelRef, ShapeModel, ground

MESH_SUFFIXES = (".obj", ".glb", ".gltf", ".ply", ".off", ".stl")
# Bounding-box diagonals of typical pieces: dining chair 0.5x0.9x0.5 m (~1.15), three-seat sofa
# 2.0x0.85x0.9 m (~2.35) and loveseat (~1.9), dining table 1.4x0.75x0.85 m (~1.8), coffee table (~1.3).
DEFAULT_DIAGONAL_M = {"chair": 1.15, "sofa": 2.2, "table": 1.6}
UP_AXES = ("+x", "-x", "+y", "-y", "+z", "-z")
SCALE_MODES = ("category", "none")

# Rotations taking each possible up axis onto +Y (right-handed, det = +1).
_UP_TO_Y = {
    "+y": np.eye(3),
    "-y": np.diag([1.0, -1.0, -1.0]),
    "+z": np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]),
    "-z": np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]),
    "+x": np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),
    "-x": np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),
}


@dataclass(frozen=True)
class MeshNormalisation:
    """How raw mesh files become metric, +Y-up, grounded models (hashable: part of cache keys)."""

    up_axis: str = "+y"
    scale: str = "category"
    diagonals: tuple[tuple[str, float], ...] = tuple(sorted(DEFAULT_DIAGONAL_M.items()))


@dataclass
class CategoryMap:
    folders: dict[str, str]  # top-level folder name (e.g. a ShapeNet synset id) -> our category
    diagonals: dict[str, float] = field(default_factory=lambda: dict(DEFAULT_DIAGONAL_M))


def load_category_map(path: Path) -> CategoryMap:
    """Read a YAML/JSON category map: ``{folder: category}``, or
    ``{categories: {folder: category}, target_diagonal_m: {category: metres}}``.

    Everything is read as strings first (YAML would turn the synset id 03001627 into an octal number).
    """
    try:
        raw = yaml.load(Path(path).read_text(), Loader=yaml.BaseLoader)
    except (OSError, yaml.YAMLError) as exc:
        raise UslError(f"{path}: cannot read the category map: {exc}") from exc
    if not isinstance(raw, dict) or not raw:
        raise UslError(f"{path}: the category map must be a non-empty mapping of folder names to categories")
    if isinstance(raw.get("categories"), dict):
        folders, overrides = raw["categories"], raw.get("target_diagonal_m") or {}
    else:
        folders, overrides = raw, {}
    if not isinstance(overrides, dict):
        raise UslError(f"{path}: target_diagonal_m must map categories to metres")
    diagonals = dict(DEFAULT_DIAGONAL_M)
    for category, value in overrides.items():
        try:
            diagonals[category] = float(value)
        except (TypeError, ValueError) as exc:
            raise UslError(f"{path}: target_diagonal_m[{category}] = {value!r} is not a number") from exc
        if not diagonals[category] > 0:
            raise UslError(f"{path}: target_diagonal_m[{category}] must be positive")
    for folder, category in folders.items():
        if category not in CATEGORIES:
            raise UslError(
                f"{path}: folder {folder!r} maps to unknown category {category!r} (known: {', '.join(CATEGORIES)})"
            )
    unknown = set(diagonals) - set(CATEGORIES)
    if unknown:
        raise UslError(f"{path}: target_diagonal_m names unknown categories {sorted(unknown)}")
    return CategoryMap({str(k): str(v) for k, v in folders.items()}, diagonals)


def discover_models(
    root: Path, category_map: CategoryMap, empty_is_error: bool = True
) -> tuple[list[ModelRef], list[str]]:
    """All mesh files under the mapped folders of ``root``, sorted; and the unmapped folder names.

    Empty (0-byte) files fail here, before any rendering, unless ``empty_is_error`` is False; then
    they stay in the pool and the scenes using them are skipped and recorded like other unreadable files.
    """
    root = Path(root)
    if not root.is_dir():
        raise UslError(f"--mesh-root {root} is not a directory")
    folders = sorted(p.name for p in root.iterdir() if p.is_dir())
    missing = sorted(set(category_map.folders) - set(folders))
    if missing:
        raise UslError(f"{root}: the category map names folders that do not exist here: {missing}")
    refs: list[ModelRef] = []
    for folder in folders:
        if folder not in category_map.folders:
            continue
        files = sorted(p for p in (root / folder).rglob("*") if p.suffix.lower() in MESH_SUFFIXES and p.is_file())
        if not files:
            raise UslError(f"{root / folder}: no mesh files ({', '.join(MESH_SUFFIXES)}) under this category folder")
        for file in files:
            if empty_is_error and file.stat().st_size == 0:
                raise UslError(f"{file}: empty mesh file (0 bytes); remove it or fix it")
            refs.append(ModelRef(file.relative_to(root).as_posix(), category_map.folders[folder], str(file)))
    return refs, [f for f in folders if f not in category_map.folders]


def read_mesh(path: str) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and faces of a mesh file (scenes are flattened); a UslError naming the file otherwise."""
    try:
        mesh = trimesh.load(path, force="mesh", skip_materials=True)  # colours are ours; textures only cost time
    except Exception as exc:  # trimesh raises many types for malformed files
        raise UslError(f"{path}: cannot read mesh: {type(exc).__name__}: {exc}") from exc
    faces = np.asarray(getattr(mesh, "faces", np.zeros((0, 3))), dtype=np.int64)
    vertices = np.asarray(getattr(mesh, "vertices", np.zeros((0, 3))), dtype=np.float64)
    if len(faces) == 0 or len(vertices) == 0:
        raise UslError(f"{path}: mesh has no triangles")
    if not np.isfinite(vertices).all():
        raise UslError(f"{path}: mesh has non-finite vertex coordinates")
    return vertices, faces


@lru_cache(maxsize=64)
def load_mesh_model(ref: ModelRef, normalisation: MeshNormalisation) -> ShapeModel:
    """A --mesh-root model, rotated to +Y up, scaled to metres and grounded."""
    if ref.path is None:
        raise UslError(f"{ref.source_id}: not a mesh-root model (no file path)")
    vertices, faces = read_mesh(ref.path)
    vertices = vertices @ _UP_TO_Y[normalisation.up_axis].T
    if normalisation.scale == "category":
        diagonal = float(np.linalg.norm(vertices.max(axis=0) - vertices.min(axis=0)))
        if diagonal <= 0:
            raise UslError(f"{ref.path}: mesh is degenerate (zero-size bounding box)")
        vertices = vertices * (dict(normalisation.diagonals)[ref.category] / diagonal)
    model = ShapeModel(
        ref.source_id, ref.category, ground(vertices), faces, np.full(len(vertices), BODY, dtype=np.uint8)
    )
    for array in (model.vertices, model.faces, model.vertex_roles):
        array.flags.writeable = False
    return model


def dump_category_map(category_map: CategoryMap) -> str:
    """Canonical JSON of a map, for the dataset fingerprint."""
    return json.dumps({"categories": category_map.folders, "target_diagonal_m": category_map.diagonals}, sort_keys=True)
