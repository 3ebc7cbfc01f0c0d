"""Muon for the hidden layers' weight matrices, Adam for every other parameter, in one optimizer.

Muon (Jordan et al. 2024, "Muon: An optimizer for hidden layers in neural networks") replaces a
weight matrix's Nesterov momentum by its nearest semi-orthogonal matrix (a few Newton-Schulz
iterations), so that every direction of the layer moves at the same rate. Scaled to Adam's typical
update RMS (0.2 sqrt(max(rows, cols)), Moonshot AI's "Muon is Scalable for LLM Training"), one
learning rate and schedule serve both kinds of parameter.

``torch.optim.Muon`` takes 2-D parameters only and has no on-device skip, so it is not used: here a
convolution's weight is the matrix (out, in x kh x kw), the matrices of one shape are orthogonalised
together (a batched matmul instead of a loop of small ones), the Adam part is torch's fused Adam,
and a step that ``GradScaler`` flags as non-finite (``found_inf``) leaves every parameter and
every state untouched without a host sync, as the fused optimizers do. Under DDP every process
would orthogonalise the same matrices; instead each takes a share, balanced by cost, and broadcasts
its results, so two CPU processes spend half the time and step exactly as one would.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import torch
import torch.distributed as dist
from torch.optim.adam import adam

NEWTON_SCHULZ_COEFFICIENTS = (3.4445, -4.7750, 2.0315)  # Jordan et al.'s quintic: fast, not exact
NEWTON_SCHULZ_STEPS = 5
RMS_MATCH = 0.2  # Adam's typical update RMS


def _through_gram(n: int, m: int) -> bool:
    """Whether an n x m matrix (n the smaller side) iterates on its Gram matrix: only when wide enough."""
    return m >= 3 * n


def orthogonalize(matrices: torch.Tensor, steps: int = NEWTON_SCHULZ_STEPS) -> torch.Tensor:
    """About U V^T of each matrix's SVD, for a batch (B, rows, cols) of matrices.

    Each iteration maps X to P(X X^T) X, with P a polynomial, so X_k = Q_k X_0 for an n x n matrix
    Q_k (n the smaller side). Wide matrices (a convolution's out x in*kh*kw, an RoI head's 128 x 1568)
    iterate on Q_k and the Gram matrix G_k = X_k X_k^T = Q_k G_0 Q_k^T alone, then apply Q to X_0
    once: two n x n x m products instead of two per iteration, about 3 times less CPU here.
    """
    a, b, c = NEWTON_SCHULZ_COEFFICIENTS
    x = matrices / (torch.linalg.matrix_norm(matrices, keepdim=True) + 1e-7)
    tall = x.shape[-2] > x.shape[-1]
    if tall:  # iterate on the smaller side
        x = x.mT
    n, m = x.shape[-2:]
    if _through_gram(n, m):
        gram = x @ x.mT
        q = torch.eye(n, dtype=x.dtype, device=x.device).expand_as(gram)
        for _ in range(steps):
            poly = b * gram + c * gram @ gram
            poly.diagonal(dim1=-2, dim2=-1).add_(a)
            q = poly @ q
            gram = poly @ gram @ poly  # P commutes with G: G_{k+1} = P G_k P^T = P G_k P
        x = q @ x
    else:  # near square: the direct iteration is as cheap
        for _ in range(steps):
            gram = x @ x.mT
            x = a * x + (b * gram + c * gram @ gram) @ x
    return x.mT if tall else x


@dataclass
class _MuonBatch:
    """The parameters of one shape in one group: their momentum buffers (old and new) and the update."""

    params: list[torch.Tensor]
    buffers: list[torch.Tensor]
    old_buffers: torch.Tensor
    new_buffers: torch.Tensor
    update: torch.Tensor  # (batch, *shape)
    lr: float

    @property
    def cost(self) -> int:
        """Multiply-adds of the orthogonalisation, about: the Gram products dominate."""
        n, m = sorted((self.update.shape[1], self.update[0, 0].numel()))
        steps = NEWTON_SCHULZ_STEPS
        per_matrix = 2 * n * n * m + steps * 4 * n**3 if _through_gram(n, m) else steps * (2 * n * n * m + n**3)
        return len(self.params) * per_matrix


def _balanced_owners(costs: list[int], world: int) -> list[int]:
    """A process for each batch, the largest first to the least loaded (the same on every process)."""
    load, owners = [0] * world, [0] * len(costs)
    for index in sorted(range(len(costs)), key=lambda i: -costs[i]):
        owner = min(range(world), key=lambda r: load[r])
        owners[index], load[owner] = owner, load[owner] + costs[index]
    return owners


class MuonAdam(torch.optim.Optimizer):
    """Groups with ``muon=True`` step with Muon (Nesterov ``momentum``), the others with Adam (``betas``, ``eps``)."""

    _step_supports_amp_scaling = True  # GradScaler hands over grad_scale and found_inf as attributes

    def __init__(
        self,
        param_groups: Iterable[dict[str, Any]],
        lr: float,
        momentum: float = 0.95,
        betas: tuple[float, float] = (0.9, 0.999),
        eps: float = 1e-8,
    ):
        # "fused": Adam's step counts then stay float32 tensors on the parameter's device, also on load
        defaults = dict(lr=lr, momentum=momentum, betas=betas, eps=eps, muon=False, fused=True)
        super().__init__(param_groups, defaults)
        for group in self.param_groups:
            for param in group["params"]:
                if group["muon"] and param.ndim < 2:
                    raise ValueError(
                        f"Muon steps weight matrices; a parameter of shape {tuple(param.shape)} is not one"
                    )

    @torch.no_grad()
    def step(self, closure: None = None) -> None:
        grad_scale = getattr(self, "grad_scale", None)
        found_inf = getattr(self, "found_inf", None)
        batches: list[_MuonBatch] = []
        for group in self.param_groups:
            params = [p for p in group["params"] if p.grad is not None]
            if group["muon"]:
                batches += self._muon_batches(params, group, grad_scale)
            else:
                self._adam_step(params, group, grad_scale, found_inf)
        self._muon_step(batches, found_inf)

    def _adam_step(self, params: list[torch.Tensor], group: dict[str, Any], grad_scale, found_inf) -> None:
        for param in params:
            state = self.state[param]
            if not state:
                state["step"] = torch.zeros((), dtype=torch.float32, device=param.device)
                state["exp_avg"] = torch.zeros_like(param, memory_format=torch.preserve_format)
                state["exp_avg_sq"] = torch.zeros_like(param, memory_format=torch.preserve_format)
        states = [self.state[p] for p in params]
        beta1, beta2 = group["betas"]
        adam(
            params,
            [p.grad for p in params],
            [s["exp_avg"] for s in states],
            [s["exp_avg_sq"] for s in states],
            [],
            [s["step"] for s in states],
            fused=True,
            grad_scale=grad_scale,
            found_inf=found_inf,
            amsgrad=False,
            beta1=beta1,
            beta2=beta2,
            lr=group["lr"],
            weight_decay=0.0,
            eps=group["eps"],
            maximize=False,
        )

    def _muon_batches(self, params: list[torch.Tensor], group: dict[str, Any], grad_scale) -> list[_MuonBatch]:
        """The group's parameters by shape, each shape's new momentum and Nesterov update stacked."""
        by_shape: dict[torch.Size, list[torch.Tensor]] = {}
        for param in params:
            by_shape.setdefault(param.shape, []).append(param)
        momentum = group["momentum"]
        batches = []
        for members in by_shape.values():
            buffers = [self._momentum_buffer(p) for p in members]
            grads = torch.stack([p.grad for p in members])
            if grad_scale is not None:
                grads = grads / grad_scale
            old_buffers = torch.stack(buffers)
            new_buffers = old_buffers * momentum + grads
            update = grads.add_(new_buffers, alpha=momentum)  # Nesterov
            batches.append(_MuonBatch(members, buffers, old_buffers, new_buffers, update, group["lr"]))
        return batches

    def _muon_step(self, batches: list[_MuonBatch], found_inf) -> None:
        """Orthogonalise every batch's update and step; under DDP each process orthogonalises a
        share of the batches and broadcasts them (every process steps the same replicas)."""
        rank, world = (dist.get_rank(), dist.get_world_size()) if dist.is_initialized() else (0, 1)
        owners = _balanced_owners([batch.cost for batch in batches], world)
        steps, pending = [], []
        for batch, owner in zip(batches, owners, strict=True):
            members, shape = batch.params, batch.params[0].shape
            if owner == rank:
                matrices = batch.update.reshape(len(members), shape[0], -1)
                scale = RMS_MATCH * math.sqrt(max(matrices.shape[-2:]))
                # contiguous: a broadcast sends and receives memory in order, whatever the strides say
                step = orthogonalize(matrices).reshape(batch.update.shape).mul(-batch.lr * scale).contiguous()
            else:
                step = torch.empty(batch.update.shape, dtype=batch.update.dtype, device=batch.update.device)
            if world > 1:
                pending.append(dist.broadcast(step, src=owner, async_op=True))
            steps.append(step)
        for work in pending:
            work.wait()
        for batch, step in zip(batches, steps, strict=True):
            new_buffers = batch.new_buffers
            if found_inf is not None:  # a skipped step moves nothing (its gradients are NaN)
                skip = found_inf.to(torch.bool)
                new_buffers = torch.where(skip, batch.old_buffers, new_buffers)
                step = torch.where(skip, 0.0, step)
            torch._foreach_copy_(batch.buffers, list(new_buffers.unbind(0)))
            torch._foreach_add_(batch.params, list(step.unbind(0)))

    def _momentum_buffer(self, param: torch.Tensor) -> torch.Tensor:
        state = self.state[param]
        if "momentum_buffer" not in state:
            state["momentum_buffer"] = torch.zeros_like(param, memory_format=torch.preserve_format)
        return state["momentum_buffer"]


def is_hidden_weight(param: torch.Tensor) -> bool:
    """Whether Muon should step ``param``: a hidden layer's weight matrix (or convolution).

    Not a bias or norm (fewer than 2 dimensions), not the stem (a convolution of the 3 colour
    channels), not a layer with under 16 outputs (classes, boxes, depths, a vertex's 3 offsets):
    Muon's equal rate for every direction suits neither a layer's input nor its few outputs.
    A prediction layer with many outputs is named by its model (``USLModel.prediction_weights``).
    """
    if param.ndim < 2 or param.shape[0] < 16:
        return False
    return not (param.ndim == 4 and param.shape[1] == 3)
