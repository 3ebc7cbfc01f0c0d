"""Table families. Frame: +Y up, floor at y = 0, long side along X, metres.

Heights: dining, round, pedestal, trestle and desk tables 0.70-0.78 m; coffee tables 0.38-0.48 m.
Tops stay within 1.6 m so a pair of objects fits in view at the paper's 1.5-1.9 m distances.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from .primitives import (
    BODY,
    FRAME,
    Part,
    box,
    cylinder_y,
    disk_cone,
    mirrored_x,
    ring_y,
    rod,
    rounded_slab_y,
)

Rng = np.random.Generator


def _top(rng: Rng, width: float, depth: float, height: float, roundness: float) -> tuple[Part, float]:
    """Table top whose upper face is at ``height``; returns it and the y of its underside."""
    thickness = rng.uniform(0.02, 0.05)
    under = height - thickness
    return rounded_slab_y(width, depth, thickness, [0.0, under + 0.5 * thickness, 0.0], BODY, roundness), under


def _corner_legs(rng: Rng, x: float, z: float, under: float, splay: float = 0.0) -> list[Part]:
    """Four legs from the underside corners (x, z) to the floor, square or round, optionally splayed."""
    thickness = rng.uniform(0.03, 0.07)
    parts: list[Part] = []
    for sz in (-1.0, 1.0):
        if splay == 0.0 and rng.random() < 0.5:
            leg = box([thickness, under, thickness], [x, 0.5 * under, sz * z], FRAME)
        else:
            leg = rod([x, under, sz * z], [x + splay, 0.0, sz * (z + splay)], 0.5 * thickness)
        parts += [leg, mirrored_x(leg)]
    return parts


def _apron(x: float, z: float, under: float, height: float) -> list[Part]:
    """Rails under the top joining the legs."""
    return [
        box([2 * x, height, 0.02], [0.0, under - 0.5 * height, z], FRAME),
        box([2 * x, height, 0.02], [0.0, under - 0.5 * height, -z], FRAME),
        box([0.02, height, 2 * z], [x, under - 0.5 * height, 0.0], FRAME),
        box([0.02, height, 2 * z], [-x, under - 0.5 * height, 0.0], FRAME),
    ]


def rectangular(rng: Rng) -> list[Part]:
    """Dining table: rectangular top on four legs, often with an apron."""
    width, depth, height = rng.uniform(1.0, 1.6), rng.uniform(0.7, 0.95), rng.uniform(0.72, 0.78)
    top, under = _top(rng, width, depth, height, rng.uniform(0.0, 0.2))
    inset = rng.uniform(0.04, 0.12)
    x, z = 0.5 * width - inset, 0.5 * depth - inset
    parts = [top] + _corner_legs(rng, x, z, under)
    if rng.random() < 0.7:
        parts += _apron(x, z, under, rng.uniform(0.06, 0.11))
    return parts


def round_legged(rng: Rng) -> list[Part]:
    """Round (or slightly oval) top on three or four legs, straight or splayed."""
    radius, height = rng.uniform(0.4, 0.6), rng.uniform(0.72, 0.78)
    top, under = _top(rng, 2 * radius, 2 * radius * rng.uniform(0.85, 1.0), height, 1.0)
    count, splay = int(rng.choice([3, 4])), rng.uniform(0.0, 0.12)
    reach = radius * rng.uniform(0.5, 0.75)
    leg_r = rng.uniform(0.015, 0.03)
    parts = [top]
    for k in range(count):
        angle = 2 * np.pi * k / count
        direction = np.array([np.cos(angle), 0.0, np.sin(angle)])
        parts.append(rod(reach * direction + [0, under, 0], (reach + splay) * direction, leg_r))
    if rng.random() < 0.5:
        parts.append(ring_y(reach + leg_r, reach - leg_r, rng.uniform(0.05, 0.09), [0.0, under - 0.04, 0.0]))
    return parts


def pedestal(rng: Rng) -> list[Part]:
    """Single column on a flared disc or cross feet, under a round, oval or square top."""
    height = rng.uniform(0.70, 0.78)
    width = rng.uniform(0.7, 1.2)
    depth = width * rng.uniform(0.7, 1.0)
    top, under = _top(rng, width, depth, height, rng.uniform(0.0, 1.0))
    column_r = rng.uniform(0.04, 0.09)
    foot = rng.uniform(0.22, 0.36)
    parts = [top, cylinder_y(column_r, under - 0.03, [0.0, 0.5 * (under + 0.03), 0.0])]
    if rng.random() < 0.5:
        parts.append(disk_cone(foot, column_r * 1.5, rng.uniform(0.04, 0.1), 0.0))
    else:
        for yaw in (0.0, np.pi / 2):
            parts.append(box([2 * foot, 0.05, 0.07], [0.0, 0.025, 0.0], FRAME, yaw=yaw + rng.uniform(-0.1, 0.1)))
    parts.append(box([0.5 * width, 0.03, 0.5 * width], [0.0, under - 0.015, 0.0], FRAME))
    return parts


def trestle(rng: Rng) -> list[Part]:
    """Two end trestles (upright board, foot, top cleat) joined by a stretcher, or X-shaped trestles."""
    width, depth, height = rng.uniform(1.2, 1.6), rng.uniform(0.75, 0.95), rng.uniform(0.72, 0.78)
    top, under = _top(rng, width, depth, height, 0.0)
    x = 0.5 * width - rng.uniform(0.12, 0.25)
    span = depth * rng.uniform(0.7, 0.85)
    parts = [top]
    boards = rng.random() < 0.5
    for side in (-1.0, 1.0):
        parts.append(box([0.07, 0.05, span], [side * x, under - 0.025, 0.0], FRAME))
        if boards:
            parts.append(box([0.07, 0.06, span], [side * x, 0.03, 0.0], FRAME))
            parts.append(
                box([0.06, under - 0.11, rng.uniform(0.08, 0.2)], [side * x, 0.5 * (under - 0.05 + 0.06), 0.0], FRAME)
            )
        else:
            half = 0.5 * span - 0.03
            parts += [
                rod([side * x, under - 0.05, -half], [side * x, 0.0, half], 0.025),
                rod([side * x, under - 0.05, half], [side * x, 0.0, -half], 0.025),
            ]
    parts.append(box([2 * x, 0.06, 0.05], [0.0, rng.uniform(0.25, 0.45), 0.0], FRAME))
    return parts


def coffee(rng: Rng) -> list[Part]:
    """Low table, rectangular to oval, four legs, often with a lower shelf."""
    width, depth, height = rng.uniform(0.8, 1.3), rng.uniform(0.5, 0.8), rng.uniform(0.38, 0.48)
    roundness = rng.choice([0.0, rng.uniform(0.3, 1.0)])
    top, under = _top(rng, width, depth, height, roundness)
    inset = rng.uniform(0.05, 0.12) + 0.1 * roundness * min(width, depth)
    x, z = 0.5 * width - inset, 0.5 * depth - inset
    parts = [top] + _corner_legs(rng, x, z, under)
    if rng.random() < 0.5:
        parts.append(box([2 * x, 0.02, 2 * z], [0.0, rng.uniform(0.08, 0.15), 0.0], BODY))
    return parts


def desk(rng: Rng) -> list[Part]:
    """Writing desk: a drawer cabinet on one side, legs or a side panel on the other."""
    width, depth, height = rng.uniform(1.0, 1.5), rng.uniform(0.55, 0.75), rng.uniform(0.72, 0.76)
    top, under = _top(rng, width, depth, height, 0.0)
    cabinet = rng.uniform(0.35, 0.45)
    x_cab = 0.5 * width - 0.5 * cabinet - 0.01
    parts = [top, box([cabinet, under, depth - 0.04], [x_cab, 0.5 * under, 0.0], FRAME)]
    drawers = int(rng.integers(2, 5))
    front = 0.5 * (depth - 0.04)
    for k in range(drawers):
        h = under / drawers
        parts.append(box([cabinet - 0.03, h - 0.02, 0.015], [x_cab, (k + 0.5) * h, front + 0.0075], BODY))
    if rng.random() < 0.5:
        parts.append(box([0.03, under, depth - 0.04], [-0.5 * width + 0.03, 0.5 * under, 0.0], FRAME))
    else:
        for sz in (-1.0, 1.0):
            parts.append(box([0.04, under, 0.04], [-0.5 * width + 0.05, 0.5 * under, sz * (0.5 * depth - 0.05)], FRAME))
    return parts


FAMILIES: dict[str, Callable[[Rng], list[Part]]] = {
    "rectangular": rectangular,
    "round": round_legged,
    "pedestal": pedestal,
    "trestle": trestle,
    "coffee": coffee,
    "desk": desk,
}
