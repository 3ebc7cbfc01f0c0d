"""Regions that must run in float32 whatever autocast the caller set (geometry, RoIAlign's pooling)."""

from __future__ import annotations

import contextlib

import torch


def autocast_off(device_type: str) -> contextlib.AbstractContextManager:
    """Autocast disabled on ``device_type``. A device without autocast has none to disable, and
    ``torch.autocast`` raises for it (meta, or mps on older torch), so it gets a null context."""
    available = getattr(torch.amp, "is_autocast_available", None)  # absent from older torch
    if available(device_type) if available else device_type in ("cpu", "cuda"):
        return torch.autocast(device_type, enabled=False)
    return contextlib.nullcontext()
