"""Load backbone weights from a LOCAL checkpoint file, with errors that name the file."""
from __future__ import annotations

from pathlib import Path
from typing import Union

import torch
from torch import nn

# Keys a checkpoint may wrap its state dict in (raw torchvision files have none).
_WRAPPER_KEYS = ("state_dict", "model")
_SHOWN_KEYS = 8


class WeightsError(RuntimeError):
    """A weights file is missing, unreadable, or does not fit the model."""


def read_state_dict(path: Union[str, Path]) -> dict[str, torch.Tensor]:
    """Read a state dict saved with ``torch.save`` (optionally wrapped in ``state_dict``/``model``)."""
    path = Path(path)
    if not path.is_file():
        raise WeightsError(f"weights file {path} does not exist (weights are never downloaded; give a local path)")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # torch raises several types for corrupt or foreign files
        raise WeightsError(f"weights file {path} could not be read as a torch checkpoint: {error}") from error
    for key in _WRAPPER_KEYS:
        if isinstance(payload, dict) and isinstance(payload.get(key), dict):
            payload = payload[key]
    if not isinstance(payload, dict) or not all(isinstance(v, torch.Tensor) for v in payload.values()):
        raise WeightsError(f"weights file {path} does not hold a state dict of tensors")
    return payload


def load_weights(module: nn.Module, path: Union[str, Path]) -> None:
    """Strictly load ``path`` into ``module``: every key and every shape must match."""
    state = read_state_dict(path)
    expected = module.state_dict()
    # BatchNorm's step counter is optional in checkpoints (torchvision's own files lack it).
    missing = sorted(k for k in expected.keys() - state.keys() if not k.endswith("num_batches_tracked"))
    unexpected = sorted(k for k in state.keys() - expected.keys() if not k.endswith("num_batches_tracked"))
    wrong_shape = sorted(
        f"{k}: file {tuple(state[k].shape)} vs model {tuple(expected[k].shape)}"
        for k in expected.keys() & state.keys()
        if state[k].shape != expected[k].shape
    )
    findings = {"missing keys": missing, "unexpected keys": unexpected, "shape mismatches": wrong_shape}
    problems = [
        f"{label} ({len(keys)}): {keys[:_SHOWN_KEYS]}{' ...' if len(keys) > _SHOWN_KEYS else ''}"
        for label, keys in findings.items()
        if keys
    ]
    if problems:
        raise WeightsError(f"weights file {path} does not match {type(module).__name__}: " + "; ".join(problems))
    module.load_state_dict(state, strict=False)
