"""Normalisation layers for the backbone: BatchNorm, or BatchNorm frozen to an affine map."""

from __future__ import annotations

import torch
from torch import nn

Tensor = torch.Tensor

NORMS = ("BN", "FrozenBN")


class FrozenBatchNorm2d(nn.Module):
    """BatchNorm with fixed statistics and affine parameters (buffers, never trained).

    Small detection batches give poor batch statistics, so pretrained backbones keep
    their ImageNet/COCO statistics. State-dict keys match ``nn.BatchNorm2d`` so
    torchvision weights load strictly; their ``num_batches_tracked`` is accepted and dropped.
    """

    def __init__(self, num_features: int, eps: float = 1e-5):
        super().__init__()
        self.num_features = num_features
        self.eps = eps
        self.register_buffer("weight", torch.ones(num_features))
        self.register_buffer("bias", torch.zeros(num_features))
        self.register_buffer("running_mean", torch.zeros(num_features))
        self.register_buffer("running_var", torch.ones(num_features))
        self._affine: tuple[tuple, Tensor, Tensor] | None = None  # (buffers' identity, scale, shift)

    def forward(self, x: Tensor) -> Tensor:
        scale, shift = self._scale_and_shift(x.dtype)
        return x * scale + shift

    def _scale_and_shift(self, dtype: torch.dtype) -> tuple[Tensor, Tensor]:
        """The affine map (1, C, 1, 1) in ``dtype``, computed again only when a buffer was replaced
        (``.to()``, which drops the map, since a new buffer may reuse a freed one's address), written
        in place (its version counter), or ``eps`` changed: 11 ops a layer saved on every step. Maps
        made under ``torch.inference_mode`` are kept apart (autograd cannot save them)."""
        buffers = (self.weight, self.bias, self.running_mean, self.running_var)
        key = (dtype, self.eps, torch.is_inference_mode_enabled(), *((b.data_ptr(), b._version) for b in buffers))
        if self._affine is None or self._affine[0] != key:
            with torch.no_grad():
                scale = self.weight * torch.rsqrt(self.running_var + self.eps)
                shift = self.bias - self.running_mean * scale
                self._affine = (key, scale.to(dtype)[None, :, None, None], shift.to(dtype)[None, :, None, None])
        return self._affine[1], self._affine[2]

    def _apply(self, fn, recurse=True):
        self._affine = None
        return super()._apply(fn, recurse)

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        state_dict.pop(prefix + "num_batches_tracked", None)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    @classmethod
    def from_batch_norm(cls, bn: nn.BatchNorm2d) -> FrozenBatchNorm2d:
        """A frozen copy of ``bn``'s current statistics and affine parameters."""
        frozen = cls(bn.num_features, bn.eps)
        with torch.no_grad():
            if bn.affine:
                frozen.weight.copy_(bn.weight)
                frozen.bias.copy_(bn.bias)
            frozen.running_mean.copy_(bn.running_mean)
            frozen.running_var.copy_(bn.running_var)
        return frozen.to(bn.running_mean.device)

    def extra_repr(self) -> str:
        return f"{self.num_features}, eps={self.eps}"


def make_norm(kind: str, channels: int) -> nn.Module:
    if kind == "BN":
        return nn.BatchNorm2d(channels)
    if kind == "FrozenBN":
        return FrozenBatchNorm2d(channels)
    raise ValueError(f"unknown norm {kind!r}; choose one of {NORMS}")


def freeze_batch_norms(module: nn.Module) -> nn.Module:
    """Replace every ``nn.BatchNorm2d`` inside ``module`` by a frozen copy (returns the new module)."""
    if isinstance(module, nn.BatchNorm2d):
        return FrozenBatchNorm2d.from_batch_norm(module)
    for name, child in module.named_children():
        replacement = freeze_batch_norms(child)
        if replacement is not child:
            setattr(module, name, replacement)
    return module
