"""Optimizer and learning-rate schedule from ``OptimConfig`` (the paper's recipe table)."""

from __future__ import annotations

from bisect import bisect_right
from collections.abc import Collection, Iterable, Mapping

import torch
from torch import nn

from usl.engine.config import OptimConfig
from usl.engine.muon import MuonAdam, is_hidden_weight

WARMUP_FACTOR = 0.001  # the rate at iteration 0 of the warm-up, as a fraction of lr (detectron2's)


def build_optimizer(
    named_params: Iterable[tuple[str, nn.Parameter]],
    cfg: OptimConfig,
    lr_factors: Mapping[str, float] | None = None,
    prediction_weights: Collection[str] = (),
) -> torch.optim.Optimizer:
    """One parameter group per learning-rate factor (and, for Muon, per kind of step); the schedule scales them all.

    ``lr_factors``: factors on ``cfg.lr`` by parameter-name prefix (the longest matching prefix wins),
    from the model (``USLModel.lr_factors``); every other parameter learns at ``cfg.lr``.
    ``prediction_weights``: for ``muon``, the weights Adam steps although their shape says hidden layer
    (``USLModel.prediction_weights``).

    Fused: one kernel per step instead of a few ops (and, for Adam, a step-count read) per parameter,
    and ``GradScaler.step`` hands it the skip of a non-finite step on the device, without a host sync.
    """
    lr_factors = lr_factors or {}
    groups: dict[tuple[float, bool], list[nn.Parameter]] = {}
    matched = set()
    for name, param in named_params:
        if not param.requires_grad:
            continue
        prefix = max((k for k in lr_factors if name == k or name.startswith(k + ".")), key=len, default=None)
        matched.add(prefix)
        muon = cfg.name == "muon" and is_hidden_weight(param) and name not in prediction_weights
        groups.setdefault((lr_factors[prefix] if prefix is not None else 1.0, muon), []).append(param)
    unused = sorted(set(lr_factors) - matched)
    if unused:
        raise ValueError(f"learning-rate factors: no trainable parameter is named {unused} or below it")
    param_groups = [{"params": params, "lr": cfg.lr * factor} for (factor, _), params in groups.items()]
    if cfg.name == "muon":
        muon_groups = [{**group, "muon": muon} for group, (_, muon) in zip(param_groups, groups, strict=True)]
        return MuonAdam(muon_groups, lr=cfg.lr, momentum=cfg.momentum)
    if cfg.name == "adam":
        return torch.optim.Adam(param_groups, lr=cfg.lr, weight_decay=cfg.weight_decay, fused=True)
    return torch.optim.SGD(param_groups, lr=cfg.lr, momentum=cfg.momentum, weight_decay=cfg.weight_decay, fused=True)


def lay_out_state_like_params(optimizer: torch.optim.Optimizer) -> None:
    """Give each per-element state tensor (Adam's moments, SGD's momentum) its parameter's strides.

    The fused kernels walk a parameter, its gradient and its state as flat memory, so a state in
    another layout pairs the wrong elements, silently. Loaded state keeps the layout it was saved
    in: a checkpoint written where the parameter had another layout (channels-last weights on the
    CPU, NCHW on CUDA: ``MaskRCNN.lay_out_weights_like_features``) would resume wrong without this.
    """
    for param, state in optimizer.state.items():
        for key, value in state.items():
            if isinstance(value, torch.Tensor) and value.shape == param.shape and value.stride() != param.stride():
                state[key] = torch.empty_like(param, dtype=value.dtype).copy_(value)


class LRFactor:
    """Linear warmup from ``WARMUP_FACTOR`` to 1, then x ``gamma`` at each of ``steps``.

    Holds plain numbers only: LambdaLR saves a callable's ``__dict__`` in its state, and
    checkpoints must load with ``torch.load(weights_only=True)``.
    """

    def __init__(self, cfg: OptimConfig):
        self.steps = sorted(cfg.steps)
        self.gamma = cfg.gamma
        self.warmup_iters = cfg.warmup_iters
        self.warmup_factor = WARMUP_FACTOR

    def __call__(self, iteration: int) -> float:
        factor = self.gamma ** bisect_right(self.steps, iteration)
        if iteration < self.warmup_iters:
            alpha = iteration / self.warmup_iters
            factor *= self.warmup_factor * (1 - alpha) + alpha
        return factor


def build_scheduler(optimizer: torch.optim.Optimizer, cfg: OptimConfig) -> torch.optim.lr_scheduler.LambdaLR:
    """Stepped once per iteration; its state (``last_epoch`` = iterations done) resumes exactly."""
    return torch.optim.lr_scheduler.LambdaLR(optimizer, LRFactor(cfg))
