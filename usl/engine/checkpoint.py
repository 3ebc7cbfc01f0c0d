"""Checkpoints: atomic files holding the model, its full config and the training state.

A checkpoint is a ``torch.save`` dict (loadable with ``weights_only=True``):
``format`` (int), ``config`` (the resolved ``usl.config.Config`` as a plain dict), ``model``
(state dict of ``USLModel``), ``iteration``, and for resuming ``optimizer``, ``scheduler``,
``scaler``, ``data`` ({epoch, batch}) and ``rng`` (one entry per rank); ``replica_sha256`` (one
entry per rank: ``usl.engine.distributed.parameter_digest`` of its weights, equal in every rank).

Consumers (evaluation, prediction) need only::

    from usl.engine.checkpoint import load_model
    model, config = load_model("runs/hypersim/checkpoints/model_0080000.pt")  # or the run folder
    predictions = model.predict(frames, mode="gt_boxes")  # list[ObjectPredictions]
"""

from __future__ import annotations

import os
import random
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from usl.config import Config, ConfigError, saved_config
from usl.model.pretrained.files import torch_load_failure
from usl.records.atomic import write_text_atomic
from usl.records.tempfiles import temp_path

CHECKPOINT_FORMAT = 1
CHECKPOINT_DIR = "checkpoints"
LAST_POINTER = "last_checkpoint"


class CheckpointError(RuntimeError):
    """A checkpoint file or run folder is missing, unreadable or not a usl checkpoint."""


def save_atomic(payload: dict[str, Any], path: str | Path) -> Path:
    """``torch.save`` to a temp file in the same folder, fsync, then rename over ``path``.

    The temp file carries this process's token, so a later run reaps it once this one is gone
    (killed mid-save): ``claims.sole_writer`` with the folder among its ``token_dirs``.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temp_path(path, hidden=True)
    try:
        with open(tmp, "wb") as f:
            torch.save(payload, f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def resolve_checkpoint(path: str | Path) -> Path:
    """A checkpoint file, or a run folder / its ``checkpoints`` folder (-> the newest checkpoint)."""
    path = Path(path)
    if path.is_dir():
        folder = path / CHECKPOINT_DIR if (path / CHECKPOINT_DIR).is_dir() else path
        pointer = folder / LAST_POINTER
        if not pointer.is_file():
            raise CheckpointError(f"{path}: no checkpoint in this folder (missing {pointer})")
        path = folder / pointer.read_text().strip()
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path} does not exist")
    return path


def read_checkpoint(path: str | Path) -> dict[str, Any]:
    """Load and check a checkpoint dict (on CPU)."""
    path = resolve_checkpoint(path)
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # truncated files, foreign pickles and non-torch files raise various types
        raise CheckpointError(f"checkpoint {path} could not be read: {torch_load_failure(exc)}") from exc
    if not isinstance(payload, dict) or "model" not in payload or "config" not in payload:
        raise CheckpointError(f"{path} is not a usl checkpoint (expected a dict with 'model' and 'config')")
    if payload.get("format") != CHECKPOINT_FORMAT:
        raise CheckpointError(
            f"{path}: checkpoint format {payload.get('format')!r}, this usl reads {CHECKPOINT_FORMAT}"
        )
    payload["path"] = str(path)
    return payload


def checkpoint_config(payload: dict[str, Any]) -> Config:
    """The checkpoint's config; keys this version no longer has are ignored with one ``UslWarning``."""
    try:
        return saved_config(payload["config"], where=payload.get("path", "checkpoint"))
    except ConfigError as exc:
        raise CheckpointError(f"{payload.get('path', 'checkpoint')}: stored config is invalid: {exc}") from exc


@dataclass
class LoadedCheckpoint:
    """A trained model with what says which one it is: reports name the file and iteration scored."""

    model: Any  # usl.model.usl_model.USLModel, in eval mode
    config: Config
    path: Path  # the checkpoint file (a run folder resolves to its newest)
    iteration: int


def load_checkpoint(checkpoint_path: str | Path, device: str | torch.device = "cpu") -> LoadedCheckpoint:
    """The model of a checkpoint file or run folder, with its config, file and iteration."""
    from usl.model.usl_model import USLModel  # the model imports engine-free modules only

    payload = read_checkpoint(checkpoint_path)
    config = checkpoint_config(payload)
    model = USLModel(config.model, config.loss, load_init_weights=False)  # the checkpoint holds every weight
    try:
        model.load_state_dict(payload["model"])
    except RuntimeError as exc:
        raise CheckpointError(f"{payload['path']}: weights do not fit the model its config describes: {exc}") from exc
    return LoadedCheckpoint(
        model.to(device).eval(), config, Path(payload["path"]).resolve(), int(payload.get("iteration", -1))
    )


def load_model(checkpoint_path: str | Path, device: str | torch.device = "cpu"):
    """``(USLModel in eval mode on device, Config)`` from a checkpoint file or run folder."""
    loaded = load_checkpoint(checkpoint_path, device)
    return loaded.model, loaded.config


# ----------------------------------------------------------------------------- run folders
def checkpoint_name(iteration: int) -> str:
    return f"model_{iteration:07d}.pt"


def write_run_checkpoint(run_dir: str | Path, iteration: int, payload: dict[str, Any], keep: int = 0) -> Path:
    """Save ``payload`` as ``<run>/checkpoints/model_<iteration>.pt``, point ``last_checkpoint``
    at it (also atomically), and delete all but the ``keep`` newest (``keep <= 0`` keeps all)."""
    folder = Path(run_dir) / CHECKPOINT_DIR
    path = save_atomic(
        {"format": CHECKPOINT_FORMAT, **payload, "iteration": iteration}, folder / checkpoint_name(iteration)
    )
    write_text_atomic(folder / LAST_POINTER, path.name + "\n")
    if keep > 0:
        for old in sorted(folder.glob("model_*.pt"))[:-keep]:
            old.unlink(missing_ok=True)
    return path


# ----------------------------------------------------------------------------- RNG state
def rng_state() -> dict[str, Any]:
    """This process's random state (python, numpy, torch CPU and CUDA), as tensors and lists."""
    kind, keys, pos, has_gauss, cached = np.random.get_state()
    return {
        "python": random.getstate(),
        "numpy": [kind, torch.from_numpy(keys.astype(np.int64)), pos, has_gauss, cached],
        "torch": torch.get_rng_state(),
        "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else [],
    }


def set_rng_state(state: dict[str, Any]) -> None:
    version, internal, gauss = state["python"]
    random.setstate((version, tuple(internal), gauss))
    kind, keys, pos, has_gauss, cached = state["numpy"]
    np.random.set_state((kind, keys.numpy().astype(np.uint32), pos, has_gauss, cached))
    torch.set_rng_state(state["torch"])
    if state["cuda"] and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])
