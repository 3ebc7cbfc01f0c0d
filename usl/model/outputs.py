"""What a model (or a baseline) predicts for one input image: the contract between the model,
the evaluator, the report and ``usl-predict``."""

from __future__ import annotations

from dataclasses import dataclass, fields

import torch


@dataclass
class ObjectPredictions:
    """N objects predicted from one input view.

    All meshes share one topology (the deformed ico-sphere), so vertices are a dense (N, V, 3)
    tensor and ``faces`` is shared.
    """

    boxes: torch.Tensor  # (N, 4) xyxy in the input view's pixel frame
    labels: torch.Tensor  # (N,) contiguous category index (data_specs order)
    scores: torch.Tensor  # (N,) detection score (1 for ground-truth boxes)
    z: torch.Tensor  # (N,) predicted depth of the object centre (layout head)
    rho: torch.Tensor  # (N,) predicted depth extent (layout head)
    verts: torch.Tensor  # (N, V, 3) mesh vertices in the input camera's frame, metres
    faces: torch.Tensor  # (F, 3) int64, shared by every mesh
    instance_ids: torch.Tensor  # (N,) ground-truth instance id each object stands for, -1 if none

    def __len__(self) -> int:
        return int(self.boxes.shape[0])

    def to(self, device: torch.device | str) -> ObjectPredictions:
        return ObjectPredictions(**{f.name: getattr(self, f.name).to(device) for f in fields(self)})

    def select(self, keep: torch.Tensor) -> ObjectPredictions:
        """Subset of objects (boolean mask or indices); faces stay shared."""
        values = {f.name: getattr(self, f.name) for f in fields(self)}
        return ObjectPredictions(**{k: (v if k == "faces" else v[keep]) for k, v in values.items()})
