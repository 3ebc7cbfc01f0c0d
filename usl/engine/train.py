"""``usl-train``: train USL from a recipe, on CPU, one GPU, or many GPUs/machines with torchrun.

    usl-train --config tiny data.root=/data/scene_shapes_small
    usl-train --config hypersim --output-dir runs/hs data.root=/data/hypersim \\
        model.detector.backbone.resnet.weights=/weights/R-50.pth
    torchrun --nproc_per_node 8 -m usl.engine.train --config hypersim data.root=...
    usl-train --resume --output-dir runs/hs            # continue exactly where it stopped

The run folder gets ``config.yaml`` (the resolved config), ``metrics.csv`` (and TensorBoard
events when tensorboard is installed) and ``checkpoints/`` (see ``usl.engine.checkpoint``).
"""
from __future__ import annotations

import argparse
import resource
import sys
import time
from pathlib import Path
from typing import Any, Sequence

import torch
from tqdm import tqdm

from usl.config import Config, ConfigError, config_from_dict, deep_merge, load_config, parse_overrides, save_config, to_dict
from usl.data import CategoryIndex, MultiViewDataset, ShardedBatchSampler, build_train_loader
from usl.model.usl_model import USLModel
from usl.records import RecordsDataset, UslError
from usl.records.errors import error_line

from .checkpoint import (
    CHECKPOINT_DIR,
    CheckpointError,
    checkpoint_config,
    read_checkpoint,
    rng_state,
    set_rng_state,
    write_run_checkpoint,
)
from .distributed import DistInfo, all_gather_objects, barrier, init_distributed, shutdown_distributed
from .run_log import RunLog
from .skip_guard import SkipGuard
from .train_step import TrainStep

COMMAND = "usl-train"


def fill_dataset_fields(cfg: Config, records: RecordsDataset) -> None:
    """Categories and layout ranges come from the records' manifest (data_specs), checked if set."""
    names = tuple(c["name"] for c in records.categories)
    if cfg.model.categories and tuple(cfg.model.categories) != names:
        raise ConfigError(f"model.categories {list(cfg.model.categories)} differ from {records.root}'s {list(names)}")
    cfg.model.categories = names
    if cfg.model.layout_range.z1 <= 0:
        layout = records.manifest.get("layout")
        if not layout:
            raise ConfigError(f"{records.root}/manifest.json has no 'layout' ranges; set model.layout_range.*")
        cfg.model.layout_range = type(cfg.model.layout_range)(**{k: float(layout[k]) for k in ("z0", "z1", "rho0", "rho1")})


def seed_everything(seed: int, rank: int) -> None:
    import random

    import numpy as np

    random.seed(seed + 1000 * rank)
    np.random.seed(seed + 1000 * rank)
    torch.manual_seed(seed + 1000 * rank)


