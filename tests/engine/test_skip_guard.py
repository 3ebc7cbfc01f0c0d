"""Training stops with a clear error once most recent steps were skipped as non-finite
(the Trainer end to end: tests/engine/test_train.py::test_non_finite_loss_skips_the_step)."""

import pytest

from usl.config import ConfigError, load_config
from usl.engine.skip_guard import SkipGuard, TooManySkippedSteps


def test_isolated_skips_pass_and_a_run_of_them_stops():
    guard = SkipGuard(max_fraction=0.5, window=4)
    for iteration in range(40):  # one in four skipped: never more than half of a window
        guard.update(iteration % 4 == 0, iteration)
    guard.update(True, 40)
    guard.update(True, 41)
    with pytest.raises(TooManySkippedSteps, match=r"3 of the last 4 steps \(up to iteration 42\)"):
        guard.update(True, 42)
    never = SkipGuard(max_fraction=1.0, window=3)
    for iteration in range(10):
        never.update(True, iteration)
    with pytest.raises(ConfigError, match="max_skipped_fraction"):
        load_config("tiny", ["train.max_skipped_fraction=1.5"])
