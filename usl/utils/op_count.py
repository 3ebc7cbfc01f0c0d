"""Counting the ATen ops a piece of code dispatches and the points where it would wait for the device.

Wall time on a shared CPU is noise; op counts are deterministic. ``count_ops()`` records every op
dispatched (forward and backward) and every *host sync*: an op whose result the host must read
before it can go on (on CUDA it blocks until the device has caught up), whichever device the code
runs on, so a CPU run shows what a GPU run would wait for:

* ``scalar read``: ``.item()``, ``float(t)``, ``bool(t)``, ``if t:`` (``aten._local_scalar_dense``);
* ``nonzero``, ``boolean index`` (``t[mask]``, ``t[mask] = v``), ``masked_select``, ``unique``,
  ``repeat_interleave`` without ``output_size``, ``bincount``: output shapes that depend on data;
* ``tolist`` and ``numpy``: a tensor's data read into Python.

``uploads`` counts ``torch.tensor``/``torch.as_tensor`` calls, which build a tensor from host data
(a host-to-device copy on CUDA), apart from the syncs.

Source lines are the innermost frame in the project's own packages (``usl``, ``pipelines``,
``data_specs``, ``scripts``, ``tests``), never in an installed package (site-packages, the standard
library, torch), wherever the environment lives, a venv inside the checkout included.
"""

from __future__ import annotations

import os
import site
import sys
import sysconfig
from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch.overrides import TorchFunctionMode
from torch.utils._python_dispatch import TorchDispatchMode

aten = torch.ops.aten
_SYNC_OPS = {
    aten._local_scalar_dense.default: "scalar read",
    aten.nonzero.default: "nonzero",
    aten.masked_select.default: "masked_select",
    aten._unique2.default: "unique",
    aten.unique_dim.default: "unique",
    aten.unique_consecutive.default: "unique",
    aten.bincount.default: "bincount",
    aten.equal.default: "scalar read",
}
_INDEX_OPS = {aten.index.Tensor, aten.index_put.default, aten.index_put_.default, aten._index_put_impl_.default}
_HOST_READS = {torch.Tensor.tolist: "tolist", torch.Tensor.numpy: "numpy"}
_UPLOADS = {torch.tensor, torch.as_tensor}
_THIS_FILE = str(Path(__file__).resolve())
REPOSITORY = Path(__file__).resolve().parents[2]
PROJECT_PACKAGES = ("usl", "pipelines", "data_specs", "scripts", "tests")


@dataclass
class OpCount:
    """What ``count_ops`` saw: ``ops`` ATen ops, ``syncs`` host syncs by kind, ``uploads`` host-data
    tensors, and per source line (``path:line function``) the ops and syncs it caused."""

    ops: int = 0
    syncs: Counter = field(default_factory=Counter)
    uploads: int = 0
    op_lines: Counter = field(default_factory=Counter)
    sync_lines: Counter = field(default_factory=Counter)

    @property
    def total_syncs(self) -> int:
        return sum(self.syncs.values())


def _is_sync(func, args, kwargs) -> str | None:
    kind = _SYNC_OPS.get(func)
    if kind:
        return kind
    if func in _INDEX_OPS:
        indices = args[1] if len(args) > 1 else kwargs.get("indices", ())
        if any(isinstance(i, torch.Tensor) and i.dtype in (torch.bool, torch.uint8) for i in indices):
            return "boolean index"
    if func is aten.repeat_interleave.Tensor and kwargs.get("output_size") is None:
        return "repeat_interleave"
    return None


def installed_dirs() -> tuple[str, ...]:
    """Folders of installed code: site-packages (the running environment's, wherever it lives), the
    standard library, and torch's own folder."""
    paths = set(getattr(site, "getsitepackages", list)())
    paths.add(site.getusersitepackages())
    paths.update(sysconfig.get_paths()[name] for name in ("purelib", "platlib", "stdlib", "platstdlib"))
    paths.add(str(Path(torch.__file__).parent))
    return tuple(sorted({os.path.join(os.path.realpath(p), "") for p in paths if p}))


class _Site:
    """The innermost calling line in the project's own packages (outside this module), as
    ``path:line function`` with the path relative to the repository."""

    def __init__(
        self,
        root: Path = REPOSITORY,
        packages: tuple[str, ...] = PROJECT_PACKAGES,
        installed: tuple[str, ...] | None = None,
    ):
        self.root = os.path.join(os.path.realpath(root), "")
        self.packages = tuple(os.path.join(self.root, p, "") for p in packages)
        self.installed = installed_dirs() if installed is None else installed
        self._known: dict[str, str | None] = {}

    def project_path(self, filename: str) -> str | None:
        """``filename`` relative to the repository when it is project code, else None."""
        if filename not in self._known:
            path = os.path.realpath(filename) if os.path.isabs(filename) else filename
            parts = path.split(os.sep)
            own = (
                path != _THIS_FILE
                and path.startswith(self.packages)
                and not path.startswith(self.installed)
                and "site-packages" not in parts
                and "dist-packages" not in parts
            )
            self._known[filename] = path[len(self.root) :] if own else None
        return self._known[filename]

    def __call__(self) -> str:
        frame = sys._getframe(2)
        while frame is not None:
            path = self.project_path(frame.f_code.co_filename)
            if path is not None:
                return f"{path}:{frame.f_lineno} {frame.f_code.co_name}"
            frame = frame.f_back
        return "<outside>"


class _DispatchCounter(TorchDispatchMode):
    def __init__(self, result: OpCount, site: _Site):
        super().__init__()
        self.result, self.site = result, site

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        line = self.site()
        self.result.ops += 1
        self.result.op_lines[line] += 1
        kind = _is_sync(func, args, kwargs)
        if kind:
            self.result.syncs[kind] += 1
            self.result.sync_lines[f"{line} [{kind}]"] += 1
        return func(*args, **kwargs)


class _FunctionCounter(TorchFunctionMode):
    def __init__(self, result: OpCount, site: _Site):
        super().__init__()
        self.result, self.site = result, site

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kind = _HOST_READS.get(func)
        if kind:
            self.result.syncs[kind] += 1
            self.result.sync_lines[f"{self.site()} [{kind}]"] += 1
        elif func in _UPLOADS:
            self.result.uploads += 1
        return func(*args, **(kwargs or {}))


@contextmanager
def count_ops() -> Iterator[OpCount]:
    """Count what the block dispatches, attributed to the project's source lines."""
    result = OpCount()
    site = _Site()
    with _FunctionCounter(result, site), _DispatchCounter(result, site):
        yield result


def format_report(count: OpCount, top: int = 15) -> str:
    """The totals, syncs by kind, and the ``top`` source lines by ops and by syncs."""
    lines = [f"ATen ops: {count.ops}   host syncs: {count.total_syncs}   uploads (torch.tensor): {count.uploads}"]
    lines += [f"  {kind:>16}: {n}" for kind, n in count.syncs.most_common()]
    lines.append(f"top {top} lines by ops:")
    lines += [f"  {n:7d}  {line}" for line, n in count.op_lines.most_common(top)]
    lines.append(f"top {top} lines by host syncs:")
    lines += [f"  {n:7d}  {line}" for line, n in count.sync_lines.most_common(top)]
    return "\n".join(lines)
