"""What a training run tells its user, in detectron2's manner (rank 0 only).

* ``log.txt`` in the run folder: everything below plus one line per logged interval.
* At the start: parameter count, iterations, device, run folder.
* Periodic validation (``usl.engine.validation``), printed and logged to ``validation.csv``.
* At the end: ``curves.png`` (``usl.engine.curves``) and a summary: time, final checkpoint, where
  the logs are.
Console lines go through ``tqdm.write`` so the progress bar stays intact.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from datetime import datetime, timedelta
from pathlib import Path
from typing import Any

from tqdm import tqdm

from usl.config import Config
from usl.engine.checkpoint import CheckpointError, resolve_checkpoint
from usl.engine.command import COMMAND
from usl.engine.curves import plot_curves
from usl.engine.run_log import CSV_NAME, tensorboard_events
from usl.engine.validation import CSV_NAME as VALIDATION_CSV
from usl.engine.validation import PeriodicValidation
from usl.model.usl_model import USLModel

LOG_NAME = "log.txt"


def _duration(seconds: float) -> str:
    return str(timedelta(seconds=round(seconds)))


def _number(value: Any) -> str:
    return f"{value:.4g}" if isinstance(value, float) else str(value)


class TrainingFeedback:
    def __init__(self, cfg: Config, run_dir: Path, model: USLModel, iteration: int, resumed: bool):
        self.cfg, self.run_dir, self.model = cfg, run_dir, model
        self.start_iteration, self.start = iteration, time.perf_counter()
        self.file = open(run_dir / LOG_NAME, "a" if resumed else "w")
        self.validation = PeriodicValidation(cfg, run_dir, iteration if resumed else None) if cfg.val.period else None
        params = sum(p.numel() for p in model.parameters())
        trainable = sum(p.numel() for p in model.parameters() if p.requires_grad)
        device = next(model.parameters()).device
        verb = f"resuming at iteration {iteration}" if resumed else "starting"
        self.say(
            f"{verb}: {cfg.name}, {params:,} parameters ({trainable:,} trainable), iterations "
            f"{iteration} -> {cfg.optim.max_iter} on {device}, run folder {run_dir}"
        )
        if self.validation is not None and self.validation.problem:
            self.say(self.validation.problem)

    def say(self, line: str, console: bool = True) -> None:
        stamped = f"[{datetime.now():%Y-%m-%d %H:%M:%S}] {line}"
        self.file.write(stamped + "\n")
        self.file.flush()
        if console:
            tqdm.write(f"{COMMAND}: {line}")

    def log_row(self, iteration: int, row: Mapping[str, Any]) -> None:
        """One line of ``log.txt`` per ``metrics.csv`` row (the console has the progress bar)."""
        done = iteration - self.start_iteration
        eta = (time.perf_counter() - self.start) / max(done, 1) * (self.cfg.optim.max_iter - iteration)
        values = "  ".join(f"{k}: {_number(v)}" for k, v in row.items() if not k.startswith("stat/"))
        self.say(f"iter {iteration}/{self.cfg.optim.max_iter}  eta {_duration(eta)}  {values}", console=False)

    def after_step(self, iteration: int) -> None:
        if self.validation is not None and self.validation.due(iteration):
            began = time.perf_counter()
            where = f"validation at iteration {iteration} on {self.cfg.data.val_split}"
            try:
                metrics = self.validation.run(self.model, iteration)
            except (RuntimeError, ValueError) as exc:  # e.g. a diverged model's non-finite meshes
                self.say(f"{where} failed, training goes on: {type(exc).__name__}: {exc}")
                return
            values = ", ".join(f"{k.removeprefix('val/')} {v:.4g}" for k, v in metrics.items())
            self.say(f"{where} ({time.perf_counter() - began:.1f} s): {values or 'no object scored'}")

    def close(self, iteration: int) -> None:
        """Curves and the end-of-run summary (also after an error: what the run got to)."""
        if self.validation is not None:
            self.validation.close()
        curves = plot_curves(self.run_dir, VALIDATION_CSV if self.validation is not None else None)
        try:
            checkpoint = str(resolve_checkpoint(self.run_dir))
        except CheckpointError:
            checkpoint = "none"
        state = "finished" if iteration >= self.cfg.optim.max_iter else "stopped"
        logs = [self.run_dir / LOG_NAME, self.run_dir / CSV_NAME]
        logs += [self.run_dir / VALIDATION_CSV] if (self.run_dir / VALIDATION_CSV).is_file() else []
        logs += [curves] if curves is not None else []
        events = tensorboard_events(self.run_dir)
        logs += (
            [f"TensorBoard events (tensorboard --logdir {self.run_dir.parent})"]
            if events
            else ["no TensorBoard events (pip install 'usl[tensorboard]')"]
        )
        self.say(
            f"{state} at iteration {iteration} after {_duration(time.perf_counter() - self.start)}; "
            f"final checkpoint {checkpoint}; logs: {', '.join(str(p) for p in logs)}"
        )
        self.file.close()
