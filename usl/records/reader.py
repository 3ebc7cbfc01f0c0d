"""Reading records: random access by scene, and iteration split across DataLoader workers and ranks.

Shards are opened lazily and per process, so a ``RecordsDataset`` pickles cheaply into DataLoader
workers and never shares a file handle across a fork.
"""

from __future__ import annotations

import os
from bisect import bisect_right
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.parquet as pq
import torch
from torch.utils.data import IterableDataset, get_worker_info

from usl.errors import UslError, one_line

from .manifest import load_manifest
from .schema import read_metadata
from .shards import VERIFY_MODES, open_shard, verify_file
from .upgrade import upgrade_table


@dataclass(frozen=True)
class SceneLocation:
    shard: int  # position in the split's shard list
    first_row: int
    num_rows: int


class _OpenShard:
    """A verified Parquet file plus the first row of each row group, for reading a row range cheaply.

    Rows come back in the current schema whatever version the file was written in.
    """

    def __init__(self, root: Path, info: dict[str, Any], table: str):
        self.path = root / info["file"]
        self.file: pq.ParquetFile = open_shard(root, info)
        self.table = table
        self.version = read_metadata(self.file.schema_arrow, str(self.path))["schema_version"]
        meta = self.file.metadata
        self.group_starts = np.cumsum([0] + [meta.row_group(i).num_rows for i in range(meta.num_row_groups)])

    def read_rows(self, first: int, offsets: Sequence[int], columns: Sequence[str] | None) -> list[dict[str, Any]]:
        """Rows ``first + o`` for each offset, reading only the row groups that hold them and
        converting only those rows to Python (a scene's row groups also hold its other views)."""
        rows = [first + o for o in offsets]
        g0 = bisect_right(self.group_starts, min(rows)) - 1
        g1 = bisect_right(self.group_starts, max(rows)) - 1
        table = self.file.read_row_groups(list(range(g0, g1 + 1)), columns=list(columns) if columns else None)
        base = int(self.group_starts[g0])
        return upgrade_table(table.take([r - base for r in rows]), self.table, self.version).to_pylist()

    def read_all(self) -> list[dict[str, Any]]:
        try:
            return upgrade_table(self.file.read(), self.table, self.version).to_pylist()
        except Exception as exc:  # corrupt pages: checksum, decompression or decoding errors
            raise UslError(f"{self.path}: cannot read ({one_line(exc)})") from exc


