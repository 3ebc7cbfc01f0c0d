"""numba-compiled CPU loops beside torch paths (the soft rasterizer, mask resampling, 2D nearest points).

As the NMS's CPU loop in ``usl.model.ops.nms``: numba is a dependency, compiled loops are cached on
disk (compiled once per machine and argument types), and without numba the torch paths serve the
CPU too; the torch paths also serve other devices and are the tests' oracles. Loops get their
outputs preallocated, so compiled code never allocates.
"""

from __future__ import annotations

import torch

try:
    import numba
except ImportError:
    numba = None


def compiled(loop):
    """``loop`` compiled by numba (numpy's error model: x / 0 gives inf or nan as in torch), or
    unchanged without numba."""
    return numba.njit(cache=True, nogil=True, error_model="numpy")(loop) if numba else loop


def serves(tensor: torch.Tensor) -> bool:
    """Whether compiled loops serve ``tensor``: numba imports and it is a CPU tensor."""
    return numba is not None and tensor.device.type == "cpu"
