"""numba-compiled CPU loops beside torch paths (the soft rasterizer, mask resampling, 2D nearest
points, the greedy NMS of ``usl.model.ops.nms``).

numba is a dependency, compiled loops are cached on disk (compiled once per machine and argument
types), and without numba the torch paths serve the CPU too; the torch paths also serve other
devices and are the tests' oracles. Loops get their outputs preallocated, so compiled code never
allocates.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import torch

try:
    import numba
except ImportError:
    numba = None


def compiled(loop):
    """``loop`` compiled by numba (numpy's error model: x / 0 gives inf or nan as in torch), or
    unchanged without numba."""
    return numba.njit(cache=True, nogil=True, error_model="numpy")(loop) if numba else loop


_torch_paths_only = False


def serves(tensor: torch.Tensor) -> bool:
    """Whether compiled loops serve ``tensor``: numba imports, it is a CPU tensor, and no
    :func:`torch_paths_only` block is open."""
    return numba is not None and tensor.device.type == "cpu" and not _torch_paths_only


@contextmanager
def torch_paths_only() -> Iterator[None]:
    """Within the block CPU tensors take the torch paths, as CUDA tensors always do: what
    ``scripts/bench/count_ops.py`` counts by default, the ops and host syncs of a CUDA step, on a
    machine without a GPU (a compiled loop reads its inputs on the host, which only the CPU pays)."""
    global _torch_paths_only
    previous, _torch_paths_only = _torch_paths_only, True
    try:
        yield
    finally:
        _torch_paths_only = previous