class RecordsDataset:
    """One split of a dataset folder, indexed by scene.

    ``read_scene(scene_id)`` returns that scene's frame rows (dicts in the current schema, v3,
    also for a v1 or v2 dataset; sorted by view_id); ``views`` picks rows by position within the scene.
    Decode fields with ``usl.records.decode_image`` / ``decode_depth`` / ``decode_mask``, naming
    ``source(scene_id)`` in errors. Every shard is checked against the manifest when first opened
    (its size); with ``verify="sha256"`` every shard's checksum is checked once, here, before any
    worker reads it.
    """

    def __init__(self, root: str | Path, split: str, verify: str = "size"):
        if verify not in VERIFY_MODES:
            raise UslError(f"unknown shard verification {verify!r}; choose from {VERIFY_MODES}")
        self.root = Path(root)
        self.split = split
        self.manifest = load_manifest(self.root)
        if split not in self.manifest["splits"]:
            raise UslError(f"{self.root / 'manifest.json'}: no split {split!r} (has {sorted(self.manifest['splits'])})")
        self.shards = self.manifest["splits"][split]["shards"]
        self.locations: dict[str, SceneLocation] = {}
        for shard_pos, shard in enumerate(self.shards):
            for scene_id, first, count in shard["scenes"]:
                self.locations[scene_id] = SceneLocation(shard_pos, first, count)
        self.scene_ids: list[str] = list(self.locations)
        if verify == "sha256":
            for info in (s[t] for s in self.shards for t in ("frames", "objects") if s.get(t)):
                problem = verify_file(self.root, info)
                if problem:
                    raise UslError(problem)
        self._open: dict[tuple[int, str, int], _OpenShard] = {}
        self._objects_cache: dict[int, dict[str, list[dict[str, Any]]]] = {}

    @property
    def categories(self) -> list[dict[str, Any]]:
        return self.manifest["categories"]

    def __len__(self) -> int:
        return len(self.scene_ids)

    def __getstate__(self) -> dict[str, Any]:
        state = dict(self.__dict__)
        state["_open"], state["_objects_cache"] = {}, {}
        return state

    def _shard(self, shard_pos: int, table: str) -> _OpenShard:
        key = (os.getpid(), table, shard_pos)
        if key not in self._open:
            info = self.shards[shard_pos][table]
            if info is None:
                raise UslError(f"{self.root}: split {self.split!r} has no {table} table")
            self._open[key] = _OpenShard(self.root, info, table)
        return self._open[key]

    def source(self, scene_id: str) -> str:
        """The frames shard holding a scene, for error messages."""
        return str(self.root / self.shards[self._location(scene_id).shard]["frames"]["file"])

    def num_views(self, scene_id: str) -> int:
        return self._location(scene_id).num_rows

    def _location(self, scene_id: str) -> SceneLocation:
        try:
            return self.locations[scene_id]
        except KeyError:
            raise KeyError(f"scene {scene_id!r} is not in split {self.split!r} of {self.root}") from None

    def read_scene(
        self, scene_id: str, views: Sequence[int] | None = None, columns: Sequence[str] | None = None
    ) -> list[dict[str, Any]]:
        loc = self._location(scene_id)
        shard = self._shard(loc.shard, "frames")
        views = list(range(loc.num_rows)) if views is None else list(views)
        if any(not 0 <= v < loc.num_rows for v in views):
            raise IndexError(f"scene {scene_id!r} has {loc.num_rows} views; asked for {views}")
        if not views:
            return []
        try:
            return shard.read_rows(loc.first_row, views, columns)
        except Exception as exc:  # corrupt pages: checksum, decompression or decoding errors
            raise UslError(
                f"{shard.path}: scene {scene_id!r} views at positions {views}: cannot read ({one_line(exc)})"
            ) from exc

    @property
    def has_objects(self) -> bool:
        """Whether every shard of the split has an objects table (3D ground truth)."""
        return bool(self.shards) and all(s.get("objects") for s in self.shards)

    def read_objects(self, scene_id: str) -> list[dict[str, Any]]:
        """3D ground-truth objects of a scene (empty if the dataset has none)."""
        loc = self._location(scene_id)
        if self.shards[loc.shard]["objects"] is None:
            return []
        if loc.shard not in self._objects_cache:
            rows = self._shard(loc.shard, "objects").read_all()
            by_scene: dict[str, list[dict[str, Any]]] = {}
            for row in rows:
                by_scene.setdefault(row["scene_id"], []).append(row)
            self._objects_cache = {loc.shard: by_scene}  # keep one shard's objects in memory at a time
        return self._objects_cache[loc.shard].get(scene_id, [])


def partition(items: Sequence[Any], part: int, num_parts: int) -> list[Any]:
    """Strided partition: every item goes to exactly one part, part sizes differ by at most one."""
    return list(items[part::num_parts])


class SceneStream(IterableDataset):
    """Iterates over whole scenes, each exactly once across all DataLoader workers and ranks.

    ``rank``/``world_size`` default to torch.distributed's when it is initialised. With
    ``shuffle``, the scene order is a permutation seeded by (seed, epoch), identical on every rank.
    """

    def __init__(
        self,
        dataset: RecordsDataset,
        rank: int | None = None,
        world_size: int | None = None,
        shuffle: bool = False,
        seed: int = 0,
        columns: Sequence[str] | None = None,
    ):
        self.dataset = dataset
        dist = torch.distributed
        initialised = dist.is_available() and dist.is_initialized()
        self.rank = rank if rank is not None else (dist.get_rank() if initialised else 0)
        self.world_size = world_size if world_size is not None else (dist.get_world_size() if initialised else 1)
        self.shuffle, self.seed, self.epoch = shuffle, seed, 0
        self.columns = columns

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def scene_order(self) -> list[str]:
        ids = list(self.dataset.scene_ids)
        if self.shuffle:
            gen = torch.Generator().manual_seed(self.seed * 100003 + self.epoch)
            ids = [ids[i] for i in torch.randperm(len(ids), generator=gen).tolist()]
        return ids

    def __iter__(self) -> Iterator[tuple[str, list[dict[str, Any]]]]:
        worker = get_worker_info()
        num_workers, worker_id = (worker.num_workers, worker.id) if worker else (1, 0)
        part = self.rank * num_workers + worker_id
        for scene_id in partition(self.scene_order(), part, self.world_size * num_workers):
            yield scene_id, self.dataset.read_scene(scene_id, columns=self.columns)
