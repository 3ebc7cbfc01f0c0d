"""The blocked nearest-neighbour loop over two k-d trees against brute force: the exact nearest
point, of equidistant ones the lowest index, for near, far-apart and tiny sets."""

import numpy as np
import pytest
import torch

from usl.geometry.kdtree_search import leaf_ranges, nearest_in_tree
from usl.geometry.nearest import KDTREE_LEAF_SIZE, kdtree_indices
from usl.geometry.nearest import _kdtree as tree
from usl.utils import compiled

pytestmark = pytest.mark.skipif(compiled.numba is None, reason="numba is not installed")


def brute_force(queries, candidates):
    """First index of the smallest (dx*dx + dy*dy) + dz*dz, in float64."""
    diff = queries[:, None, :] - candidates[None, :, :]
    sq = diff[..., 0] * diff[..., 0] + diff[..., 1] * diff[..., 1] + diff[..., 2] * diff[..., 2]
    return sq.argmin(1)


def sphere(rng, count, centre, radius):
    p = rng.normal(size=(count, 3))
    return p / np.linalg.norm(p, axis=1, keepdims=True) * radius + centre


@pytest.mark.parametrize(
    "num_queries,num_candidates,offset",
    [(2000, 1500, 0.0), (2000, 1500, 0.4), (1500, 2000, 3.0), (1, 700, 1.0), (700, 1, 0.5), (64, 65, 0.2), (5, 3, 0.0)],
)
def test_nearest_in_tree_equals_brute_force(num_queries, num_candidates, offset):
    rng = np.random.default_rng(num_queries + num_candidates)
    queries = sphere(rng, num_queries, [0.0, 0.0, 0.0], 0.3)
    candidates = sphere(rng, num_candidates, [offset, 0.1 * offset, 0.0], 0.25) * rng.uniform(0.9, 1.1, (1, 3))
    found = nearest_in_tree(tree(queries), tree(candidates))
    assert found.dtype == np.int64
    np.testing.assert_array_equal(found, brute_force(queries, candidates))
    np.testing.assert_array_equal(found, tree(candidates).query(queries)[1])


def test_equidistant_candidates_resolve_to_the_lowest_index():
    """Candidates on a lattice, each twice (the copy at a higher index), and queries at lattice
    points and midway between two: every query has two or four candidates at exactly its distance."""
    lattice = np.stack(np.meshgrid(*[np.arange(6.0)] * 3, indexing="ij"), -1).reshape(-1, 3)
    rng = np.random.default_rng(0)
    candidates = np.concatenate([lattice, lattice])[rng.permutation(2 * len(lattice))]
    queries = np.concatenate([lattice + [0.5, 0.0, 0.0], lattice, lattice + [0.0, 0.5, 0.0]])
    found = nearest_in_tree(tree(queries), tree(candidates))
    np.testing.assert_array_equal(found, brute_force(queries, candidates))
    assert len(leaf_ranges(tree(candidates))) > 4  # the ties span leaves


def test_leaf_ranges_tile_the_tree_order():
    points = np.random.default_rng(1).normal(size=(1000, 3))
    ranges = leaf_ranges(tree(points))
    assert ranges[0, 0] == 0 and ranges[-1, 1] == 1000 and (ranges[1:, 0] == ranges[:-1, 1]).all()
    assert (ranges[:, 1] - ranges[:, 0]).max() <= KDTREE_LEAF_SIZE


def test_kdtree_indices_gives_the_same_answer_with_one_thread_and_with_several():
    """One torch thread takes the blocked loop, several the tree's own threaded query: same indices,
    padding never chosen, a batch element without valid candidates gets 0."""
    generator = torch.Generator().manual_seed(4)
    x = torch.rand(3, 900, 3, generator=generator) + torch.tensor(
        [[[0.0, 0.0, 0.0]], [[2.0, 0.0, 0.0]], [[0.0, 0.0, 0.0]]]
    )
    y = torch.rand(3, 700, 3, generator=generator, dtype=torch.float64)
    valid = torch.rand(3, 700, generator=generator) > 0.4
    valid[2] = False
    threads = torch.get_num_threads()
    try:
        answers = []
        for count in (1, 2):
            torch.set_num_threads(count)
            answers.append(kdtree_indices(x, y, valid))
    finally:
        torch.set_num_threads(threads)
    assert torch.equal(answers[0], answers[1])
    assert valid[:2].gather(1, answers[0][:2]).all() and (answers[0][2] == 0).all()
    sq = ((x[:2, :, None].double() - torch.where(valid[:2, None, :, None], y[:2, None], torch.inf)) ** 2).sum(-1)
    assert torch.equal(answers[0][:2], sq.argmin(2))
