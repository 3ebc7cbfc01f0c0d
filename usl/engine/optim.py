"""Optimizer and learning-rate schedule from ``OptimConfig`` (the paper's recipe table)."""
from __future__ import annotations

from bisect import bisect_right
from typing import Iterable

import torch
from torch import nn

from usl.config import OptimConfig


def build_optimizer(params: Iterable[nn.Parameter], cfg: OptimConfig) -> torch.optim.Optimizer:
    trainable = [p for p in params if p.requires_grad]
    if cfg.name == "adam":
        return torch.optim.Adam(trainable, lr=cfg.lr, weight_decay=cfg.weight_decay)
    return torch.optim.SGD(trainable, lr=cfg.lr, momentum=cfg.momentum, weight_decay=cfg.weight_decay)


class LRFactor:
    """Linear warmup from ``warmup_factor`` to 1, then x ``gamma`` at each of ``steps`` ("step").

    Holds plain numbers only: LambdaLR saves a callable's ``__dict__`` in its state, and
    checkpoints must load with ``torch.load(weights_only=True)``.
    """

    def __init__(self, cfg: OptimConfig):
        self.steps = sorted(cfg.steps) if cfg.schedule == "step" else []
        self.gamma = cfg.gamma
        self.warmup_iters = cfg.warmup_iters
        self.warmup_factor = cfg.warmup_factor

    def __call__(self, iteration: int) -> float:
        factor = self.gamma ** bisect_right(self.steps, iteration)
        if iteration < self.warmup_iters:
            alpha = iteration / self.warmup_iters
            factor *= self.warmup_factor * (1 - alpha) + alpha
        return factor


def build_scheduler(optimizer: torch.optim.Optimizer, cfg: OptimConfig) -> torch.optim.lr_scheduler.LambdaLR:
    """Stepped once per iteration; its state (``last_epoch`` = iterations done) resumes exactly."""
    return torch.optim.lr_scheduler.LambdaLR(optimizer, LRFactor(cfg))
