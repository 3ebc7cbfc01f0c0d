"""Counting the ATen ops a piece of code dispatches and the points where it would wait for the device.

Wall time on a shared CPU is noise; op counts are deterministic. ``count_ops()`` records every op
dispatched (forward and backward) and every *host sync*: a point where the host must wait for the
device before it can go on (on CUDA it blocks until the device has caught up), whichever device the
code runs on, so a CPU run shows what a GPU run would wait for:

* ``scalar read``: ``.item()``, ``float(t)``, ``bool(t)``, ``if t:`` (``aten._local_scalar_dense``);
* ``nonzero``, ``boolean index`` (``t[mask]``, ``t[mask] = v``), ``masked_select``, ``unique``,
  ``repeat_interleave`` without ``output_size``, ``bincount``: output shapes that depend on data;
* ``tolist`` and ``numpy``: a tensor's data read into Python;
* ``upload``: a copy of host data to the device from pageable memory: ``torch.tensor(values,
  device=d)`` (also ``as_tensor``, ``asarray``, ``new_tensor``), ``t.to(d)``, ``t.cuda()``,
  ``device_t.copy_(t)`` of a host tensor ``t``, ``device_t[[1, 0]]`` (a list index becomes a tensor
  on the indexed tensor's device). The host waits for the device's queue to drain
  before such a copy, whatever ``non_blocking`` says. ``OpCount.uploads`` counts every
  host-to-device copy; those from page-locked memory with ``non_blocking=True``
  (``usl.utils.transfer.to_device``, the loader's ``pin_memory``) are queued like kernels and are
  not syncs;
* ``host operand``: a host tensor with elements passed to an op on device tensors (CUDA copies an
  index tensor over, as an upload, and refuses other operands; 0-d host tensors are scalars).

Which tensors are on the host: on an accelerator, the CPU tensors. A run on the CPU is counted as if
it ran on an accelerator: host tensors are those made within the block without a ``device`` argument
(``torch.tensor(values)``, ``torch.from_numpy``, ``torch.zeros(n)``, ``.cpu()``) and those computed
from host tensors alone; an explicit ``device`` names the device (code meaning the host leaves it
out, or says ``.cpu()``), and tensors made before the block (parameters, the loader's batch, caches
built in a warm-up step) are on the device, so a host tensor kept from before the block and copied
within it shows on an accelerator only. ``pin_memory``, which needs an accelerator, is stood in for
by an uncounted copy, and ``to_device`` takes its accelerator path. With ``as_on_accelerator=False``
``count_ops`` counts the CPU's own run (all tensors on the host, no uploads).

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
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.overrides import TorchFunctionMode
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils.weak import WeakIdKeyDictionary

from usl.utils.transfer import accelerator_transfers

Tensor = torch.Tensor
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
_HOST_READS = {Tensor.tolist: "tolist", Tensor.numpy: "numpy"}
_FROM_VALUES = {torch.tensor, torch.as_tensor, torch.asarray}  # tensors from Python/numpy data
_THIS_FILE = str(Path(__file__).resolve())
REPOSITORY = Path(__file__).resolve().parents[2]
PROJECT_PACKAGES = ("usl", "pipelines", "data_specs", "scripts", "tests")


@dataclass
class OpCount:
    """What ``count_ops`` saw: ``ops`` ATen ops, ``syncs`` host syncs by kind (uploads from pageable
    memory included), ``uploads`` host-to-device copies, and per source line (``path:line function``)
    the ops and syncs it caused."""

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
        if any(isinstance(i, Tensor) and i.dtype in (torch.bool, torch.uint8) for i in indices):
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
        self.paused = False  # while the function counter runs a stand-in of its own
        self.functions: _FunctionCounter | None = None

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if self.paused:
            return func(*args, **kwargs)
        line = self.site()
        self.result.ops += 1
        self.result.op_lines[line] += 1
        kind = _is_sync(func, args, kwargs)
        if kind:
            self.result.syncs[kind] += 1
            self.result.sync_lines[f"{line} [{kind}]"] += 1
        out = func(*args, **kwargs)
        if func is aten.lift_fresh.default and self.functions and not self.functions.inside:
            self.functions._mark(out, pinned=False)  # host data through a constructor modes miss: from_numpy
        return out


def _tensors(value: Any) -> Iterator[Tensor]:
    if isinstance(value, Tensor):
        yield value
    elif isinstance(value, (list, tuple)):
        for item in value:
            yield from _tensors(item)
    elif isinstance(value, dict):
        for item in value.values():
            yield from _tensors(item)


def _lists_in(index: Any) -> bool:
    """Whether an index holds Python lists or numpy arrays of positions (advanced indexing)."""
    return any(isinstance(i, (list, np.ndarray)) for i in (index if isinstance(index, tuple) else (index,)))


def _parse_to(args: tuple, kwargs: dict) -> tuple[torch.device | None, Tensor | None, bool]:
    """``Tensor.to``'s target device (None for a dtype cast), the tensor it names if any, non_blocking."""
    rest, kwargs = list(args[1:]), {k: v for k, v in kwargs.items() if k != "copy"}
    if len(rest) == 4 or (len(rest) == 3 and isinstance(rest[0], (Tensor, torch.dtype))):
        rest.pop()  # the positional copy flag
    device, _, non_blocking, _ = torch._C._nn._parse_to(*rest, **kwargs)
    return device, rest[0] if rest and isinstance(rest[0], Tensor) else None, non_blocking


