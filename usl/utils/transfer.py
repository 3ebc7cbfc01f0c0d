"""Host data onto the device without the host waiting for the device.

A copy from pageable host memory (``torch.tensor(values, device=cuda)``, ``t.to(cuda)``) waits until
the device has run everything queued before it: a host sync, as a device read is. From page-locked
memory with ``non_blocking=True`` the copy is queued like a kernel, and the caching host allocator
keeps the page-locked buffer until the copy has run. :func:`to_device` takes that path for the
values the host computes per batch (sizes, counts, index plans); constants are made once per device.
"""

from __future__ import annotations

import functools
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import torch

_as_on_accelerator = False


def to_device(values: Any, device: torch.device | str, dtype: torch.dtype | None = None) -> torch.Tensor:
    """``values`` (Python numbers or sequences, a numpy array, a CPU tensor) as a tensor on ``device``,
    copied from page-locked memory without blocking; on the CPU, the host tensor itself."""
    host = torch.as_tensor(values, dtype=dtype)
    if torch.device(device).type == "cpu" and not _as_on_accelerator:
        return host
    return host.pin_memory().to(device, non_blocking=True)


@functools.lru_cache(maxsize=256)
def constant(values: tuple, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """``values`` (numbers or nested tuples) as a tensor on ``device``, copied over once per values,
    dtype and device and shared by every caller: never write into it."""
    return to_device(values, device, dtype)


@contextmanager
def accelerator_transfers() -> Iterator[None]:
    """Within the block :func:`to_device` takes its accelerator path on the CPU too: what
    ``usl.utils.op_count.count_ops`` counts, with a stand-in for ``pin_memory`` (which needs an
    accelerator). Outside a counting block ``pin_memory`` fails on a machine without one."""
    global _as_on_accelerator
    previous, _as_on_accelerator = _as_on_accelerator, True
    try:
        yield
    finally:
        _as_on_accelerator = previous
