"""Other-view sampling and the rank-sharded batch sampler."""
import numpy as np
import pytest

from usl.data import SampleKey, ShardedBatchSampler, sample_other_views

VIEW_IDS = [0, 1, 2, 3, 4, 10, 20]
IDS = [np.array([1, 2]), np.array([1]), np.array([3]), np.array([2, 3]), np.array([], dtype=np.int64),
       np.array([1]), np.array([2])]


def test_candidates_share_an_object_and_exclude_the_input():
    rng = np.random.default_rng(0)
    for _ in range(50):
        chosen = sample_other_views(VIEW_IDS, IDS, 0, np.array([1, 2]), 3, "uniform", rng)
        assert len(chosen) == 3 and len(set(chosen)) == 3
        assert set(chosen) <= {1, 3, 5, 6}


def test_too_few_candidates_returns_all_of_them_once():
    rng = np.random.default_rng(0)
    assert sorted(sample_other_views(VIEW_IDS, IDS, 0, np.array([1, 2]), 10, "uniform", rng)) == [1, 3, 5, 6]
    assert sample_other_views(VIEW_IDS, IDS, 4, np.array([], dtype=np.int64), 3, "uniform", rng) == []
    assert sample_other_views(VIEW_IDS, IDS, 2, np.array([7]), 3, "uniform", rng) == []


def test_time_distance_frequencies_follow_the_view_id_gap():
    """One draw at a time, each candidate's frequency ~ |view_id - input view_id| / sum."""
    rng = np.random.default_rng(1)
    counts = np.zeros(len(VIEW_IDS))
    draws = 3000
    for _ in range(draws):
        counts[sample_other_views(VIEW_IDS, IDS, 0, np.array([1, 2]), 1, "time_distance", rng)[0]] += 1
    gaps = np.array([0, 1, 0, 3, 0, 10, 20], dtype=float)
    expected = gaps / gaps.sum()
    assert np.allclose(counts / draws, expected, atol=0.03)  # > 3 standard errors


def test_unknown_strategy_is_an_error():
    with pytest.raises(ValueError, match="unknown view sampling"):
        sample_other_views(VIEW_IDS, IDS, 0, np.array([1]), 1, "nearest", np.random.default_rng(0))


def test_ranks_get_disjoint_equal_shares_and_resume_mid_epoch():
    world, batch = 3, 2
    samplers = [ShardedBatchSampler(20, batch, rank, world, seed=5) for rank in range(world)]
    seen = []
    for sampler in samplers:
        sampler.set_epoch(4)
        batches = list(sampler)
        assert len(batches) == len(sampler) == 20 // world // batch
        assert all(len(b) == batch and all(isinstance(k, SampleKey) and k.epoch == 4 for k in b) for b in batches)
        seen += [k.index for b in batches for k in b]
    assert len(seen) == len(set(seen)) == 18  # no item on two ranks; the 2-item tail waits for another epoch
    full = list(samplers[1])
    samplers[1].set_epoch(4, start_batch=2)
    assert list(samplers[1]) == full[2:]
    samplers[1].set_epoch(5)
    assert list(samplers[1]) != full  # a new permutation each epoch


def test_too_small_dataset_is_an_error():
    with pytest.raises(ValueError, match="cannot fill one batch"):
        ShardedBatchSampler(3, 2, 0, 2)
