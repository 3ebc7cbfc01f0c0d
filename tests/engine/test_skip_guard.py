"""Training stops with a clear error once most recent steps were skipped as non-finite."""
import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).parents[1] / "data"))

from synthetic_records import build_synthetic_records  # noqa: E402

from usl.config import ConfigError, load_config  # noqa: E402
from usl.engine.distributed import DistInfo  # noqa: E402
from usl.engine.skip_guard import SkipGuard, TooManySkippedSteps  # noqa: E402
from usl.engine.train import Trainer  # noqa: E402


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


def test_trainer_stops_instead_of_finishing_on_non_finite_steps(tmp_path):
    records = build_synthetic_records(tmp_path / "records", num_scenes=2, num_views=2, size=32)
    cfg = load_config("tiny", [f"data.root={records}", "data.num_workers=0", "train.batch_size=1", "optim.max_iter=30",
                               "train.skip_window=10", "train.max_skipped_fraction=0.2", "train.cpu_threads=1"])
    trainer = Trainer(cfg, tmp_path / "run", DistInfo(0, 1, 0, torch.device("cpu")))
    trainer.step = lambda batch: {"loss": float("nan"), "skipped": 1.0}  # as TrainStep reports a skipped step
    with pytest.raises(TooManySkippedSteps, match="3 of the last 3 steps"):
        trainer.train()
    assert trainer.iteration == 2  # stopped at the third step, long before max_iter
