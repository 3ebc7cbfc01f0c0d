"""Optimizer and learning-rate schedule from ``OptimConfig`` (the paper's recipe table)."""
from __future__ import annotations

from bisect import bisect_right
from typing import Iterable

import torch
from torch import nn

from usl.config import OptimConfig

DEFAULT_ADAM_EPS = 1e-8  # torch.optim.Adam's


def _longest_prefix(name: str, prefixes: Iterable[str]) -> str | None:
    return max((k for k in prefixes if name == k or name.startswith(k + ".")), key=len, default=None)


def build_optimizer(named_params: Iterable[tuple[str, nn.Parameter]], cfg: OptimConfig) -> torch.optim.Optimizer:
    """One parameter group per (learning-rate factor, Adam epsilon) pair (``cfg.lr_mult``,
    ``cfg.adam_eps``); the schedule scales them all."""
    groups: dict[tuple[float, float], list[nn.Parameter]] = {}
    matched: dict[str, set] = {"lr_mult": set(), "adam_eps": set()}
    for name, param in named_params:
        if not param.requires_grad:
            continue
        lr_prefix = _longest_prefix(name, cfg.lr_mult)
        eps_prefix = _longest_prefix(name, cfg.adam_eps)
        matched["lr_mult"].add(lr_prefix)
        matched["adam_eps"].add(eps_prefix)
        key = (cfg.lr_mult[lr_prefix] if lr_prefix is not None else 1.0,
               cfg.adam_eps[eps_prefix] if eps_prefix is not None else DEFAULT_ADAM_EPS)
        groups.setdefault(key, []).append(param)
    for option, prefixes in (("lr_mult", cfg.lr_mult), ("adam_eps", cfg.adam_eps)):
        unused = sorted(set(prefixes) - matched[option])
        if unused:
            raise ValueError(f"optim.{option}: no trainable parameter is named {unused} or below it")
    if cfg.adam_eps and cfg.name != "adam":
        raise ValueError(f"optim.adam_eps is set but optim.name is {cfg.name!r}, not 'adam'")
    if cfg.name == "adam":
        param_groups = [{"params": params, "lr": cfg.lr * factor, "eps": eps} for (factor, eps), params in groups.items()]
        return torch.optim.Adam(param_groups, lr=cfg.lr, weight_decay=cfg.weight_decay)
    param_groups = [{"params": params, "lr": cfg.lr * factor} for (factor, _), params in groups.items()]
    return torch.optim.SGD(param_groups, lr=cfg.lr, momentum=cfg.momentum, weight_decay=cfg.weight_decay)


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
