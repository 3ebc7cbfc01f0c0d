"""Sofa families. Frame: +Y up, floor at y = 0, the sitter faces +Z, width along X, metres.

Seat heights 0.38-0.48 m, backs 0.70-0.95 m, depths 0.80-1.00 m; widths from 1.0 m (armless
two-seaters) to 2.1 m (three-seaters), L-shaped chaises reach 1.6 m deep.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .primitives import BODY, FRAME, Part, ball, box, cylinder_y, rod, rounded_box

Rng = np.random.Generator


@dataclass
class SofaSpec:
    width: float
    seats: int
    arms: str  # "box", "rolled", "thin" or "none"
    leg_height: float
    high_arms: bool = False  # arms as high as the back (chesterfield) instead of below it
    chaise: bool = False
    back_cushions: bool = True


def _legs(rng: Rng, positions: list[tuple[float, float]], height: float) -> list[Part]:
    """Short legs at the given (x, z) spots: cylinders, blocks or bun feet."""
    style = rng.choice(["cylinder", "block", "bun"])
    parts: list[Part] = []
    for x, z in positions:
        if style == "cylinder":
            parts.append(cylinder_y(0.025, height, [x, 0.5 * height, z], sections=16))
        elif style == "block":
            parts.append(box([0.05, height, 0.05], [x, 0.5 * height, z], FRAME))
        else:
            parts.append(ball(0.5 * height, [x, 0.5 * height, z]))
    return parts


def build_sofa(rng: Rng, spec: SofaSpec) -> list[Part]:
    """Upholstered sofa assembled from base, seat cushions, back, arms, optional chaise and legs."""
    depth = rng.uniform(0.80, 1.00)
    seat_top, cushion = rng.uniform(0.38, 0.48), rng.uniform(0.10, 0.18)
    back_top, back_t = rng.uniform(0.70, 0.95), rng.uniform(0.15, 0.25)
    arm_top = back_top if spec.high_arms else rng.uniform(0.52, min(0.68, back_top - 0.02))
    arm_w = {
        "box": rng.uniform(0.12, 0.25),
        "rolled": rng.uniform(0.14, 0.24),
        "thin": rng.uniform(0.05, 0.09),
        "none": 0.0,
    }[spec.arms]
    soft = rng.uniform(0.02, 0.05)
    legs = spec.leg_height
    width, base_top = spec.width, seat_top - cushion
    inner = width - 2 * arm_w
    seat_depth = depth - back_t
    z_seat = 0.5 * back_t  # centre of the seating area along z
    parts = [rounded_box([inner, base_top - legs, seat_depth], [0.0, 0.5 * (base_top + legs), z_seat], soft)]
    parts.append(
        rounded_box([width, back_top - legs, back_t], [0.0, 0.5 * (back_top + legs), -0.5 * (depth - back_t)], soft)
    )
    chaise_w = rng.uniform(0.65, 0.85) if spec.chaise else 0.0
    chaise_extra = rng.uniform(0.5, 0.7) if spec.chaise else 0.0
    cushion_span = inner - chaise_w
    for k in range(spec.seats):
        x = -0.5 * inner + chaise_w + (k + 0.5) * cushion_span / spec.seats
        parts.append(
            rounded_box(
                [cushion_span / spec.seats - 0.01, cushion, seat_depth - 0.01],
                [x, base_top + 0.5 * cushion, z_seat],
                soft,
            )
        )
    if spec.chaise:
        x = -0.5 * inner + 0.5 * chaise_w
        length = seat_depth + chaise_extra
        z = -0.5 * depth + back_t + 0.5 * length
        parts.append(rounded_box([chaise_w, base_top - legs, length], [x, 0.5 * (base_top + legs), z], soft))
        parts.append(rounded_box([chaise_w - 0.01, cushion, length - 0.01], [x, base_top + 0.5 * cushion, z], soft))
    if spec.back_cushions:
        pillow_t, lean = rng.uniform(0.10, 0.18), rng.uniform(0.1, 0.25)
        pillow_h = min(back_top - seat_top + 0.02, rng.uniform(0.38, 0.52))
        count = max(1, spec.seats + (1 if spec.chaise else 0))
        span = inner / count
        y = seat_top + 0.5 * pillow_h - 0.01
        z = -0.5 * depth + back_t + 0.5 * pillow_t - 0.02
        for k in range(count):
            parts.append(
                rounded_box(
                    [span - 0.015, pillow_h, pillow_t], [-0.5 * inner + (k + 0.5) * span, y, z], 0.04, pitch=-lean
                )
            )
    if spec.arms != "none":
        # With a chaise the arm on its side (-x) runs along the chaise.
        arm_depths = [depth + chaise_extra, depth] if spec.chaise else [depth, depth]
        for side, arm_depth in zip((-1.0, 1.0), arm_depths, strict=True):
            x = side * 0.5 * (width - arm_w)
            z = -0.5 * depth + 0.5 * arm_depth
            parts.append(rounded_box([arm_w, arm_top - legs, arm_depth], [x, 0.5 * (arm_top + legs), z], soft))
            if spec.arms == "rolled":
                roll_r = 0.55 * arm_w
                parts.append(
                    rod(
                        [x + side * 0.1 * arm_w, arm_top - 0.3 * roll_r, z - 0.5 * arm_depth + back_t],
                        [x + side * 0.1 * arm_w, arm_top - 0.3 * roll_r, z + 0.5 * arm_depth],
                        roll_r,
                        role=BODY,
                        sections=24,
                    )
                )
    if legs > 0:
        x, z_front, z_back = 0.5 * width - 0.05, 0.5 * depth - 0.05, -0.5 * depth + 0.05
        spots = [(-x, z_front + chaise_extra), (x, z_front), (-x, z_back), (x, z_back)]
        if width > 1.6:
            spots += [(0.0, z_front), (0.0, z_back)]
        parts += _legs(rng, spots, legs)
    return parts


def straight(rng: Rng) -> list[Part]:
    return build_sofa(
        rng,
        SofaSpec(
            width=rng.uniform(1.6, 2.1),
            seats=int(rng.integers(2, 4)),
            arms=str(rng.choice(["box", "rolled", "thin"])),
            leg_height=rng.uniform(0.03, 0.14),
        ),
    )


def loveseat(rng: Rng) -> list[Part]:
    return build_sofa(
        rng,
        SofaSpec(
            width=rng.uniform(1.2, 1.55),
            seats=2,
            arms=str(rng.choice(["box", "rolled"])),
            leg_height=rng.uniform(0.03, 0.14),
        ),
    )


def l_shaped(rng: Rng) -> list[Part]:
    return build_sofa(
        rng,
        SofaSpec(
            width=rng.uniform(1.75, 2.1),
            seats=int(rng.integers(1, 3)),
            arms=str(rng.choice(["box", "thin"])),
            leg_height=rng.uniform(0.02, 0.1),
            chaise=True,
        ),
    )


def armless(rng: Rng) -> list[Part]:
    return build_sofa(
        rng,
        SofaSpec(
            width=rng.uniform(1.0, 1.8),
            seats=int(rng.integers(1, 4)),
            arms="none",
            leg_height=rng.uniform(0.08, 0.18),
            back_cushions=bool(rng.random() < 0.5),
        ),
    )


def chesterfield(rng: Rng) -> list[Part]:
    """Arms as high as the back, rolled, no loose back cushions, bun feet."""
    spec = SofaSpec(
        width=rng.uniform(1.5, 2.0),
        seats=int(rng.integers(2, 4)),
        arms="rolled",
        leg_height=rng.uniform(0.04, 0.08),
        high_arms=True,
        back_cushions=False,
    )
    return build_sofa(rng, spec)


FAMILIES: dict[str, Callable[[Rng], list[Part]]] = {
    "straight": straight,
    "loveseat": loveseat,
    "l_shaped": l_shaped,
    "armless": armless,
    "chesterfield": chesterfield,
}
