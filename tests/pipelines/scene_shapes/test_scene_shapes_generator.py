"""Procedural furniture: closed outward parts, metric sizes, determinism, distinct families.

Oracles: trimesh's watertightness/volume, and a vertical ray cast written here (a point-in-
triangle test in the XZ plane) for seat and table-top heights.
"""

import numpy as np
import pytest
import trimesh

from pipelines.scene_shapes.shapes import (
    CATEGORIES,
    FAMILIES,
    family_seed,
    generate_procedural,
    procedural_refs,
    procedural_source_id,
)
from usl.errors import UslError

SEEDS = range(3)
# Documented extents (x = width, y = height, z = depth), metres, of each family (module docstrings).
EXTENTS = {
    "chair": ([0.35, 0.70, 0.35], [1.00, 1.30, 1.00]),
    "sofa": ([1.00, 0.65, 0.75], [2.20, 1.10, 1.70]),
    "table": ([0.55, 0.37, 0.50], [1.65, 0.80, 1.20]),
}
SEAT_HEIGHT = {
    "four_legged": (0.42, 0.50),
    "swivel": (0.42, 0.50),
    "armchair": (0.40, 0.47),
    "stool_with_back": (0.60, 0.78),
    "cantilever": (0.42, 0.50),
}
TABLE_HEIGHT = {"coffee": (0.38, 0.48)}
DINING_HEIGHT = (0.70, 0.80)

FAMILY_CASES = [(c, f) for c in CATEGORIES for f in FAMILIES[c]]


