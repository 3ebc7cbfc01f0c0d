"""Multi-view training samples from records: one item per (scene, input view).

An item is addressed by a ``SampleKey(index, epoch)``; every random choice of the item (other
views, object subset, the loss's seed) comes from a generator seeded by (seed, epoch, index),
so a sample is the same whichever DataLoader worker, process or GPU builds it, and a resumed
run sees exactly the data it would have seen.
"""
from __future__ import annotations

from collections import OrderedDict
from typing import Any, NamedTuple

import numpy as np
import torch
from torch.utils.data import Dataset

from usl.data.config import DataConfig
from usl.records import RecordsDataset, decode_mask, decoding, frame_K, frame_pose
from usl.errors import UslError

from .frames import CategoryIndex, FrameData, decode_frame
from .mirror import mirror_sample
from .samples import MultiViewSample, TargetView
from .sampling import sample_other_views
from .transforms import resize_frame, resize_target_view
from .true_meshes import object_true_meshes

# Columns a loss-only view needs (no image, no depth).
TARGET_COLUMNS = ("scene_id", "view_id", "height", "width", "K", "cam_to_world", "instances")
# Just the instance ids of every view: a cheap nested-column read for choosing views.
INDEX_COLUMNS = ("view_id", "instances.list.element.instance_id")
SCENE_CACHE_SIZE = 512


class SampleKey(NamedTuple):
    index: int
    epoch: int


class MultiViewDataset(Dataset):
    """``with_true_meshes`` adds each loss object's objects-table mesh in the input camera's frame
    (``loss.supervision=3d``); otherwise the objects table is never read."""

    def __init__(
        self, records: RecordsDataset, cfg: DataConfig, categories: CategoryIndex, seed: int = 0, with_true_meshes: bool = False
    ):
        if with_true_meshes and not records.has_objects:
            raise UslError(
                f"{records.root}: split {records.split!r} has no objects table (3D ground truth); "
                "loss.supervision=3d needs one (Scene-Shapes builds have it, Hypersim and ScanNet do not)"
            )
        self.records = records
        self.cfg = cfg
        self.categories = categories
        self.seed = seed
        self.with_true_meshes = with_true_meshes
        self.items: list[tuple[str, int]] = [
            (scene_id, position)
            for scene_id in records.scene_ids
            for position in range(0, records.num_views(scene_id), cfg.input_view_stride)
        ]
        self._scenes: OrderedDict[str, tuple[list[int], list[np.ndarray]]] = OrderedDict()

    def __len__(self) -> int:
        return len(self.items)

    def __getstate__(self) -> dict[str, Any]:
        state = dict(self.__dict__)
        state["_scenes"] = OrderedDict()
        return state

    def __getitem__(self, key: SampleKey | int) -> MultiViewSample:
        index, epoch = (key, 0) if isinstance(key, int) else key
        rng = np.random.default_rng([self.seed, epoch, index])
        scene_id, position = self.items[index]
        source = self.records.source(scene_id)
        frame = decode_frame(self.records.read_scene(scene_id, views=[position])[0], self.categories, source=source)
        rows = np.arange(len(frame.instance_ids))
        if 0 < self.cfg.max_objects < len(rows):
            rows = np.sort(rng.choice(len(rows), self.cfg.max_objects, replace=False))
        object_ids = frame.instance_ids[torch.from_numpy(rows)]
        view_ids, instance_ids = self.scene_index(scene_id)
        others = sample_other_views(
            view_ids, instance_ids, position, object_ids.numpy(), self.cfg.num_views - 1, self.cfg.view_sampling, rng
        )
        other_rows = self.records.read_scene(scene_id, views=others, columns=TARGET_COLUMNS) if others else []
        object_rows = torch.from_numpy(rows).long()
        views = [input_target_view(frame, object_rows)] + [decode_target_view(r, object_ids, source) for r in other_rows]
        true_meshes = None
        if self.with_true_meshes:  # camera-frame meshes: resizing the image does not change them
            where = f"{self.records.root} scene {scene_id!r}"
            true_meshes = object_true_meshes(self.records.read_objects(scene_id), object_ids.tolist(), frame.cam_to_world, where)
        sample = MultiViewSample(
            frame=resize_frame(frame, self.cfg.max_size),
            object_rows=object_rows,
            views=[resize_target_view(v, self.cfg.max_size) for v in views],
            seed=int(rng.integers(2**62)),
            true_meshes=true_meshes,
        )
        # drawn last and only when enabled, so samples without flipping are unchanged
        if self.cfg.flip_prob > 0 and rng.random() < self.cfg.flip_prob:
            sample = mirror_sample(sample)
        return sample

    def scene_index(self, scene_id: str) -> tuple[list[int], list[np.ndarray]]:
        """View ids and per-view instance ids of a scene (LRU-cached per process)."""
        if scene_id in self._scenes:
            self._scenes.move_to_end(scene_id)
            return self._scenes[scene_id]
        rows = self.records.read_scene(scene_id, columns=INDEX_COLUMNS)
        entry = (
            [int(r["view_id"]) for r in rows],
            [np.asarray([i["instance_id"] for i in r["instances"] or []], dtype=np.int64) for r in rows],
        )
        self._scenes[scene_id] = entry
        if len(self._scenes) > SCENE_CACHE_SIZE:
            self._scenes.popitem(last=False)
        return entry


def input_target_view(frame: FrameData, object_rows: torch.Tensor) -> TargetView:
    """The input view as the loss's first view (j = 1): every object is present."""
    return TargetView(
        view_id=frame.view_id,
        K=frame.K,
        cam_to_world=frame.cam_to_world,
        masks=frame.masks[object_rows],
        present=torch.ones(len(object_rows), dtype=torch.bool),
    )


def decode_target_view(row: dict[str, Any], object_ids: torch.Tensor, source: str = "") -> TargetView:
    """Masks of the given instance ids in another view (all-False where an id is absent)."""
    with decoding(row, source):
        return _decode_target_view(row, object_ids)


def _decode_target_view(row: dict[str, Any], object_ids: torch.Tensor) -> TargetView:
    height, width = int(row["height"]), int(row["width"])
    masks = torch.zeros(len(object_ids), height, width, dtype=torch.bool)
    present = torch.zeros(len(object_ids), dtype=torch.bool)
    slot = {int(i): k for k, i in enumerate(object_ids.tolist())}
    for instance in row["instances"] or []:
        k = slot.get(int(instance["instance_id"]))
        if k is not None:
            masks[k] = torch.from_numpy(decode_mask(instance["mask"]))
            present[k] = bool(masks[k].any())
    return TargetView(
        view_id=int(row["view_id"]),
        K=torch.from_numpy(frame_K(row)).float(),
        cam_to_world=torch.from_numpy(frame_pose(row)),
        masks=masks,
        present=present,
    )
