"""Closed mesh primitives that furniture is assembled from.

Every primitive is a closed, consistently wound trimesh with outward normals (trimesh's
creation functions and convex hulls guarantee it), so a model built as a concatenation of
parts is closed part by part. Parts carry a ``role`` so the renderer can give upholstery and
frame different materials, as real furniture has.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import trimesh
from trimesh import creation

# Roles of a part: 0 = body (seat, cushions, table top), 1 = frame (legs, rails, bases).
BODY, FRAME = 0, 1

# Tessellation: enough for smooth silhouettes at 512 px, few enough to keep models small.
ROUND_SECTIONS = 32
THIN_SECTIONS = 12


@dataclass
class Part:
    mesh: trimesh.Trimesh
    role: int = BODY


def _moved(mesh: trimesh.Trimesh, center: Sequence[float]) -> trimesh.Trimesh:
    mesh.apply_translation(np.asarray(center, dtype=np.float64))
    return mesh


def _rotated(mesh: trimesh.Trimesh, yaw: float, pitch: float) -> trimesh.Trimesh:
    """Rotate about the mesh's own origin: first ``pitch`` about x (leaning backs), then ``yaw`` about y."""
    if pitch:
        mesh.apply_transform(trimesh.transformations.rotation_matrix(pitch, [1.0, 0.0, 0.0]))
    if yaw:
        mesh.apply_transform(trimesh.transformations.rotation_matrix(yaw, [0.0, 1.0, 0.0]))
    return mesh


def box(size: Sequence[float], center: Sequence[float], role: int = BODY, yaw: float = 0.0, pitch: float = 0.0) -> Part:
    """Box of ``size`` (x, y, z) at ``center``, optionally pitched and yawed about its own centre."""
    mesh = creation.box(extents=np.asarray(size, dtype=np.float64))
    return Part(_moved(_rotated(mesh, yaw, pitch), center), role)


def rounded_box(
    size: Sequence[float], center: Sequence[float], radius: float, role: int = BODY, pitch: float = 0.0
) -> Part:
    """Box with edges rounded by ``radius``: the convex hull of eight corner spheres (cushions)."""
    size = np.asarray(size, dtype=np.float64)
    radius = float(min(radius, 0.49 * size.min()))
    half = 0.5 * size - radius
    sphere = creation.icosphere(subdivisions=1, radius=radius).vertices
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * half
    points = (corners[:, None, :] + sphere[None, :, :]).reshape(-1, 3)
    return Part(_moved(_rotated(trimesh.convex.convex_hull(points), 0.0, pitch), center), role)


def cylinder_y(
    radius: float, height: float, center: Sequence[float], role: int = FRAME, sections: int = ROUND_SECTIONS
) -> Part:
    """Vertical cylinder (axis +Y) of ``height`` centred at ``center``."""
    return Part(
        _moved(
            creation.cylinder(radius=radius, height=height, sections=sections).apply_transform(
                trimesh.transformations.rotation_matrix(np.pi / 2, [1.0, 0.0, 0.0])
            ),
            center,
        ),
        role,
    )


def rod(
    start: Sequence[float], end: Sequence[float], radius: float, role: int = FRAME, sections: int = THIN_SECTIONS
) -> Part:
    """Cylinder between two points (splayed legs, stretchers, rails)."""
    segment = np.asarray([start, end], dtype=np.float64)
    return Part(creation.cylinder(radius=radius, segment=segment, sections=sections), role)


def tube(start: Sequence[float], end: Sequence[float], radius: float, role: int = FRAME) -> Part:
    """Capsule between two points: rounded joints for bent-tube frames (cantilever chairs)."""
    start, end = np.asarray(start, dtype=np.float64), np.asarray(end, dtype=np.float64)
    axis = end - start
    length = float(np.linalg.norm(axis))
    mesh = creation.capsule(height=length, radius=radius, count=[THIN_SECTIONS, THIN_SECTIONS])
    # trimesh's capsule is centred on the origin along +Z; align it with the segment.
    mesh.apply_transform(trimesh.geometry.align_vectors([0.0, 0.0, 1.0], axis / length))
    return Part(_moved(mesh, 0.5 * (start + end)), role)


def disk_cone(bottom_radius: float, top_radius: float, height: float, base_y: float, role: int = FRAME) -> Part:
    """Truncated cone standing on ``base_y`` (pedestal feet, flared bases): a convex hull of two rings."""
    angles = np.linspace(0.0, 2 * np.pi, ROUND_SECTIONS, endpoint=False)
    ring = np.stack([np.cos(angles), np.zeros_like(angles), np.sin(angles)], axis=1)
    points = np.concatenate(
        [ring * bottom_radius + [0.0, base_y, 0.0], ring * top_radius + [0.0, base_y + height, 0.0]]
    )
    return Part(trimesh.convex.convex_hull(points), role)


def ring_y(outer: float, inner: float, height: float, center: Sequence[float], role: int = FRAME) -> Part:
    """Horizontal annulus (foot rings of bar stools)."""
    mesh = creation.annulus(r_min=inner, r_max=outer, height=height, sections=ROUND_SECTIONS)
    mesh.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1.0, 0.0, 0.0]))
    return Part(_moved(mesh, center), role)


def rounded_slab_y(
    width: float, depth: float, thickness: float, center: Sequence[float], role: int = BODY, roundness: float = 1.0
) -> Part:
    """Horizontal slab whose outline is a superellipse: ``roundness`` 1 = ellipse, 0 -> rectangle.

    Gives oval and soft-cornered table tops and seats from one continuous parameter.
    """
    exponent = 2.0 + 8.0 * (1.0 - float(np.clip(roundness, 0.0, 1.0)))  # 2 = ellipse, 10 ~ rectangle
    angles = np.linspace(0.0, 2 * np.pi, 2 * ROUND_SECTIONS, endpoint=False)
    cos, sin = np.cos(angles), np.sin(angles)
    x = 0.5 * width * np.sign(cos) * np.abs(cos) ** (2.0 / exponent)
    z = 0.5 * depth * np.sign(sin) * np.abs(sin) ** (2.0 / exponent)
    bottom = np.stack([x, np.full_like(x, -0.5 * thickness), z], axis=1)
    top = bottom + [0.0, thickness, 0.0]
    return Part(_moved(trimesh.convex.convex_hull(np.concatenate([bottom, top])), center), role)


def mirrored_x(part: Part) -> Part:
    """The part reflected through the x = 0 plane (left/right symmetric furniture).

    trimesh reverses the faces of a reflected mesh, so normals stay outward.
    """
    mesh = part.mesh.copy()
    mesh.apply_transform(np.diag([-1.0, 1.0, 1.0, 1.0]))
    return Part(mesh, part.role)


def ball(radius: float, center: Sequence[float], role: int = FRAME) -> Part:
    """Sphere (casters, bun feet)."""
    return Part(_moved(creation.icosphere(subdivisions=2, radius=radius), center), role)
