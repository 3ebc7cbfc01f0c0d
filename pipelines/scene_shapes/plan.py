"""Splits and shard plans: models first, then each split's scenes from its own models only.

Everything here is a function of the build arguments (``--seed`` included) and never of the
worker count: each scene's randomness is seeded from (seed, split, scene index).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from pipelines.common import ShardPlan
from usl.errors import UslError

from .layout import PlacementConfig, sample_layout
from .scene import SceneConfig, SceneUnit
from .shapes import CATEGORIES, ModelRef

# Seed-sequence tags that keep the model shuffle and the scene streams independent.
_MODEL_STREAM, _SCENE_STREAM = 0, 1


@dataclass(frozen=True)
class PlanConfig:
    num_scenes: int
    seed: int
    fractions: tuple[tuple[str, float], ...]  # split -> fraction, in output order
    scenes_per_shard: int
    placement: PlacementConfig = PlacementConfig()


def split_counts(total: int, fractions: list[float]) -> list[int]:
    """Largest-remainder rounding of ``total * fractions``; every split gets at least one item
    when there are enough, so tiny builds still have val and test."""
    exact = [total * f / sum(fractions) for f in fractions]
    counts = [math.floor(x) for x in exact]
    by_remainder = sorted(range(len(exact)), key=lambda i: (counts[i] - exact[i], i))
    for i in by_remainder[: total - sum(counts)]:
        counts[i] += 1
    if total >= len(counts):
        for i, count in enumerate(counts):
            if count == 0:
                counts[i] = 1
                counts[counts.index(max(counts))] -= 1
    return counts


def split_models(refs: list[ModelRef], fractions: list[tuple[str, float]], seed: int) -> dict[str, list[ModelRef]]:
    """Disjoint model sets per split, stratified by category, shuffled by ``seed``."""
    splits: dict[str, list[ModelRef]] = {name: [] for name, _ in fractions}
    for c, category in enumerate(CATEGORIES):
        pool = sorted((r for r in refs if r.category == category), key=lambda r: r.source_id)
        order = np.random.default_rng(np.random.SeedSequence([seed, _MODEL_STREAM, c])).permutation(len(pool))
        start = 0
        for (name, _), count in zip(fractions, split_counts(len(pool), [f for _, f in fractions]), strict=True):
            splits[name] += [pool[i] for i in order[start : start + count]]
            start += count
    return splits


def plan_shards(refs: list[ModelRef], plan: PlanConfig, scene_config: SceneConfig) -> list[ShardPlan]:
    """Every shard of the dataset, in output order: the same list for any worker/shard settings."""
    names = [name for name, _ in plan.fractions]
    models = split_models(refs, list(plan.fractions), plan.seed)
    scene_counts = split_counts(plan.num_scenes, [f for _, f in plan.fractions])
    shards: list[ShardPlan] = []
    for s, (name, count) in enumerate(zip(names, scene_counts, strict=True)):
        if count and not models[name]:
            raise UslError(
                f"split {name!r} has {count} scenes but no models; use more models "
                f"(--num-models, or more meshes under --mesh-root)"
            )
        pools = {c: [r for r in models[name] if r.category == c] for c in CATEGORIES}
        units = []
        for i in range(count):
            rng = np.random.default_rng(np.random.SeedSequence([plan.seed, _SCENE_STREAM, s, i]))
            layout = sample_layout(rng, pools, scene_config.rig, plan.placement)
            units.append(SceneUnit(f"{name}-{i:06d}", layout, int(rng.integers(2**63)), scene_config))
        for k in range(0, count, plan.scenes_per_shard):
            shards.append(ShardPlan(name, k // plan.scenes_per_shard, units[k : k + plan.scenes_per_shard]))
    return shards
