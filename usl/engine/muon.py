"""Muon for the hidden layers' weight matrices, Adam for everything else (trial).

Muon (Jordan et al. 2024) replaces each hidden weight's momentum by its nearest semi-orthogonal
matrix (a few Newton-Schulz iterations), so every direction of the layer moves at the same rate;
reported to train in fewer steps than Adam. A convolution's weight is taken as (out, in x k x k).
The update is scaled to Adam's typical RMS (0.2 sqrt(max(rows, cols))), so one rate serves both.
"""

from __future__ import annotations

import math

import torch

NS_COEFFICIENTS = (3.4445, -4.7750, 2.0315)


def orthogonalize(matrix: torch.Tensor, steps: int = 5) -> torch.Tensor:
    """Approximately U V^T of ``matrix``'s SVD (Newton-Schulz quintic)."""
    a, b, c = NS_COEFFICIENTS
    x = matrix / (matrix.norm() + 1e-7)
    tall = x.shape[0] > x.shape[1]
    if tall:
        x = x.T
    for _ in range(steps):
        gram = x @ x.T
        x = a * x + (b * gram + c * gram @ gram) @ x
    return x.T if tall else x


class MuonAdam(torch.optim.Optimizer):
    """Groups with ``muon=True`` step with Muon (Nesterov momentum ``momentum``), the others with Adam."""

    def __init__(self, param_groups, lr: float, momentum: float = 0.95, betas=(0.9, 0.999), eps: float = 1e-8):
        super().__init__(param_groups, dict(lr=lr, momentum=momentum, betas=betas, eps=eps, muon=False))

    @torch.no_grad()
    def step(self, closure=None):
        for group in self.param_groups:
            lr = group["lr"]
            for param in group["params"]:
                if param.grad is None:
                    continue
                grad = param.grad
                state = self.state[param]
                if group["muon"]:
                    buf = state.setdefault("momentum_buffer", torch.zeros_like(param))
                    buf.mul_(group["momentum"]).add_(grad)
                    update = grad.add(buf, alpha=group["momentum"])
                    matrix = update.reshape(update.shape[0], -1)
                    ortho = orthogonalize(matrix)
                    scale = 0.2 * math.sqrt(max(matrix.shape))
                    param.add_(ortho.reshape(param.shape), alpha=-lr * scale)
                    continue
                beta1, beta2 = group["betas"]
                if not state:
                    state["step"] = 0
                    state["exp_avg"] = torch.zeros_like(param)
                    state["exp_avg_sq"] = torch.zeros_like(param)
                state["step"] += 1
                t = state["step"]
                state["exp_avg"].lerp_(grad, 1 - beta1)
                state["exp_avg_sq"].mul_(beta2).addcmul_(grad, grad, value=1 - beta2)
                denom = (state["exp_avg_sq"] / (1 - beta2**t)).sqrt_().add_(group["eps"])
                param.addcdiv_(state["exp_avg"], denom, value=-lr / (1 - beta1**t))
        return None


def uses_muon(name: str, param: torch.Tensor) -> bool:
    """Hidden weight matrices only: not the stem, the output layers (few outputs, or the vertex offsets)."""
    if param.ndim < 2 or param.shape[0] < 16:
        return False
    return not (name.endswith("bottom_up.conv1.weight") or name.endswith("global_mlp.4.weight"))
