"""What the evaluator hands a predictor, and what a predictor must be.

The model and every baseline of the paper's tables are *predictors*: callables mapping a batch of
input views to one :class:`~usl.model.outputs.ObjectPredictions` each. The evaluator treats them
all alike, so a table row is just a predictor with a name.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import torch

from usl.data.frames import FrameData
from usl.data.true_meshes import TrueMesh  # noqa: F401  (part of EvalInput)
from usl.model.outputs import ObjectPredictions

Tensor = torch.Tensor


@dataclass
class EvalInput:
    """One input view as a predictor sees it.

    ``frame`` carries the decoded image, K and the 2D ground truth of the input view (boxes,
    labels, instance ids). Ground-truth-box predictors predict exactly one object per instance of
    ``frame`` and copy its ``instance_ids``. ``true_meshes`` (instance id -> mesh) is there for
    oracle baselines only; it is empty when the dataset has no 3D ground truth.
    """

    frame: FrameData
    true_meshes: dict[int, TrueMesh]


class Predictor(Protocol):
    """A table row: something that turns input views into object predictions.

    Attributes:
        name: the row label in reports.
        predicts_layout / predicts_shape: the "Predicts" columns of the paper's Table 2.
        uses_detections: False -> one prediction per ground-truth instance, ``instance_ids`` set;
            True -> the predictor detects objects itself (``instance_ids`` may be -1) and the
            evaluator matches them to the ground truth and computes detection AP.
    """

    name: str
    predicts_layout: bool
    predicts_shape: bool
    uses_detections: bool

    def __call__(self, inputs: Sequence[EvalInput]) -> list[ObjectPredictions]: ...
