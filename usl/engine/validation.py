"""Periodic validation during training: ``usl-eval``'s own code on a few scenes of ``data.val_split``.

The model runs with ground-truth boxes (the "USL" row of the paper's tables) on ``val.input_views``
of the first ``val.num_scenes`` scenes; Mask IoU and Box gIoU in the input view and the other views,
Depth L1 and, where the split has 3D ground truth, Chamfer and F1 go to ``validation.csv`` as
``val/<metric>``. The random state is restored afterwards, so validating never changes training.
"""

from __future__ import annotations

from pathlib import Path

import torch

from usl.config import Config
from usl.engine.checkpoint import rng_state, set_rng_state
from usl.engine.run_log import RunLog
from usl.errors import UslError
from usl.evaluation.evaluate import run_evaluation
from usl.evaluation.model import ModelPredictor
from usl.evaluation.scene import EvalConfig
from usl.evaluation.summary import METRICS
from usl.model.usl_model import USLModel
from usl.records import RecordsDataset

CSV_NAME = "validation.csv"


class PeriodicValidation:
    """Call ``due(iteration)``, then ``run(model, iteration)``; rank 0 only."""

    def __init__(self, cfg: Config, run_dir: Path, resume_iteration: int | None = None):
        self.cfg = cfg
        self.period = cfg.val.period
        self.problem = ""
        try:
            RecordsDataset(cfg.data.root, cfg.data.val_split)  # fail now, not at the first validation
        except UslError as exc:
            self.period, self.problem = 0, f"validation off: {exc}"
        self.log = RunLog(run_dir, resume_iteration, name=CSV_NAME) if self.period else None

    def due(self, iteration: int) -> bool:
        return bool(self.period) and (iteration % self.period == 0 or iteration == self.cfg.optim.max_iter)

    def run(self, model: USLModel, iteration: int) -> dict[str, float]:
        """Evaluate, log the row and return the metrics that are defined (``val/<metric>``)."""
        cfg = self.cfg
        device = next(model.parameters()).device
        evaluation = EvalConfig(
            input_views=cfg.val.input_views, num_samples_3d=cfg.val.samples_3d, seed=cfg.train.seed, device=str(device)
        )
        state = rng_state()
        try:
            with torch.no_grad():
                run = run_evaluation(
                    cfg.data.root,
                    cfg.data.val_split,
                    [ModelPredictor(model, cfg.data.max_size)],
                    evaluation,
                    max_scenes=cfg.val.num_scenes or None,
                    progress=False,
                )
        finally:
            set_rng_state(state)  # (model.predict puts the model back in training mode itself)
        (summary,) = run.summaries
        row = {f"val/{key}": summary.metrics.get(key) for key in METRICS}
        assert self.log is not None
        self.log.write(iteration, {k: ("" if v is None else v) for k, v in row.items()})
        return {k: v for k, v in row.items() if v is not None}

    def close(self) -> None:
        if self.log is not None:
            self.log.close()