class _FunctionCounter(TorchFunctionMode):
    """Host reads, and uploads: which tensors are on the host, and what copies them to the device."""

    def __init__(self, result: OpCount, site: _Site, dispatch: _DispatchCounter, as_on_accelerator: bool):
        super().__init__()
        self.result, self.site, self.dispatch = result, site, dispatch
        self.simulated = as_on_accelerator
        self.host = WeakIdKeyDictionary()  # CPU run: host tensor -> page-locked
        self.inside = False  # within a call this mode sees
        dispatch.functions = self

    def _sync(self, kind: str) -> None:
        self.result.syncs[kind] += 1
        self.result.sync_lines[f"{self.site()} [{kind}]"] += 1

    def _upload(self, pinned: bool, non_blocking: bool) -> None:
        self.result.uploads += 1
        if not (pinned and non_blocking):
            self._sync("upload")

    def _on_host(self, tensor: Tensor, accelerator: bool) -> bool:
        """On an accelerator run every CPU tensor is on the host; on a CPU run, the tracked ones."""
        if tensor.device.type != "cpu":
            return False
        return accelerator or not self.simulated or tensor in self.host

    def _pinned(self, tensor: Tensor) -> bool:
        return self.host[tensor] if tensor in self.host else tensor.is_pinned()

    def _stand_in(self, func, *args) -> Tensor:
        """``func(*args)`` uncounted: a CPU run's stand-in for what an accelerator would do."""
        self.dispatch.paused = True
        try:
            return func(*args)
        finally:
            self.dispatch.paused = False

    def _mark(self, result: Any, pinned: bool | None) -> Any:
        """Record ``result``'s tensors as host tensors (``pinned`` True/False) or device ones (None)."""
        if self.simulated:
            for tensor in _tensors(result):
                if pinned is None:
                    self.host.pop(tensor, None)
                elif tensor.device.type == "cpu":
                    self.host[tensor] = pinned
        return result

    def __torch_function__(self, func, types, args=(), kwargs=None):
        self.inside = True
        try:
            return self._call(func, args, kwargs or {})
        finally:
            self.inside = False

    def _call(self, func, args, kwargs):
        kind = _HOST_READS.get(func)
        if kind:
            self._sync(kind)
        elif func is Tensor.pin_memory:
            return self._pin(func, args, kwargs)
        elif func is Tensor.cpu:
            return self._to_host(func(*args, **kwargs), args[0])
        elif func in (Tensor.to, Tensor.cuda, Tensor.copy_):
            return self._copy(func, args, kwargs)
        elif func in _FROM_VALUES or func is Tensor.new_tensor:
            return self._from_values(func, args, kwargs)
        elif func in (Tensor.__getitem__, Tensor.__setitem__) and _lists_in(args[1]):
            # torch makes a list index a tensor where the indexed tensor is: a copy from the host
            accelerator = args[0].device.type != "cpu"
            if not self._on_host(args[0], accelerator):
                self._upload(pinned=False, non_blocking=False)
        return self._other(func, args, kwargs)

    def _pin(self, func, args, kwargs):
        source = args[0]
        if self.simulated and source.device.type == "cpu" and not torch.cuda.is_available():
            return self._mark(self._stand_in(Tensor.clone, source), pinned=True)
        return self._mark(func(*args, **kwargs), pinned=True)

    def _to_host(self, result: Tensor, source: Tensor) -> Tensor:
        if result is source and self.simulated and source not in self.host:
            result = self._stand_in(Tensor.view_as, source, source)  # a CPU tensor's .cpu() is itself
        return self._mark(result, pinned=False)

    def _device_target(self, device: torch.device | None, other: Tensor | None, source: Tensor | None) -> tuple:
        """Whether a copy or constructor aimed at ``device`` (or at ``other``'s place) lands on the
        device, and whether an accelerator takes part; on a CPU run an explicit device is the device."""
        if other is not None:
            accelerator = other.device.type != "cpu" or (source is not None and source.device.type != "cpu")
            return not self._on_host(other, accelerator), accelerator
        accelerator = device.type != "cpu"
        from_accelerator = source is not None and source.device.type != "cpu"
        return accelerator or (self.simulated and not from_accelerator), accelerator

    def _copy(self, func, args, kwargs):
        """``t.to(...)``, ``t.cuda()``, ``dst.copy_(src)``: an upload when a host tensor goes to the device."""
        if func is Tensor.copy_:
            target, source = args[0], args[1]
            non_blocking = args[2] if len(args) > 2 else kwargs.get("non_blocking", False)
            to_device, accelerator = self._device_target(None, target, source)
        elif func is Tensor.cuda:
            source, to_device, accelerator = args[0], True, True
            non_blocking = args[2] if len(args) > 2 else kwargs.get("non_blocking", False)
        else:
            source = args[0]
            device, other, non_blocking = _parse_to(args, kwargs)
            if device is None and other is None:  # a dtype cast stays where it is
                return self._other(func, args, kwargs)
            to_device, accelerator = self._device_target(device, other, source)
        result = func(*args, **kwargs)
        if func is Tensor.copy_:
            if to_device and self._on_host(source, accelerator):
                self._upload(self._pinned(source), bool(non_blocking))
            return result
        if not to_device:
            return self._to_host(result, source)
        if self._on_host(source, accelerator):
            self._upload(self._pinned(source), bool(non_blocking))
            if result is source:  # a CPU run's .to(cpu) is the tensor itself; its copy is on the device
                result = self._stand_in(Tensor.view_as, source, source)
        return self._mark(result, pinned=None)

    def _from_values(self, func, args, kwargs):
        """``torch.tensor(values, device=d)`` and kin: an upload when the values are on the host and
        ``d`` (for ``new_tensor`` without one, the tensor's place) is the device. Such a copy reads
        a pageable buffer and waits for it."""
        if func is Tensor.new_tensor:
            owner, values, device = args[0], args[1], kwargs.get("device")
        else:
            owner, values = None, args[0]
            device = kwargs.get("device", args[2] if func is torch.as_tensor and len(args) > 2 else None)
            if device is None:  # on the host, or (as_tensor, asarray of a tensor) where the tensor is
                return self._other(func, args, kwargs)
        source = values if isinstance(values, Tensor) else None
        target = None if device is None else torch.device(device)
        to_device, accelerator = self._device_target(target, owner if target is None else None, source)
        result = func(*args, **kwargs)
        if not to_device:
            return self._mark(result, pinned=False)
        if source is None or self._on_host(source, accelerator):
            self._upload(pinned=False, non_blocking=False)
            if result is source:
                result = self._stand_in(Tensor.view_as, source, source)
        return self._mark(result, pinned=None)

    def _other(self, func, args, kwargs):
        """Any other function: a host tensor with elements among device operands is a sync; on a CPU
        run the result is on the host when made without a device, or from host tensors alone."""
        tensors = [*_tensors(args), *_tensors(kwargs)]
        accelerator = any(t.device.type != "cpu" for t in tensors)
        on_host = [self._on_host(t, accelerator) for t in tensors]
        if not all(on_host) and any(host and t.dim() > 0 for host, t in zip(on_host, tensors, strict=True)):
            self.result.uploads += 1
            self._sync("host operand")
        result = func(*args, **kwargs)
        if self.simulated and not accelerator and all(on_host) and kwargs.get("device") is None:
            self._mark(result, pinned=False)
        return result


