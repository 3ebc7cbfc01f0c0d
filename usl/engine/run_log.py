"""Training logs on rank 0: a CSV file always, TensorBoard events when tensorboard is installed
(``pip install 'usl[tensorboard]'``).

The events go into the run folder itself, so ``tensorboard --logdir runs/`` lists every run by its
folder name. On resume the CSV keeps its rows up to the checkpoint's iteration and drops later ones
(written by the interrupted run after its last checkpoint), and TensorBoard hides the interrupted
run's later events (``purge_step``), so both read as one uninterrupted run.
"""

from __future__ import annotations

import csv
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from usl.records.tempfiles import temp_path

CSV_NAME = "metrics.csv"


class RunLog:
    def __init__(self, run_dir: Path, resume_iteration: int | None = None, name: str = CSV_NAME):
        self.path = run_dir / name
        self.fieldnames: list[str] | None = None
        self.rows: list[dict[str, str]] = []
        if resume_iteration is not None and self.path.is_file():
            with open(self.path, newline="") as f:
                reader = csv.DictReader(f)
                self.fieldnames = list(reader.fieldnames or [])
                self.rows = [r for r in reader if int(r["iteration"]) <= resume_iteration]
            self._rewrite()
        elif self.path.exists():
            self.path.unlink()
        self.tensorboard = _tensorboard(run_dir, resume_iteration)

    def _rewrite(self) -> None:
        tmp = temp_path(self.path, hidden=True)  # named after this process: reaped once it is gone
        with open(tmp, "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=self.fieldnames or ["iteration"], extrasaction="ignore")
            writer.writeheader()
            writer.writerows(self.rows)
        os.replace(tmp, self.path)

    def write(self, iteration: int, values: Mapping[str, Any]) -> None:
        row = {"iteration": iteration, **values}
        if self.fieldnames is None:
            self.fieldnames = list(row)
            self._rewrite()
        with open(self.path, "a", newline="") as f:
            csv.DictWriter(f, fieldnames=self.fieldnames, extrasaction="ignore").writerow(row)
        if self.tensorboard is not None:
            for key, value in values.items():
                if isinstance(value, (int, float)):
                    self.tensorboard.add_scalar(key, value, iteration)

    def close(self) -> None:
        if self.tensorboard is not None:
            self.tensorboard.close()


def _tensorboard(run_dir: Path, resume_iteration: int | None):
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:  # tensorboard is optional: usl[tensorboard]
        return None
    return SummaryWriter(str(run_dir), purge_step=None if resume_iteration is None else resume_iteration + 1)


def tensorboard_events(run_dir: Path) -> list[Path]:
    """The run's TensorBoard event files (what ``tensorboard --logdir`` reads)."""
    return sorted(Path(run_dir).glob("events.out.tfevents.*"))


def read_metrics(run_dir: str | Path, name: str = CSV_NAME) -> list[dict[str, float]]:
    """The CSV log as floats (empty cells skipped); for tests, notebooks and the report."""
    with open(Path(run_dir) / name, newline="") as f:
        return [{k: float(v) for k, v in row.items() if v not in ("", None)} for row in csv.DictReader(f)]
