"""What one training sample is: the input view (model input + detection targets) and the 2D
ground truth of its objects in M views (the multi-view loss's targets)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, fields, replace

import torch

from .frames import FrameData
from .true_meshes import TrueMesh

Tensor = torch.Tensor


@dataclass
class TargetView:
    """View j's ground truth for the N objects of a sample's input view.

    ``masks[o]`` is object o's true silhouette in this view (all False when the object is not
    annotated there: out of frame, fully occluded, or not tracked); ``present[o]`` says which.
    """

    view_id: int
    K: Tensor  # (3, 3) float32, for this view's (possibly resized) pixel frame
    cam_to_world: Tensor  # (4, 4) float64
    masks: Tensor  # (N, H, W) bool
    present: Tensor  # (N,) bool

    @property
    def size(self) -> tuple[int, int]:
        return int(self.masks.shape[-2]), int(self.masks.shape[-1])

    def to(self, device: torch.device | str, non_blocking: bool = False) -> "TargetView":
        return self.apply(lambda t: t.to(device, non_blocking=non_blocking))

    def pin_memory(self) -> "TargetView":
        """Page-locked copies, so ``to(cuda, non_blocking=True)`` overlaps the copy (DataLoader calls it)."""
        return self.apply(Tensor.pin_memory)

    def apply(self, fn: Callable[[Tensor], Tensor]) -> "TargetView":
        return replace(self, **{f.name: fn(getattr(self, f.name)) for f in fields(self) if f.name != "view_id"})


@dataclass
class MultiViewSample:
    """The input view, which of its instances the 3D loss uses, and their masks in M views.

    ``views[0]`` is the input view itself (j = 1 in the paper's sum). ``seed`` keys every random
    draw of this sample's loss (points on meshes and silhouettes), so the loss of a sample does
    not depend on the batch it lands in, the process, or the number of GPUs. ``true_meshes`` (one
    per loss object, in the input camera's frame) are there only for ``loss.supervision=3d``.
    """

    frame: FrameData
    object_rows: Tensor  # (N,) long: rows of ``frame``'s instances that are the loss's objects
    views: list[TargetView]
    seed: int
    true_meshes: list[TrueMesh] | None = None

    def to(self, device: torch.device | str, non_blocking: bool = False) -> "MultiViewSample":
        return self.apply(lambda t: t.to(device, non_blocking=non_blocking))

    def pin_memory(self) -> "MultiViewSample":
        """Page-locked copies, so ``to(cuda, non_blocking=True)`` overlaps the copy (DataLoader calls it)."""
        return self.apply(Tensor.pin_memory)

    def apply(self, fn: Callable[[Tensor], Tensor]) -> "MultiViewSample":
        """The sample with ``fn`` applied to each of its tensors."""
        frame = replace(
            self.frame,
            **{
                f.name: fn(getattr(self.frame, f.name))
                for f in fields(self.frame)
                if isinstance(getattr(self.frame, f.name), Tensor)
            },
        )
        meshes = None if self.true_meshes is None else [m.apply(fn) for m in self.true_meshes]
        return MultiViewSample(frame, fn(self.object_rows), [v.apply(fn) for v in self.views], self.seed, meshes)


def collate_samples(samples: list[MultiViewSample]) -> list[MultiViewSample]:
    """Batches stay lists: images differ in size and objects in number; the model pads images."""
    return list(samples)