@contextmanager
def count_ops(as_on_accelerator: bool = True) -> Iterator[OpCount]:
    """Count what the block dispatches, its host syncs and uploads, attributed to the project's
    source lines; a CPU run counts its transfers as on an accelerator (module docstring) unless
    ``as_on_accelerator`` is False."""
    result = OpCount()
    site = _Site()
    dispatch = _DispatchCounter(result, site)
    transfers = accelerator_transfers() if as_on_accelerator else nullcontext()
    with transfers, _FunctionCounter(result, site, dispatch, as_on_accelerator), dispatch:
        yield result


def format_report(count: OpCount, top: int = 15) -> str:
    """The totals, syncs by kind, and the ``top`` source lines by ops and by syncs."""
    waiting = count.syncs["upload"] + count.syncs["host operand"]
    lines = [
        f"ATen ops: {count.ops}   host syncs: {count.total_syncs} (uploads included)   "
        f"uploads: {count.uploads} ({waiting} from pageable memory, {count.uploads - waiting} page-locked)"
    ]
    lines += [f"  {kind:>16}: {n}" for kind, n in count.syncs.most_common()]
    lines.append(f"top {top} lines by ops:")
    lines += [f"  {n:7d}  {line}" for line, n in count.op_lines.most_common(top)]
    lines.append(f"top {top} lines by host syncs:")
    lines += [f"  {n:7d}  {line}" for line, n in count.sync_lines.most_common(top)]
    return "\n".join(lines)