class Meter:
    """Sums of logged values since the last log line."""

    def __init__(self) -> None:
        self.sums: dict[str, float] = {}
        self.counts: dict[str, int] = {}

    def add(self, values: dict[str, float]) -> None:
        for key, value in values.items():
            self.sums[key] = self.sums.get(key, 0.0) + value
            self.counts[key] = self.counts.get(key, 0) + 1

    def means(self) -> dict[str, float]:
        return {k: self.sums[k] / self.counts[k] for k in self.sums}


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
        dataset = MultiViewDataset(records, cfg.data, CategoryIndex(records.categories), seed=cfg.train.seed)
        if len(dataset) // info.world_size < cfg.train.batch_size:
            raise ConfigError(
                f"{records.root} split {cfg.data.train_split!r} has {len(dataset)} input views: too few for "
                f"train.batch_size={cfg.train.batch_size} on each of {info.world_size} process(es)"
            )
        self.sampler = ShardedBatchSampler(len(dataset), cfg.train.batch_size, info.rank, info.world_size, cfg.train.seed)
        self.loader = build_train_loader(dataset, self.sampler, cfg.data.num_workers)
        self.iteration, self.epoch, self.batch_in_epoch = 0, 0, 0
        self.skip_guard = SkipGuard(cfg.train.max_skipped_fraction, cfg.train.skip_window)
        if resume is not None:
            self.load_state(resume)
        self.log: RunLog | None = None
        if info.is_main:
            run_dir.mkdir(parents=True, exist_ok=True)
            save_config(cfg, run_dir / "config.yaml")
            self.log = RunLog(run_dir, self.iteration if resume is not None else None)

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
                    values = self.step(batch)
                    if values["skipped"]:
                        tqdm.write(f"{COMMAND}: non-finite loss or gradient at iteration {self.iteration + 1}; step skipped")
                    self.skip_guard.update(values["skipped"], self.iteration + 1)
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
                    if self.iteration >= cfg.optim.max_iter:
                        break
                else:
                    self.epoch, self.batch_in_epoch = self.epoch + 1, 0
        finally:
            bar.close()
            if self.log is not None:
                self.log.close()

    def write_log(self, meter: Meter, bar: tqdm) -> None:
        """One CSV row: means over the interval's steps, averaged over ranks (keys a rank lacks,
        e.g. ``stat/z`` without objects, average over the ranks that have them)."""
        gathered = all_gather_objects(meter.means())
        if not self.info.is_main:
            return
        keys = sorted({k for values in gathered for k in values})
        row: dict[str, Any] = {
            k: sum(v[k] for v in gathered if k in v) / sum(1 for v in gathered if k in v) for k in keys
        }
        row["skipped"] = round(row["skipped"] * meter.counts["skipped"])  # every rank skips together
        row.update(epoch=self.epoch, lr=self.step.optimizer.param_groups[0]["lr"], peak_mem_mb=self.peak_memory_mb())
        assert self.log is not None
        self.log.write(self.iteration, row)
        bar.set_postfix(loss=f"{row['loss']:.4f}", l3d=f"{row.get('l3d', 0.0):.4f}")

    def peak_memory_mb(self) -> float:
        if self.info.device.type == "cuda":
            return torch.cuda.max_memory_allocated(self.info.device) / 2**20
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # Linux reports KiB


# ---------------------------------------------------------------------------------- CLI
def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=COMMAND, description=__doc__.split("\n\n")[0])
    p.add_argument("--config", help="recipe name (tiny, scene_shapes, hypersim, scannet) or a YAML file")
    p.add_argument("--output-dir", type=Path, help="run folder (default: runs/<config name>)")
    p.add_argument("--resume", nargs="?", const="", default=None, metavar="CHECKPOINT",
                   help="continue from CHECKPOINT, or from the run folder's newest checkpoint")
    p.add_argument("overrides", nargs="*", metavar="key=value", help="config overrides, e.g. optim.lr=0.01")
    return p


def resolve_run(args: argparse.Namespace) -> tuple[Config, Path, dict[str, Any] | None]:
    """The config, run folder and (when resuming) checkpoint payload the arguments ask for."""
    if args.resume is not None:
        source = args.resume or args.output_dir
        if not source:
            raise ConfigError("--resume needs a checkpoint path or --output-dir")
        payload = read_checkpoint(source)
        stored = checkpoint_config(payload)  # --config is ignored: a resumed run keeps its recipe
        cfg = config_from_dict(deep_merge(to_dict(stored), parse_overrides(args.overrides)), where="overrides")
        run_dir = args.output_dir or Path(payload["path"]).parent.parent
        return cfg, Path(run_dir), payload
    if not args.config:
        raise ConfigError("give --config (a recipe name or YAML file), or --resume")
    cfg = load_config(args.config, args.overrides)
    run_dir = Path(args.output_dir or Path("runs") / cfg.name)
    if (run_dir / CHECKPOINT_DIR).is_dir() and any((run_dir / CHECKPOINT_DIR).glob("model_*.pt")):
        raise ConfigError(f"{run_dir} already holds checkpoints: pass --resume to continue it, or another --output-dir")
    return cfg, run_dir, None


def main(argv: Sequence[str] | None = None) -> int:
    args = parser().parse_args(argv)
    try:
        cfg, run_dir, payload = resolve_run(args)
        info = init_distributed(cfg.train.device)
        try:
            Trainer(cfg, run_dir, info, payload).train()
        finally:
            shutdown_distributed()
    except (ConfigError, CheckpointError, UslError) as exc:
        print(f"{COMMAND}: error: {error_line(exc)}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
