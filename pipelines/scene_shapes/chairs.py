"""Chair families. Frame: +Y up, floor at y = 0, the sitter faces +Z, width along X, metres.

Dimensions follow common furniture standards: dining/office seat heights 0.42-0.50 m,
upholstered armchairs 0.40-0.47 m, counter/bar stools 0.60-0.78 m.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from .primitives import (
    BODY,
    FRAME,
    Part,
    ball,
    box,
    cylinder_y,
    disk_cone,
    mirrored_x,
    ring_y,
    rod,
    rounded_box,
    rounded_slab_y,
    tube,
)

Rng = np.random.Generator


def _chair_back(
    rng: Rng, width: float, seat_top: float, back_height: float, z_rear: float, lean: float, post: float
) -> list[Part]:
    """Back of a framed chair: two leaning posts with a panel, vertical slats or ladder rails."""
    top_y = seat_top + back_height
    z_top = z_rear - back_height * np.tan(lean)
    x = 0.5 * width - 0.5 * post
    parts = [rod([x, seat_top, z_rear], [x, top_y, z_top], 0.5 * post)]
    parts.append(mirrored_x(parts[0]))
    inner = width - 2 * post
    style = rng.choice(["panel", "slats", "ladder"])

    def rail(height: float, y_mid: float, thickness: float) -> Part:
        z_mid = z_rear - (y_mid - seat_top) * np.tan(lean)
        return box([inner + post, height, thickness], [0.0, y_mid, z_mid], BODY, pitch=-lean)

    if style == "panel":
        panel_h = rng.uniform(0.35, 0.9) * back_height
        parts.append(rail(panel_h, top_y - 0.5 * panel_h - 0.01, rng.uniform(0.015, 0.035)))
    elif style == "slats":
        top_h = rng.uniform(0.04, 0.09)
        parts.append(rail(top_h, top_y - 0.5 * top_h, rng.uniform(0.02, 0.035)))
        count = int(rng.integers(2, 6))
        slat_w = rng.uniform(0.02, 0.045)
        slat_h = back_height - top_h - 0.03
        y_mid = seat_top + 0.03 + 0.5 * slat_h
        z_mid = z_rear - (y_mid - seat_top) * np.tan(lean)
        for x_slat in np.linspace(-0.5 * inner, 0.5 * inner, count + 2)[1:-1]:
            parts.append(box([slat_w, slat_h, 0.018], [x_slat, y_mid, z_mid], BODY, pitch=-lean))
    else:
        count = int(rng.integers(2, 5))
        rail_h = rng.uniform(0.03, 0.07)
        for y_mid in np.linspace(seat_top + 0.3 * back_height, top_y - 0.5 * rail_h, count):
            parts.append(rail(rail_h, y_mid, 0.022))
    return parts


def four_legged(rng: Rng) -> list[Part]:
    """Dining/kitchen chair: seat on four legs, optional stretchers, panel/slat/ladder back."""
    width, depth = rng.uniform(0.40, 0.55), rng.uniform(0.40, 0.52)
    seat_top, seat_t = rng.uniform(0.42, 0.50), rng.uniform(0.025, 0.06)
    leg = rng.uniform(0.025, 0.05)
    splay = rng.uniform(0.0, 0.04)
    under = seat_top - seat_t
    parts = [
        rounded_slab_y(width, depth, seat_t, [0.0, under + 0.5 * seat_t, 0.0], BODY, roundness=rng.uniform(0.0, 0.35))
    ]
    x, z = 0.5 * width - 0.5 * leg - 0.01, 0.5 * depth - 0.5 * leg - 0.01
    for sz in (-1.0, 1.0):
        leg_part = rod(
            [x, under, sz * z], [x + splay, 0.0, sz * (z + splay)], 0.5 * leg, sections=4 if rng.random() < 0.5 else 12
        )
        parts += [leg_part, mirrored_x(leg_part)]
    if rng.random() < 0.5:
        y = rng.uniform(0.10, 0.22)
        frac = y / under  # legs splay linearly, so follow them at this height
        xs, zs = x + splay * (1 - frac), z + splay * (1 - frac)
        parts += [
            rod([-xs, y, zs], [-xs, y, -zs], 0.011),
            rod([xs, y, zs], [xs, y, -zs], 0.011),
            rod([-xs, y, 0.0], [xs, y, 0.0], 0.011),
        ]
    back_h, lean = rng.uniform(0.35, 0.55), rng.uniform(0.0, 0.25)
    parts += _chair_back(rng, width, seat_top, back_h, -0.5 * depth + 0.5 * leg + 0.005, lean, leg)
    return parts


def swivel(rng: Rng) -> list[Part]:
    """Office chair: padded seat and back on a gas column over a five-star base with casters."""
    width, depth = rng.uniform(0.45, 0.55), rng.uniform(0.42, 0.50)
    seat_top, seat_t = rng.uniform(0.42, 0.50), rng.uniform(0.06, 0.10)
    caster = rng.uniform(0.022, 0.03)
    reach = rng.uniform(0.26, 0.34)
    arm_h, arm_w = rng.uniform(0.025, 0.04), rng.uniform(0.035, 0.05)
    arm_y = 2 * caster + 0.5 * arm_h
    parts = [rounded_box([width, seat_t, depth], [0.0, seat_top - 0.5 * seat_t, 0.0], 0.03)]
    start = rng.uniform(0.0, 2 * np.pi / 5)
    for k in range(5):
        angle = start + 2 * np.pi * k / 5
        direction = np.array([np.cos(angle), 0.0, np.sin(angle)])
        parts.append(box([reach, arm_h, arm_w], 0.5 * reach * direction + [0.0, arm_y, 0.0], FRAME, yaw=-angle))
        parts.append(ball(caster, reach * direction + [0.0, caster, 0.0]))
    hub_r = rng.uniform(0.04, 0.06)
    parts.append(cylinder_y(hub_r, arm_h + 0.03, [0.0, arm_y, 0.0]))
    column_bottom, column_top = arm_y + 0.015, seat_top - seat_t - 0.04
    parts.append(
        cylinder_y(
            rng.uniform(0.022, 0.035), column_top - column_bottom, [0.0, 0.5 * (column_bottom + column_top), 0.0]
        )
    )
    parts.append(box([0.2, 0.04, 0.2], [0.0, column_top + 0.02, 0.0], FRAME))
    back_h, lean = rng.uniform(0.40, 0.70), rng.uniform(0.08, 0.25)
    back_t = rng.uniform(0.05, 0.08)
    gap = rng.uniform(0.06, 0.14)
    back_w = width * rng.uniform(0.8, 1.0)
    z_back = -0.5 * depth - 0.5 * back_t
    y_mid = seat_top + gap + 0.5 * back_h
    parts.append(
        rounded_box(
            [back_w, back_h, back_t], [0.0, y_mid, z_back - (y_mid - seat_top) * np.tan(lean)], 0.025, pitch=-lean
        )
    )
    parts.append(box([0.05, gap + 0.2, 0.025], [0.0, seat_top - seat_t + 0.5 * (gap + 0.2), z_back], FRAME))
    if rng.random() < 0.6:
        x = 0.5 * width + 0.02
        pad_y = seat_top + rng.uniform(0.18, 0.26)
        post = box([0.025, pad_y - seat_top + seat_t, 0.05], [x, 0.5 * (pad_y + seat_top - seat_t), 0.0], FRAME)
        pad = rounded_box([0.07, 0.03, rng.uniform(0.22, 0.3)], [x, pad_y, 0.0], 0.012)
        parts += [post, pad, mirrored_x(post), mirrored_x(pad)]
    return parts


def armchair(rng: Rng) -> list[Part]:
    """Upholstered club chair: base, seat cushion, thick arms and back, skirt or short legs."""
    width, depth = rng.uniform(0.70, 0.95), rng.uniform(0.72, 0.92)
    seat_top, cushion = rng.uniform(0.40, 0.47), rng.uniform(0.10, 0.16)
    arm_top, arm_w = rng.uniform(0.55, 0.68), rng.uniform(0.10, 0.20)
    back_top, back_t = rng.uniform(0.75, 1.00), rng.uniform(0.14, 0.24)
    leg_h = rng.choice([0.0, rng.uniform(0.06, 0.16)])
    soft = rng.uniform(0.015, 0.06)
    base_top = seat_top - cushion
    parts = [
        rounded_box(
            [width - 2 * arm_w, base_top - leg_h, depth - back_t], [0.0, 0.5 * (base_top + leg_h), 0.5 * back_t], soft
        )
    ]
    parts.append(
        rounded_box(
            [width - 2 * arm_w - 0.01, cushion, depth - back_t - 0.01],
            [0.0, base_top + 0.5 * cushion, 0.5 * back_t],
            soft,
        )
    )
    arm = rounded_box([arm_w, arm_top - leg_h, depth], [0.5 * (width - arm_w), 0.5 * (arm_top + leg_h), 0.0], soft)
    parts += [arm, mirrored_x(arm)]
    parts.append(
        rounded_box([width, back_top - leg_h, back_t], [0.0, 0.5 * (back_top + leg_h), -0.5 * (depth - back_t)], soft)
    )
    if leg_h > 0:
        leg_r = rng.uniform(0.018, 0.03)
        for sz in (-1.0, 1.0):
            leg = cylinder_y(leg_r, leg_h, [0.5 * width - 0.05, 0.5 * leg_h, sz * (0.5 * depth - 0.05)], sections=16)
            parts += [leg, mirrored_x(leg)]
    return parts


def stool_with_back(rng: Rng) -> list[Part]:
    """Counter/bar stool with a low back: round or square seat, splayed legs or column, foot ring."""
    seat_top, seat_t = rng.uniform(0.60, 0.78), rng.uniform(0.035, 0.07)
    size = rng.uniform(0.34, 0.44)
    under = seat_top - seat_t
    parts = [rounded_slab_y(size, size, seat_t, [0.0, under + 0.5 * seat_t, 0.0], roundness=rng.uniform(0.3, 1.0))]
    ring_y_pos = rng.uniform(0.22, 0.32)
    if rng.random() < 0.5:
        spread = rng.uniform(0.04, 0.09)
        top_r = 0.5 * size - 0.04
        for k in range(4):
            angle = np.pi / 4 + k * np.pi / 2
            direction = np.array([np.cos(angle), 0.0, np.sin(angle)])
            parts.append(rod(top_r * direction + [0, under, 0], (top_r + spread) * direction, 0.014))
        ring_r = top_r + spread * (1 - ring_y_pos / under)
    else:
        base_r = rng.uniform(0.18, 0.24)
        parts.append(disk_cone(base_r, base_r * 0.8, 0.025, 0.0))
        parts.append(cylinder_y(0.025, under - 0.025, [0.0, 0.5 * (under + 0.025), 0.0], sections=16))
        ring_r = rng.uniform(0.16, 0.2)
        for k in range(3):
            angle = 2 * np.pi * k / 3
            direction = np.array([np.cos(angle), 0.0, np.sin(angle)])
            parts.append(rod([0.0, ring_y_pos, 0.0], ring_r * direction + [0, ring_y_pos, 0], 0.009))
    parts.append(ring_y(ring_r + 0.01, ring_r - 0.01, 0.02, [0.0, ring_y_pos, 0.0]))
    back_h, lean = rng.uniform(0.18, 0.35), rng.uniform(0.0, 0.2)
    parts += _chair_back(rng, size * rng.uniform(0.8, 0.95), seat_top, back_h, -0.5 * size + 0.03, lean, 0.025)
    return parts


def cantilever(rng: Rng) -> list[Part]:
    """Bent-tube cantilever chair: floor runners turn up at the front, under the seat, and into the back."""
    width, depth = rng.uniform(0.42, 0.52), rng.uniform(0.42, 0.50)
    seat_top, radius = rng.uniform(0.43, 0.48), rng.uniform(0.009, 0.014)
    back_h, lean = rng.uniform(0.35, 0.5), rng.uniform(0.05, 0.25)
    z_front, z_floor_back = 0.5 * depth + rng.uniform(-0.02, 0.04), -0.5 * depth + rng.uniform(0.0, 0.08)
    z_rear = -0.5 * depth + 0.02
    y_under = seat_top - 0.03 - radius
    x = 0.5 * width - radius
    path = [
        [x, radius, z_floor_back],
        [x, radius, z_front],
        [x, y_under, z_front - 0.03],
        [x, y_under, z_rear],
        [x, seat_top + back_h, z_rear - back_h * np.tan(lean)],
    ]
    parts: list[Part] = []
    for start, end in zip(path[:-1], path[1:], strict=True):
        segment = tube(start, end, radius)
        parts += [segment, mirrored_x(segment)]
    parts.append(tube([-x, radius, z_floor_back], [x, radius, z_floor_back], radius))
    parts.append(rounded_box([width - 0.02, 0.03, depth - 0.02], [0.0, seat_top - 0.015, 0.0], 0.012))
    pad_h = back_h * rng.uniform(0.45, 0.8)
    y_mid = seat_top + back_h - 0.5 * pad_h
    parts.append(
        rounded_box(
            [width - 0.02, pad_h, 0.025], [0.0, y_mid, z_rear - (y_mid - seat_top) * np.tan(lean)], 0.01, pitch=-lean
        )
    )
    return parts


FAMILIES: dict[str, Callable[[Rng], list[Part]]] = {
    "four_legged": four_legged,
    "swivel": swivel,
    "armchair": armchair,
    "stool_with_back": stool_with_back,
    "cantilever": cantilever,
}
