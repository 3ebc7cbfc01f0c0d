"""Shape models: the procedural furniture catalogue and the common in-memory model type.

A procedural model is a pure function of its ``source_id`` ("proc/<category>/<family>/<index>"):
the index seeds the family's parameters, so anyone can regenerate the exact mesh stored in a
dataset from the id alone. Every model is grounded the same way: +Y up, lowest point at y = 0,
bounding box centred on x = z = 0, metres.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from usl.errors import UslError

from . import chairs, sofas, tables
from .primitives import Part

CATEGORIES = ("chair", "sofa", "table")
FAMILIES: dict[str, dict[str, Callable[[np.random.Generator], list[Part]]]] = {
    "chair": chairs.FAMILIES,
    "sofa": sofas.FAMILIES,
    "table": tables.FAMILIES,
}
# Bump when any family changes what it builds: it is part of a dataset's fingerprint, so a
# dataset folder is never completed with meshes from a different generator.
GENERATOR_VERSION = 1
PROCEDURAL_PREFIX = "proc"
# Each build seed draws its procedural models from its own range of indices (seed x this, on): builds
# with other seeds share no shape model, so one can hold out shapes as well as scenes. Seed 0's
# models are indices 0, 1, ...
SEED_INDEX_STRIDE = 1_000_000


@dataclass(frozen=True)
class ModelRef:
    """A shape model as scenes refer to it: cheap to pickle into work units."""

    source_id: str
    category: str
    path: str | None = None  # mesh file of a --mesh-root model; None for procedural ones


@dataclass
class ShapeModel:
    """A grounded mesh: float64 (N, 3) vertices, int64 (M, 3) faces, and a per-vertex part role."""

    source_id: str
    category: str
    vertices: np.ndarray
    faces: np.ndarray
    vertex_roles: np.ndarray  # uint8 (N,), primitives.BODY or primitives.FRAME

    @property
    def extents(self) -> np.ndarray:
        return self.vertices.max(axis=0) - self.vertices.min(axis=0)


def ground(vertices: np.ndarray) -> np.ndarray:
    """Translate so the lowest point is on y = 0 and the bounding box is centred on x = z = 0."""
    low, high = vertices.min(axis=0), vertices.max(axis=0)
    offset = np.array([0.5 * (low[0] + high[0]), low[1], 0.5 * (low[2] + high[2])])
    return vertices - offset


def assemble(source_id: str, category: str, parts: list[Part]) -> ShapeModel:
    """Concatenate closed parts into one grounded model (the union is a set of closed shells)."""
    vertices, faces, roles, offset = [], [], [], 0
    for part in parts:
        vertices.append(np.asarray(part.mesh.vertices, dtype=np.float64))
        faces.append(np.asarray(part.mesh.faces, dtype=np.int64) + offset)
        roles.append(np.full(len(part.mesh.vertices), part.role, dtype=np.uint8))
        offset += len(part.mesh.vertices)
    model = ShapeModel(
        source_id, category, ground(np.concatenate(vertices)), np.concatenate(faces), np.concatenate(roles)
    )
    for array in (model.vertices, model.faces, model.vertex_roles):
        array.flags.writeable = False  # models are cached and shared; transform copies instead
    return model


def procedural_source_id(category: str, family: str, index: int) -> str:
    return f"{PROCEDURAL_PREFIX}/{category}/{family}/{index:06d}"


def procedural_refs(num_models: int, seed: int = 0, categories: tuple[str, ...] = CATEGORIES) -> list[ModelRef]:
    """``num_models`` procedural models of build seed ``seed``, spread evenly over categories, and over
    families within each; no two seeds share a model."""
    if num_models < len(categories):
        raise UslError(f"--num-models {num_models} is fewer than the {len(categories)} categories")
    if seed < 0:
        raise UslError(f"--seed {seed}: procedural models need a seed >= 0")
    refs = []
    for c, category in enumerate(categories):
        count = num_models // len(categories) + (1 if c < num_models % len(categories) else 0)
        families = list(FAMILIES[category])
        if count > len(families) * SEED_INDEX_STRIDE:
            raise UslError(f"--num-models {num_models}: over {SEED_INDEX_STRIDE:,} models of one {category} family")
        for k in range(count):
            family = families[k % len(families)]
            index = seed * SEED_INDEX_STRIDE + k // len(families)
            refs.append(ModelRef(procedural_source_id(category, family, index), category))
    return refs


def _parse_procedural(source_id: str) -> tuple[str, str, int]:
    parts = source_id.split("/")
    if (
        len(parts) != 4
        or parts[0] != PROCEDURAL_PREFIX
        or parts[1] not in FAMILIES
        or parts[2] not in FAMILIES[parts[1]]
        or not parts[3].isdigit()
    ):
        raise UslError(f"{source_id!r} is not a procedural model id ({PROCEDURAL_PREFIX}/<category>/<family>/<index>)")
    return parts[1], parts[2], int(parts[3])


def family_seed(source_id: str) -> int:
    """Stable 64-bit seed of a model id (independent of Python's salted ``hash``)."""
    return int.from_bytes(hashlib.sha256(source_id.encode()).digest()[:8], "little")


@lru_cache(maxsize=64)
def generate_procedural(source_id: str) -> ShapeModel:
    """The procedural model named by ``source_id``; the same id always gives the same mesh."""
    category, family, _ = _parse_procedural(source_id)
    rng = np.random.default_rng(family_seed(source_id))
    return assemble(source_id, category, FAMILIES[category][family](rng))
