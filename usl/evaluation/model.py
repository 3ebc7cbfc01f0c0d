"""The trained model as a predictor (table rows "USL" and "USL w/ detections").

The model sees each input view at its training resolution (``data.max_size`` of its config, as in
training); its boxes are mapped back to the stored image's pixel frame, while its meshes are in
camera coordinates and need no change.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from usl.data.frames import FrameData
from usl.data.transforms import resize_frame
from usl.errors import UslError
from usl.evaluation.types import EvalInput
from usl.model.outputs import ObjectPredictions
from usl.utils.transfer import to_device


def frames_for_model(frames: Sequence[FrameData], max_size: int) -> list[FrameData]:
    return [resize_frame(f, max_size) for f in frames]


def boxes_to_frame(
    pred: ObjectPredictions, model_size: tuple[int, int], frame_size: tuple[int, int]
) -> ObjectPredictions:
    """Boxes predicted on a resized image, back in the original image's pixel frame (a pure scale)."""
    if model_size == frame_size:
        return pred
    sx, sy = frame_size[1] / model_size[1], frame_size[0] / model_size[0]
    return replace(pred, boxes=pred.boxes * to_device([sx, sy, sx, sy], pred.boxes.device, pred.boxes.dtype))


@dataclass
class ModelPredictor:
    """``model.predict`` in ``"gt_boxes"`` or ``"detections"`` mode, at the model's input resolution."""

    model: Any  # usl.model.usl_model.USLModel
    max_size: int = 0
    mode: str = "gt_boxes"
    name: str = "USL"
    predicts_layout: bool = field(default=True, init=False)
    predicts_shape: bool = field(default=True, init=False)

    def __post_init__(self) -> None:
        self.uses_detections = self.mode == "detections"

    def __call__(self, inputs: Sequence[EvalInput]) -> list[ObjectPredictions]:
        frames = [inp.frame for inp in inputs]
        resized = frames_for_model(frames, self.max_size)
        preds = self.model.predict(resized, mode=self.mode)
        return [boxes_to_frame(p, r.size, f.size) for p, r, f in zip(preds, resized, frames, strict=True)]


# The table row of a model, by how it was trained (``loss.supervision``): Table 1's labels.
ROW_NAMES = {"2d": "USL", "3d": "Mesh R-CNN (3D sup.)"}


def load_checkpoint_model(checkpoint: str | Path, device: str):
    """``(model, config)`` with checkpoint problems turned into one-line ``UslError``s."""
    loaded = load_scored_checkpoint(checkpoint, device)
    return loaded.model, loaded.config


def load_scored_checkpoint(checkpoint: str | Path, device: str):
    """``usl.engine.checkpoint.LoadedCheckpoint``, with problems as one-line ``UslError``s."""
    from usl.engine.checkpoint import CheckpointError, load_checkpoint

    try:
        return load_checkpoint(checkpoint, device)
    except CheckpointError as exc:
        raise UslError(str(exc)) from exc


def model_predictors(
    checkpoint: str | Path, device: str, category_names: Sequence[str] | None = None, name: str | None = None
) -> tuple[ModelPredictor, ModelPredictor, dict[str, Any]]:
    """The model with ground-truth boxes and with its own detections, sharing one loaded network,
    and what was scored (``{"path", "iteration", "supervision"}``, for the report). ``name`` labels
    the rows; by default it says how the model was trained (``ROW_NAMES``)."""
    loaded = load_scored_checkpoint(checkpoint, device)
    config = loaded.config
    model_categories = list(config.model.categories)
    if category_names is not None and model_categories != list(category_names):
        raise UslError(
            f"{checkpoint}: the model was trained on categories {model_categories}, the dataset has {list(category_names)}"
        )
    name = name or ROW_NAMES[config.loss.supervision]
    max_size = int(config.data.max_size)
    scored = {
        "path": str(loaded.path),
        "iteration": loaded.iteration,
        "supervision": config.loss.supervision,
        "name": name,
    }
    return (
        ModelPredictor(loaded.model, max_size, "gt_boxes", name),
        ModelPredictor(loaded.model, max_size, "detections", f"{name} w/ detections"),
        scored,
    )
