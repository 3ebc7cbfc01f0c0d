"""usl.engine.cpu_memory, checked against glibc's own accounting (``mallinfo2``): after
``retain_freed_memory`` a large tensor comes from the heap, not a mapping of its own, and its
memory stays in the process once freed, where glibc's defaults map it and hand it back."""

import json
import subprocess
import sys

import pytest

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt is Linux-only")

# In a fresh process (glibc's defaults untouched): mapped bytes while a 16 MiB tensor lives, and
# free heap bytes kept after it is freed.
PROBE = """
import ctypes, ctypes.util, json, sys, torch
from usl.engine.cpu_memory import retain_freed_memory

class MallInfo2(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in
                ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks", "fordblks", "keepcost")]

libc = ctypes.CDLL(ctypes.util.find_library("c"))
if not hasattr(libc, "mallinfo2"):
    print(json.dumps(None)); sys.exit()
libc.mallinfo2.restype = MallInfo2
tuned = sys.argv[1] == "tuned" and retain_freed_memory()
x = torch.empty(4 << 20)  # 16 MiB
x.fill_(1.0)
mapped = libc.mallinfo2().hblkhd
del x
print(json.dumps({"tuned": tuned, "mapped": mapped, "kept": libc.mallinfo2().fordblks}))
"""


def probe(mode: str) -> dict | None:
    out = subprocess.run([sys.executable, "-c", PROBE, mode], capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_large_tensors_come_from_the_heap_and_stay_there():
    default, tuned = probe("default"), probe("tuned")
    if default is None:
        pytest.skip("glibc older than 2.33 (no mallinfo2)")
    size = 16 << 20
    assert not default["tuned"] and tuned["tuned"]
    assert default["mapped"] >= size and default["kept"] < size  # its own mapping, unmapped when freed
    assert tuned["mapped"] < size and tuned["kept"] >= size  # from the heap, and kept for the next step
