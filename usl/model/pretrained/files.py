"""Read LOCAL pretrained weight files into ``name -> tensor`` dicts, with errors that name the file.

Two on-disk formats exist in the wild for the networks we start from:

* ``torchvision``: a ``torch.save``'d state dict (optionally wrapped in ``state_dict`` / ``model``),
  e.g. ``resnet50-0676ba61.pth`` or ``maskrcnn_resnet50_fpn_coco-bf2d0c1e.pth``.
* ``detectron2``: a pickle of numpy arrays, either the model zoo's ``{"model": {...}, "__author__": ...}``
  (``model_final_f10217.pkl``) or a Caffe2 blob dict (``R-50.pkl``, optionally under ``blobs``).

Pickles are read with an unpickler that only builds numpy arrays and plain containers, so a
weights file cannot run code (the same guarantee as ``torch.load(weights_only=True)``).
"""

from __future__ import annotations

import pickle
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from usl.errors import UslError, one_line

Tensor = torch.Tensor
FORMATS = ("auto", "torchvision", "detectron2")
# Keys a torch checkpoint may wrap its state dict in (raw torchvision files have none).
_WRAPPER_KEYS = ("state_dict", "model")
# The only globals a weights pickle needs: numpy's array reconstruction and plain containers.
_PICKLE_GLOBALS = {
    ("numpy.core.multiarray", "_reconstruct"),
    ("numpy._core.multiarray", "_reconstruct"),
    ("numpy.core.multiarray", "scalar"),
    ("numpy._core.multiarray", "scalar"),
    ("numpy", "ndarray"),
    ("numpy", "dtype"),
    ("collections", "OrderedDict"),
}


class WeightsError(UslError, RuntimeError):
    """A weights file is missing, unreadable, or does not fit the model (a CLI's one-line error)."""


def torch_load_failure(exc: BaseException) -> str:
    """Why ``torch.load(weights_only=True)`` refused a file, in one line.

    torch's own message spans paragraphs and suggests ``weights_only=False``, which would run
    whatever code the file holds; this keeps the part that says what was refused.
    """
    text = str(exc)
    if "Weights only load failed" not in text:
        return one_line(f"{type(exc).__name__}: {text}")
    paragraphs = [" ".join(p.split()) for p in re.split(r"\n\s*\n", text) if p.strip()]
    details = [
        p.split("WeightsUnpickler error:", 1)[-1].strip()
        for p in paragraphs
        if not p.startswith(("Weights only load failed", "Check the documentation")) or "WeightsUnpickler error:" in p
    ]
    detail = "; ".join(d for d in details if d) or "it holds more than tensors"
    return f"refused: not a file of tensors only ({detail}); nothing in it was run"


@dataclass
class WeightsFile:
    path: Path
    format: str  # "torchvision" | "detectron2"
    tensors: dict[str, Tensor]
    author: str | None = None  # detectron2 model zoo files say who wrote them


def resolve_format(path: str | Path, requested: str = "auto") -> str:
    """``auto`` picks by suffix: ``.pkl`` is detectron2's format, anything else a torch file."""
    if requested not in FORMATS:
        raise WeightsError(f"init format {requested!r} is not one of {list(FORMATS)}")
    if requested != "auto":
        return requested
    return "detectron2" if Path(path).suffix == ".pkl" else "torchvision"


def read_weights(path: str | Path, requested: str = "auto") -> WeightsFile:
    path = Path(path)
    if not path.is_file():
        raise WeightsError(f"weights file {path} does not exist (weights are never downloaded; give a local path)")
    fmt = resolve_format(path, requested)
    if fmt == "torchvision":
        return WeightsFile(path, fmt, read_torch_state_dict(path))
    tensors, author = read_pickled_arrays(path)
    return WeightsFile(path, fmt, tensors, author)


def read_torch_state_dict(path: Path) -> dict[str, Tensor]:
    """A state dict saved with ``torch.save`` (optionally wrapped in ``state_dict``/``model``)."""
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # torch raises several types for corrupt or foreign files
        raise WeightsError(
            f"weights file {path} could not be read as a torch checkpoint: {torch_load_failure(error)}"
        ) from error
    for key in _WRAPPER_KEYS:
        if isinstance(payload, dict) and isinstance(payload.get(key), dict):
            payload = payload[key]
    if not isinstance(payload, dict) or not all(isinstance(v, Tensor) for v in payload.values()):
        raise WeightsError(f"weights file {path} does not hold a state dict of tensors")
    return dict(payload)


class _ArrayUnpickler(pickle.Unpickler):
    def find_class(self, module: str, name: str) -> Any:
        if (module, name) not in _PICKLE_GLOBALS:
            raise pickle.UnpicklingError(f"refusing to load {module}.{name} (only numpy arrays are allowed)")
        if module.startswith("numpy.core") and hasattr(np, "_core"):
            module = module.replace("numpy.core", "numpy._core", 1)  # numpy 2 moved it (and warns on the old name)
        return super().find_class(module, name)


def read_pickled_arrays(path: Path) -> tuple[dict[str, Tensor], str | None]:
    """Arrays of a detectron2 model zoo file (``model``) or a Caffe2 blob dict (``blobs`` or flat)."""
    try:
        with open(path, "rb") as stream:
            payload = _ArrayUnpickler(stream, encoding="latin1").load()  # latin1: Python 2 era Caffe2 files
    except Exception as error:
        raise WeightsError(
            f"weights file {path} could not be read as a detectron2/Caffe2 pickle: {one_line(error)}"
        ) from error
    if not isinstance(payload, dict):
        raise WeightsError(f"weights file {path} holds a {type(payload).__name__}, not a dict of arrays")
    author = payload.get("__author__") if isinstance(payload.get("__author__"), str) else None
    if isinstance(payload.get("model"), dict):
        arrays = payload["model"]
    elif isinstance(payload.get("blobs"), dict):
        arrays = payload["blobs"]
    else:
        arrays = {k: v for k, v in payload.items() if not k.startswith("__")}
    tensors = {}
    for name, value in arrays.items():
        if isinstance(value, Tensor):
            tensors[name] = value
        elif isinstance(value, np.ndarray):
            tensors[name] = torch.from_numpy(np.ascontiguousarray(value))
        else:
            raise WeightsError(f"weights file {path}: {name!r} is a {type(value).__name__}, not an array")
    return tensors, author
