"""Containers passed between detector stages: a padded image batch and per-image instances."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import torch
import torch.nn.functional as F

Tensor = torch.Tensor


@dataclass
class ImageList:
    """Images padded into one ``(N, C, H, W)`` tensor, with each image's true ``(h, w)``."""

    tensor: Tensor
    image_sizes: list[tuple[int, int]]

    def __len__(self) -> int:
        return len(self.image_sizes)

    @classmethod
    def from_tensor(
        cls, images: Tensor, image_sizes: Sequence[tuple[int, int]] | None = None, size_divisibility: int = 1
    ) -> ImageList:
        """Zero-pad the bottom/right of ``images`` to a multiple of ``size_divisibility``.

        ``image_sizes`` gives each image's valid region (default: the whole tensor); zero
        is the mean colour of normalised images, the usual padding for detection.
        """
        if images.dim() != 4:
            raise ValueError(f"images must be (N, C, H, W), got {tuple(images.shape)}")
        height, width = images.shape[-2:]
        if image_sizes is None:
            image_sizes = [(height, width)] * len(images)
        sizes = [(int(h), int(w)) for h, w in image_sizes]
        if len(sizes) != len(images):
            raise ValueError(f"{len(sizes)} image sizes for {len(images)} images")
        for h, w in sizes:
            if not (0 < h <= height and 0 < w <= width):
                raise ValueError(f"image size {(h, w)} does not fit the ({height}, {width}) batch tensor")
        step = max(int(size_divisibility), 1)
        pad_h, pad_w = -height % step, -width % step
        if pad_h or pad_w:
            images = F.pad(images, (0, pad_w, 0, pad_h))
        return cls(images, sizes)


class Instances:
    """Per-image fields of equal length (boxes, scores, labels, ...) plus the image size.

    Fields are attributes (``inst.boxes``), indexing selects rows of every field, so a
    stage can attach what it computes and later stages filter everything together.
    """

    def __init__(self, image_size: tuple[int, int], **fields: Any):
        object.__setattr__(self, "image_size", (int(image_size[0]), int(image_size[1])))
        object.__setattr__(self, "_fields", {})
        for name, value in fields.items():
            self.set(name, value)

    def set(self, name: str, value: Any) -> None:
        if self._fields and len(value) != len(self):
            raise ValueError(f"field {name!r} has {len(value)} rows, instances have {len(self)}")
        self._fields[name] = value

    def __setattr__(self, name: str, value: Any) -> None:
        self.set(name, value)

    def __getattr__(self, name: str) -> Any:
        fields = object.__getattribute__(self, "_fields")
        if name not in fields:
            raise AttributeError(f"Instances has no field {name!r}; fields: {sorted(fields)}")
        return fields[name]

    def has(self, name: str) -> bool:
        return name in self._fields

    def get_fields(self) -> dict[str, Any]:
        return dict(self._fields)

    def __len__(self) -> int:
        for value in self._fields.values():
            return len(value)
        return 0

    def __getitem__(self, index: int | slice | Tensor) -> Instances:
        if isinstance(index, int):
            index = slice(index, index + 1 if index != -1 else None)
        return Instances(self.image_size, **{name: value[index] for name, value in self._fields.items()})

    def __iter__(self) -> Iterator:
        raise TypeError("Instances is not iterable; index it or read its fields")

    def to(self, *args: Any, **kwargs: Any) -> Instances:
        moved = {k: v.to(*args, **kwargs) if hasattr(v, "to") else v for k, v in self._fields.items()}
        return Instances(self.image_size, **moved)

    @staticmethod
    def cat(parts: Sequence[Instances]) -> Instances:
        """Concatenate instances of the same image."""
        if not parts:
            raise ValueError("Instances.cat needs at least one part")
        names = set(parts[0]._fields)
        if any(set(p._fields) != names or p.image_size != parts[0].image_size for p in parts):
            raise ValueError("Instances.cat needs parts of one image with the same fields")
        return Instances(parts[0].image_size, **{n: torch.cat([p._fields[n] for p in parts]) for n in names})

    def __repr__(self) -> str:
        return f"Instances(num={len(self)}, image_size={self.image_size}, fields={sorted(self._fields)})"
