"""The loss-balance schedule (``loss.dist_schedule``): piecewise linear, constant outside its knots."""

import numpy as np
import pytest

from usl.config import ConfigError, load_config
from usl.losses import PiecewiseLinear


def test_schedule_matches_numpy_interpolation_at_every_iteration():
    schedule = PiecewiseLinear(iters=(100, 400, 1000), values=(1.0, 0.25, 0.0625))
    iterations = np.arange(0, 1500)
    expected = np.interp(iterations, schedule.iters, schedule.values)  # constant beyond the ends
    np.testing.assert_allclose([schedule(int(t)) for t in iterations], expected, rtol=1e-12)
    assert schedule(0) == 1.0 and schedule(250) == pytest.approx(0.625) and schedule(5000) == 0.0625


def test_no_knots_is_the_papers_constant_balance():
    assert all(PiecewiseLinear()(t) == 1.0 for t in (0, 10, 10**6))
    assert load_config("scene_shapes").loss.dist_schedule == PiecewiseLinear()


@pytest.mark.parametrize(
    "override, message",
    [
        ("loss.dist_schedule={iters: [10, 5], values: [1, 0.5]}", "increase"),
        ("loss.dist_schedule={iters: [10], values: [1, 0.5]}", "one value per knot"),
        ("loss.dist_schedule={iters: [10], values: [-1]}", ">= 0"),
    ],
)
def test_bad_schedules_are_config_errors_naming_the_key(override, message):
    with pytest.raises(ConfigError, match=rf"loss\.dist_schedule.*{message}"):
        load_config("tiny", [override])
