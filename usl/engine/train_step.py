"""One guarded optimisation step: the model (DDP-wrapped when distributed), optimizer, LR schedule,
autocast on CUDA, gradient clipping, and a NaN/inf guard that skips the step on every rank.

The step never waits for the device. A non-finite step (loss or gradient norm, on any rank) is
clipped against a NaN norm, which makes every gradient NaN; ``GradScaler``'s inf check then hands
the skip to the fused optimizer on the device, leaving parameters and optimizer state untouched.
Outside float16 autocast the scaler's scale stays 1: it is there for that check. The returned
values are 0-d tensors the trainer reads once per log interval."""

from __future__ import annotations

import math
import warnings
from typing import Any

import torch
from torch.nn.parallel import DistributedDataParallel

from usl.config import Config
from usl.data import MultiViewSample
from usl.model.usl_model import USLModel

from .cpu_memory import retain_freed_memory
from .distributed import DistInfo, all_reduce_min
from .optim import build_optimizer, build_scheduler, lay_out_state_like_params

AMP_DTYPES = {"bfloat16": torch.bfloat16, "float16": torch.float16}


class TrainStep:
    def __init__(self, cfg: Config, info: DistInfo):
        self.cfg, self.info = cfg, info
        # before the model exists, so its allocations follow the policy too; here, not in the
        # Trainer, so scripts/bench/train.py times the step usl-train runs
        if info.device.type == "cpu":
            retain_freed_memory()
        self.model = USLModel(cfg.model, cfg.loss).to(info.device)
        self.model.lay_out_weights_like_features(info.device)  # before DDP lays out its buckets
        self.net: torch.nn.Module = self.model
        if info.distributed:
            # without L_2D the RPN, the RoI heads and the FPN maps only they read get no gradient
            self.net = DistributedDataParallel(
                self.model,
                device_ids=[info.device] if info.device.type == "cuda" else None,
                find_unused_parameters=not cfg.loss.weights.mu_2d,
            )
        self.params = [p for p in self.model.parameters() if p.requires_grad]
        self.optimizer = build_optimizer(
            self.model.named_parameters(), cfg.optim, self.model.lr_factors(), self.model.prediction_weights()
        )
        self.scheduler = build_scheduler(self.optimizer, cfg.optim)
        self.amp_dtype = AMP_DTYPES.get(cfg.train.amp) if info.device.type == "cuda" else None
        self.loss_scaling = self.amp_dtype is torch.float16  # dynamic loss scale; otherwise it stays 1
        self.scaler = torch.amp.GradScaler(info.device.type, init_scale=2.0**16 if self.loss_scaling else 1.0)
        self.skipped_total = torch.zeros((), dtype=torch.long, device=info.device)

    def state_dict(self) -> dict[str, Any]:
        return {
            "model": self.model.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "scheduler": self.scheduler.state_dict(),
            "scaler": self.scaler.state_dict() if self.loss_scaling else {},
            "skipped_steps": self.skipped,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.model.load_state_dict(state["model"])
        self.optimizer.load_state_dict(state["optimizer"])
        lay_out_state_like_params(self.optimizer)
        self.scheduler.load_state_dict(state["scheduler"])
        if self.loss_scaling:
            self.scaler.load_state_dict(state["scaler"])
        self.skipped_total.fill_(int(state.get("skipped_steps", 0)))

    @property
    def skipped(self) -> int:
        """Steps skipped as non-finite so far (reads the device)."""
        return int(self.skipped_total)

    def __call__(self, batch: list[MultiViewSample], diagnostics: bool = False) -> dict[str, torch.Tensor]:
        """Forward, backward, clip, guard, step; returns 0-d tensors: the losses, ``grad_norm`` (before
        clipping), ``clipped``, ``skipped`` (and the model's gradient diagnostics when asked: see
        ``USLModel.forward``)."""
        device = self.info.device
        batch = [sample.to(device, non_blocking=True) for sample in batch]
        iteration = self.scheduler.last_epoch  # optimizer steps taken so far, resumed exactly
        with torch.autocast(device.type, dtype=self.amp_dtype or torch.bfloat16, enabled=self.amp_dtype is not None):
            losses = self.net(batch, iteration=iteration, diagnostics=diagnostics)
        loss = losses["loss"]
        self.scaler.scale(loss).backward()
        scale = self.scaler.scale(torch.ones((), device=device))  # the gradients are still scaled by it
        grad_norm = torch.nn.utils.get_total_norm([p.grad for p in self.params if p.grad is not None]) / scale
        finite = torch.isfinite(loss.detach()) & torch.isfinite(grad_norm)
        skipped = all_reduce_min(finite.float().reshape(1)).reshape(()) <= 0  # every rank skips together
        clip = self.cfg.optim.clip_grad_norm
        clip_norm = torch.where(skipped, math.nan, grad_norm)  # a skipped step's gradients all become NaN
        torch.nn.utils.clip_grads_with_norm_(self.params, clip if clip > 0 else math.inf, clip_norm)
        self.scaler.step(self.optimizer)  # checks the gradients for inf/NaN, unscales them, skips on the device
        self.skipped_total += skipped
        self.scaler.update(None if self.loss_scaling else 1.0)
        self.optimizer.zero_grad(set_to_none=True)
        with warnings.catch_warnings():  # a skipped step is deliberate; the schedule counts iterations
            warnings.filterwarnings("ignore", message="Detected call of `lr_scheduler.step", category=UserWarning)
            self.scheduler.step()
        values = {k: v.detach() for k, v in losses.items()}
        # grad_norm is the norm before clipping; clipped's mean over a log interval is the share of steps clipped
        clipped = ~skipped & (grad_norm > clip) if clip > 0 else torch.zeros_like(skipped)
        values.update(grad_norm=grad_norm.detach(), clipped=clipped.float(), skipped=skipped.float())
        return values
