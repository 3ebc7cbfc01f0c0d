"""Graph convolution on meshes that all share one topology (the identical ico-sphere per object)."""
from __future__ import annotations

import torch
from torch import nn

Tensor = torch.Tensor


class GraphConv(nn.Module):
    """``y_i = W0 x_i + sum_{j in N(i)} W1 x_j`` over undirected edges (Mesh R-CNN's GraphConv).

    Works on a dense batch of meshes with the same edges: ``x`` is (N, V, C_in) and ``edges``
    (E, 2) indexes the V vertices of every mesh, so one ``index_add`` serves the whole batch.
    Weights start small (normal, std 0.01) and biases at zero, as in Mesh R-CNN.
    """

    def __init__(self, in_dim: int, out_dim: int):
        super().__init__()
        self.w0 = nn.Linear(in_dim, out_dim)
        self.w1 = nn.Linear(in_dim, out_dim)
        for layer in (self.w0, self.w1):
            nn.init.normal_(layer.weight, std=0.01)
            nn.init.zeros_(layer.bias)

    def forward(self, x: Tensor, edges: Tensor) -> Tensor:
        own, message = self.w0(x), self.w1(x)
        a, b = edges[:, 0], edges[:, 1]
        return own.index_add(1, a, message[:, b]).index_add(1, b, message[:, a])
