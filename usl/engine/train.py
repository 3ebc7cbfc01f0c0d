"""The training loop of ``usl-train`` (command line: ``usl.cli.train``, also run as
``torchrun -m usl.cli.train``): data, guarded steps, logs, checkpoints, exact resume."""

from __future__ import annotations

import math
import resource
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from tqdm import tqdm

from usl.config import Config, ConfigError, save_config, to_dict
from usl.data import CategoryIndex, MultiViewDataset, ShardedBatchSampler, build_train_loader
from usl.model.usl_model import USLModel
from usl.records import RecordsDataset

from .checkpoint import CheckpointError, rng_state, set_rng_state, write_run_checkpoint
from .command import COMMAND
from .distributed import DistInfo, all_gather_objects, barrier, replica_digests
from .feedback import TrainingFeedback
from .run_log import RunLog
from .skip_guard import SkipGuard
from .train_step import TrainStep


def fill_dataset_fields(cfg: Config, records: RecordsDataset) -> None:
    """Categories and layout ranges come from the records' manifest (data_specs), checked if set."""
    names = tuple(c["name"] for c in records.categories)
    if cfg.model.categories and tuple(cfg.model.categories) != names:
        raise ConfigError(f"model.categories {list(cfg.model.categories)} differ from {records.root}'s {list(names)}")
    cfg.model.categories = names
    cfg.model.category_ids = tuple(int(c["id"]) for c in records.categories)
    if cfg.model.layout_range.z1 <= 0:
        layout = records.manifest.get("layout")
        if not layout:
            raise ConfigError(f"{records.root}/manifest.json has no 'layout' ranges; set model.layout_range.*")
        cfg.model.layout_range = type(cfg.model.layout_range)(
            **{k: float(layout[k]) for k in ("z0", "z1", "rho0", "rho1")}
        )


def seed_everything(seed: int, rank: int) -> None:
    import random

    import numpy as np

    random.seed(seed + 1000 * rank)
    np.random.seed(seed + 1000 * rank)
    torch.manual_seed(seed + 1000 * rank)


class Meter:
    """The logged values of the steps since the last log line: their means, and the largest value
    of the keys in ``PEAKS`` (a mean over the interval hides the single steps that matter there:
    after a gradient spike a run's training IoUs can stall, README).

    Steps hand in 0-d tensors; ``means()`` reads them all from the device at once, so a step never
    waits for the device to report a number."""

    PEAKS = ("grad_norm",)

    def __init__(self) -> None:
        self.values: dict[str, list[torch.Tensor | float]] = {}

    def add(self, values: Mapping[str, torch.Tensor | float]) -> None:
        for key, value in values.items():
            self.values.setdefault(key, []).append(value)

    def read(self) -> dict[str, list[float]]:
        """Every value added, as Python numbers (one device read: the tensors are stacked where they are)."""
        flat = [(k, i, v) for k in self.values for i, v in enumerate(self.values[k])]
        out = {k: [0.0] * len(v) for k, v in self.values.items()}
        tensors = [(k, i, v) for k, i, v in flat if isinstance(v, torch.Tensor)]
        if tensors:
            numbers = torch.stack([v.detach().reshape(()).to(torch.float64) for _, _, v in tensors]).tolist()
            for (key, index, _), number in zip(tensors, numbers, strict=True):
                out[key][index] = number
        for key, index, value in flat:
            if not isinstance(value, torch.Tensor):
                out[key][index] = float(value)
        return out

    def means(self, numbers: dict[str, list[float]] | None = None) -> dict[str, float]:
        """The interval's means, and ``KEY_max`` for each key in ``PEAKS`` over its finite values
        (a skipped step's inf/NaN is counted in ``skipped``)."""
        numbers = self.read() if numbers is None else numbers
        peaks = {f"{k}_max": max(f) for k in self.PEAKS if (f := [v for v in numbers.get(k, []) if math.isfinite(v)])}
        return {**{k: sum(v) / len(v) for k, v in numbers.items()}, **peaks}


