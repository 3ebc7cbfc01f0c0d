"""Keep freed heap memory in the process instead of handing it back to the kernel (glibc only).

Why: a CPU training step allocates and frees the same large tensors every iteration (the soft
rasterizer's pair buffers, feature maps, their gradients). glibc serves allocations above its
mmap threshold with fresh ``mmap`` calls and trims the heap top after large frees, so each step
faults its working set in again page by page, and the kernel zeroes every page. In the main job's
two-process training that was ~1/5 of all CPU time as system time (120 iterations of ``tiny``:
6.5 M minor page faults, 20.9 s system CPU, against 0.41 M and 4.1 s with this). PyTorch's CPU
performance guides recommend jemalloc or tcmalloc for the same reason; two ``mallopt`` calls get
the same effect without another library. The cost: the process keeps its peak heap until it exits.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import sys

# mallopt parameters (glibc's malloc.h)
M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3
# The largest mmap threshold glibc accepts on 64-bit (HEAP_MAX_SIZE / 2): only blocks above 32 MiB
# still get their own mapping. Setting it also turns off glibc's dynamic threshold.
MMAP_THRESHOLD_BYTES = 32 << 20
# Free memory at the heap top is returned to the kernel only above 1 GiB.
TRIM_THRESHOLD_BYTES = 1 << 30


def retain_freed_memory() -> bool:
    """Raise glibc's mmap and trim thresholds for this process; False where there is no glibc
    (macOS; musl's mallopt does nothing) or glibc refused a value."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)) and bool(
        mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES)
    )