def vertical_hits(model, x: float, z: float) -> np.ndarray:
    """Heights where the vertical line through (x, z) crosses the model's triangles."""
    tri = model.vertices[model.faces]
    a, b, c = tri[:, 0][:, [0, 2]], tri[:, 1][:, [0, 2]], tri[:, 2][:, [0, 2]]
    p = np.array([x, z])
    det = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])
    ok = np.abs(det) > 1e-12
    det = np.where(ok, det, 1.0)
    u = ((p[0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (p[1] - a[:, 1])) / det
    v = ((b[:, 0] - a[:, 0]) * (p[1] - a[:, 1]) - (p[0] - a[:, 0]) * (b[:, 1] - a[:, 1])) / det
    inside = ok & (u >= 0) & (v >= 0) & (u + v <= 1)
    y = tri[:, 0, 1] + u * (tri[:, 1, 1] - tri[:, 0, 1]) + v * (tri[:, 2, 1] - tri[:, 0, 1])
    return y[inside]


@pytest.mark.parametrize("category,family", FAMILY_CASES)
def test_every_part_is_closed_with_outward_normals(category, family):
    for index in SEEDS:
        model = generate_procedural(procedural_source_id(category, family, index))
        mesh = trimesh.Trimesh(model.vertices, model.faces, process=False)
        parts = mesh.split(only_watertight=False)  # parts share no vertices: one component each
        assert len(parts) >= 3
        for part in parts:
            assert part.is_watertight and part.is_winding_consistent
            assert part.volume > 1e-7  # positive signed volume = normals point outward


@pytest.mark.parametrize("category,family", FAMILY_CASES)
def test_models_are_grounded_and_metric(category, family):
    low, high = (np.array(b) for b in EXTENTS[category])
    for index in SEEDS:
        model = generate_procedural(procedural_source_id(category, family, index))
        lo, hi = model.vertices.min(axis=0), model.vertices.max(axis=0)
        assert lo[1] == pytest.approx(0.0, abs=1e-9)
        assert (lo[0] + hi[0]) == pytest.approx(0.0, abs=1e-9) and (lo[2] + hi[2]) == pytest.approx(0.0, abs=1e-9)
        assert np.all(model.extents >= low) and np.all(model.extents <= high), (family, index, model.extents)


@pytest.mark.parametrize("family", list(FAMILIES["chair"]))
def test_chair_seat_heights(family):
    lo, hi = SEAT_HEIGHT[family]
    for index in SEEDS:
        model = generate_procedural(procedural_source_id("chair", family, index))
        seat = vertical_hits(model, 0.0, 0.05).max()  # seat centre, in front of any back
        assert lo - 0.005 <= seat <= hi + 0.005, (index, seat)


@pytest.mark.parametrize("family", list(FAMILIES["table"]))
def test_table_top_heights(family):
    lo, hi = TABLE_HEIGHT.get(family, DINING_HEIGHT)
    for index in SEEDS:
        model = generate_procedural(procedural_source_id("table", family, index))
        assert lo - 0.005 <= vertical_hits(model, 0.0, 0.0).max() <= hi + 0.015


def test_sofa_seats_are_sofa_height():
    """The typical top surface over the middle of a sofa is its seat (cushion gaps and backs are rare)."""
    for family in FAMILIES["sofa"]:
        model = generate_procedural(procedural_source_id("sofa", family, 0))
        tops = [
            hits.max()
            for x in np.linspace(-0.3, 0.3, 7)
            for z in np.linspace(-0.1, 0.3, 5)
            if len(hits := vertical_hits(model, x, z))
        ]
        assert 0.36 <= np.median(tops) <= 0.50, (family, np.median(tops))


def test_same_id_same_mesh_and_different_ids_differ():
    source_id = procedural_source_id("sofa", "l_shaped", 7)
    first = generate_procedural(source_id)
    generate_procedural.cache_clear()
    again = generate_procedural(source_id)
    assert first is not again
    np.testing.assert_array_equal(first.vertices, again.vertices)
    np.testing.assert_array_equal(first.faces, again.faces)
    other = generate_procedural(procedural_source_id("sofa", "l_shaped", 8))
    assert other.vertices.shape != first.vertices.shape or not np.allclose(other.vertices, first.vertices)
    assert family_seed(source_id) == family_seed(str(source_id))  # not Python's salted hash


def test_families_are_recognisable_from_coarse_shape():
    """Leave-one-out nearest-centroid on coarse shape (extents, fill of the bounding box, log vertex
    count, a 3x3 top-height profile, where the vertices lie in height) must name each model's family far above chance (1/5 or 1/6)."""

    def descriptor(model):
        ext = model.extents
        volume = trimesh.Trimesh(model.vertices, model.faces, process=False).volume
        profile = [
            max(vertical_hits(model, fx * ext[0], fz * ext[2]), default=0.0) / ext[1]
            for fx in (-0.45, 0.0, 0.45)
            for fz in (-0.35, 0.0, 0.3)
        ]
        heights = np.histogram(model.vertices[:, 1] / ext[1], bins=4, range=(0, 1))[0] / len(model.vertices)
        return np.array(
            [
                ext[0] / ext[1],
                ext[2] / ext[1],
                ext[1],
                volume / np.prod(ext),
                np.log(len(model.vertices)),
                *profile,
                *heights,
            ]
        )

    for category in CATEGORIES:
        families = list(FAMILIES[category])
        feats = {
            f: np.array([descriptor(generate_procedural(procedural_source_id(category, f, i))) for i in range(6)])
            for f in families
        }
        scale = np.concatenate(list(feats.values())).std(axis=0) + 0.02  # constant features must not dominate
        correct = total = 0
        for f in families:
            for i in range(len(feats[f])):
                centroids = {
                    g: np.delete(feats[g], i, axis=0).mean(0) if g == f else feats[g].mean(0) for g in families
                }
                guess = min(families, key=lambda g: np.linalg.norm((feats[f][i] - centroids[g]) / scale))
                correct += guess == f
                total += 1
        assert correct / total >= 0.7, (category, correct, total)


def test_procedural_refs_balance_categories_and_families():
    refs = procedural_refs(100)
    assert len({r.source_id for r in refs}) == 100
    per_category = {c: [r for r in refs if r.category == c] for c in CATEGORIES}
    assert sorted(len(v) for v in per_category.values()) == [33, 33, 34]
    for category, models in per_category.items():
        counts = [sum(f"/{family}/" in r.source_id for r in models) for family in FAMILIES[category]]
        assert max(counts) - min(counts) <= 1
        for ref in models[:5]:
            assert generate_procedural(ref.source_id).category == category


def test_each_seed_draws_its_own_models_and_seed_0_keeps_its_ids():
    pools = {seed: {r.source_id for r in procedural_refs(300, seed)} for seed in (0, 1, 2, 7)}
    for a in pools:
        for b in pools:
            if a < b:
                assert not pools[a] & pools[b], (a, b)
    # seed 0: the models builds had before seeds had model ranges (their data is unchanged)
    first_chair = next(iter(FAMILIES["chair"]))
    assert (
        procedural_refs(3)[0].source_id
        == procedural_source_id("chair", first_chair, 0)
        == procedural_refs(3, 0)[0].source_id
    )
    assert procedural_refs(3, 2)[0].source_id == procedural_source_id("chair", first_chair, 2_000_000)
    assert [r.category for r in procedural_refs(100, 1)] == [r.category for r in procedural_refs(100)]


def test_procedural_models_refuse_a_negative_seed():
    with pytest.raises(UslError, match="--seed -1"):
        procedural_refs(10, -1)