class Trainer:
    def __init__(self, cfg: Config, run_dir: Path, info: DistInfo, resume: dict[str, Any] | None = None):
        if not cfg.data.root:
            raise ConfigError("data.root is not set: pass data.root=/path/to/records")
        self.cfg, self.run_dir, self.info = cfg, run_dir, info
        if cfg.train.cpu_threads > 0:
            torch.set_num_threads(cfg.train.cpu_threads)
        records = RecordsDataset(cfg.data.root, cfg.data.train_split, verify=cfg.data.verify)
        fill_dataset_fields(cfg, records)
        seed_everything(cfg.train.seed, info.rank)
        self.step = TrainStep(cfg, info)
        dataset = MultiViewDataset(
            records,
            cfg.data,
            CategoryIndex(records.categories),
            seed=cfg.train.seed,
            with_true_meshes=cfg.loss.supervision == "3d",
        )
        if len(dataset) // info.world_size < cfg.train.batch_size:
            raise ConfigError(
                f"{records.root} split {cfg.data.train_split!r} has {len(dataset)} input views: too few for "
                f"train.batch_size={cfg.train.batch_size} on each of {info.world_size} process(es)"
            )
        self.sampler = ShardedBatchSampler(
            len(dataset), cfg.train.batch_size, info.rank, info.world_size, cfg.train.seed
        )
        self.loader = build_train_loader(
            dataset, self.sampler, cfg.data.num_workers, pin_memory=info.device.type == "cuda"
        )
        self.iteration, self.epoch, self.batch_in_epoch = 0, 0, 0
        self.skip_guard = SkipGuard(cfg.train.max_skipped_fraction)
        if resume is not None:
            self.load_state(resume)
        self.log: RunLog | None = None
        self.feedback: TrainingFeedback | None = None  # log.txt, validation, curves.png, summary
        if info.is_main:
            run_dir.mkdir(parents=True, exist_ok=True)
            save_config(cfg, run_dir / "config.yaml")
            self.log = RunLog(run_dir, self.iteration if resume is not None else None)
            self.feedback = TrainingFeedback(cfg, run_dir, self.model, self.iteration, resume is not None)

    @property
    def model(self) -> USLModel:
        return self.step.model

    # ------------------------------------------------------------------ state
    def state(self) -> dict[str, Any]:
        """Everything to continue exactly; collective (every rank must call it)."""
        return {
            "config": to_dict(self.cfg),
            **self.step.state_dict(),
            "data": {"epoch": self.epoch, "batch": self.batch_in_epoch},
            "world_size": self.info.world_size,
            "rng": all_gather_objects(rng_state()),
            "replica_sha256": replica_digests(self.model),  # checked equal: the model is every process's
        }

    def load_state(self, payload: dict[str, Any]) -> None:
        if payload.get("world_size") != self.info.world_size:
            raise CheckpointError(
                f"{payload['path']} was written by {payload.get('world_size')} process(es); resume with as many "
                f"(now {self.info.world_size}) so data shards and random states continue exactly"
            )
        self.step.load_state_dict(payload)
        self.iteration = int(payload["iteration"])
        self.epoch, self.batch_in_epoch = int(payload["data"]["epoch"]), int(payload["data"]["batch"])
        set_rng_state(payload["rng"][self.info.rank])

    def save(self) -> None:
        state = self.state()
        if self.info.is_main:
            write_run_checkpoint(self.run_dir, self.iteration, state, self.cfg.train.keep_checkpoints)
        barrier()

    # ------------------------------------------------------------------ loop
    def train(self) -> None:
        cfg = self.cfg
        bar = tqdm(total=cfg.optim.max_iter, initial=self.iteration, desc=COMMAND, disable=not self.info.is_main)
        meter, last = Meter(), time.perf_counter()
        try:
            while self.iteration < cfg.optim.max_iter:
                self.sampler.set_epoch(self.epoch, self.batch_in_epoch)
                for batch in self.loader:
                    data_time = time.perf_counter() - last
                    values = self.step(batch, diagnostics=(self.iteration + 1) % cfg.train.log_every == 0)
                    self.iteration += 1
                    self.batch_in_epoch += 1
                    now = time.perf_counter()
                    meter.add({**values, "time": now - last, "data_time": data_time})
                    last = now
                    bar.update(1)
                    if self.iteration % cfg.train.log_every == 0 or self.iteration == cfg.optim.max_iter:
                        self.write_log(meter, bar)
                        meter = Meter()
                    if self.iteration % cfg.train.checkpoint_every == 0 or self.iteration == cfg.optim.max_iter:
                        self.save()
                    if self.feedback is not None:
                        self.feedback.after_step(self.iteration)
                    if self.iteration >= cfg.optim.max_iter:
                        break
                else:
                    self.epoch, self.batch_in_epoch = self.epoch + 1, 0
        finally:
            bar.close()
            if self.log is not None:
                self.log.close()
            if self.feedback is not None:
                self.feedback.close(self.iteration)

    def write_log(self, meter: Meter, bar: tqdm) -> None:
        """One CSV row: means over the interval's steps, averaged over ranks (keys a rank lacks,
        e.g. ``stat/z`` without objects, average over the ranks that have them). The interval's
        skipped steps are reported and counted by the skip guard here, where the values are read."""
        numbers = meter.read()
        first = self.iteration - len(numbers["skipped"]) + 1
        for offset, skipped in enumerate(numbers["skipped"]):
            if skipped:
                tqdm.write(f"{COMMAND}: non-finite loss or gradient at iteration {first + offset}; step skipped")
            self.skip_guard.update(bool(skipped), first + offset)
        gathered = all_gather_objects(meter.means(numbers))
        if not self.info.is_main:
            return
        keys = sorted({k for values in gathered for k in values})
        row: dict[str, Any] = {
            k: sum(v[k] for v in gathered if k in v) / sum(1 for v in gathered if k in v) for k in keys
        }
        row["skipped"] = round(row["skipped"] * len(numbers["skipped"]))  # every rank skips together
        row.update(epoch=self.epoch, lr=self.step.optimizer.param_groups[0]["lr"], peak_mem_mb=self.peak_memory_mb())
        assert self.log is not None
        self.log.write(self.iteration, row)
        if self.feedback is not None:
            self.feedback.log_row(self.iteration, row)
        bar.set_postfix(loss=f"{row['loss']:.4f}", l3d=f"{row.get('l3d', 0.0):.4f}")

    def peak_memory_mb(self) -> float:
        if self.info.device.type == "cuda":
            return torch.cuda.max_memory_allocated(self.info.device) / 2**20
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # Linux reports KiB
