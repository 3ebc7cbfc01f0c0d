"""Writing one shard atomically: streamed row groups into a temp file, checksum, then rename.

A shard is a ``frames-NNNNN.parquet`` file and, when the dataset has 3D ground truth, a matching
``objects-NNNNN.parquet``. Nothing appears under its final name until it is complete, so a killed
build leaves only temp files, which the next run removes and redoes.
"""
from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from .encode import SceneRecord, Skip
from .errors import UslError
from .schema import table_schema, with_metadata

# Small row groups keep "read one scene" cheap; a long video scene spans several groups.
MAX_ROWS_PER_GROUP = 64
MAX_SCENES_PER_GROUP = 4
BINARY_COLUMNS = ("image", "depth")
TMP_SUFFIX = ".tmp"


def sha256_file(path: Path, chunk: int = 1 << 20) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            digest.update(block)
    return digest.hexdigest()


def _nested_lists(arrays: list[np.ndarray], value_type: pa.DataType, width: int) -> pa.Array:
    """list<fixed_size_list<T, width>> from per-row (n_i, width) arrays, without Python per-value work."""
    flat = np.concatenate([a.reshape(-1) for a in arrays]) if arrays else np.zeros(0)
    inner = pa.FixedSizeListArray.from_arrays(pa.array(flat.astype(value_type.to_pandas_dtype())), width)
    offsets = np.zeros(len(arrays) + 1, dtype=np.int32)
    offsets[1:] = np.cumsum([a.reshape(-1, width).shape[0] for a in arrays])
    return pa.ListArray.from_arrays(pa.array(offsets), inner)


def objects_table(rows: list[dict[str, Any]], schema: pa.Schema) -> pa.Table:
    columns = {
        "scene_id": pa.array([r["scene_id"] for r in rows], pa.string()),
        "instance_id": pa.array([r["instance_id"] for r in rows], pa.int64()),
        "category_id": pa.array([r["category_id"] for r in rows], pa.int32()),
        "source_id": pa.array([r["source_id"] for r in rows], pa.string()),
        "vertices": _nested_lists([np.asarray(r["vertices"]) for r in rows], pa.float32(), 3),
        "faces": _nested_lists([np.asarray(r["faces"]) for r in rows], pa.int32(), 3),
    }
    return pa.Table.from_pydict(columns, schema=schema)


def frames_table(rows: list[dict[str, Any]], schema: pa.Schema) -> pa.Table:
    try:
        return pa.Table.from_pylist(rows, schema=schema)
    except (pa.ArrowInvalid, pa.ArrowTypeError, KeyError) as exc:
        raise ValueError(f"frame rows do not match record schema v1: {exc}") from exc


@dataclass
class ShardResult:
    """What a finished shard is: kept in the build state and copied into the manifest."""

    split: str
    index: int
    frames: dict[str, Any]
    objects: dict[str, Any] | None
    scenes: list[list[Any]]  # [scene_id, first_row, num_rows]
    skips: list[dict[str, Any]] = field(default_factory=list)


class _TableStream:
    """A ParquetWriter on a temp path that becomes ``final`` on ``commit``."""

    def __init__(self, final: Path, schema: pa.Schema, binary_plain: bool):
        self.final = final
        self.tmp = final.with_name(final.name + f"{TMP_SUFFIX}-{os.getpid()}")
        self.schema = schema
        self.rows = 0
        names = set(schema.names)
        binary = [c for c in BINARY_COLUMNS if c in names] if binary_plain else []
        self.writer = pq.ParquetWriter(
            self.tmp,
            schema,
            compression={n: ("NONE" if n in binary else "ZSTD") for n in schema.names},
            use_dictionary=[n for n in schema.names if n not in binary and n not in ("instances",)],
            column_encoding={n: "PLAIN" for n in binary} or None,
            write_statistics=["scene_id", "view_id"] if "view_id" in names else ["scene_id"],
        )

    def write(self, table: pa.Table) -> None:
        self.writer.write_table(table, row_group_size=MAX_ROWS_PER_GROUP)
        self.rows += table.num_rows

    def commit(self) -> dict[str, Any]:
        self.writer.close()
        with open(self.tmp, "rb") as f:
            os.fsync(f.fileno())
        info = {
            "file": f"{self.final.parent.name}/{self.final.name}",
            "rows": self.rows,
            "bytes": self.tmp.stat().st_size,
            "sha256": sha256_file(self.tmp),
        }
        os.replace(self.tmp, self.final)
        return info

    def abort(self) -> None:
        try:
            self.writer.close()
        finally:
            self.tmp.unlink(missing_ok=True)


class ShardWriter:
    """Streams scenes into one shard; use as a context manager so failures leave no partial file."""

    def __init__(self, root: Path, split: str, index: int, metadata: dict[str, Any]):
        self.split, self.index = split, index
        directory = Path(root) / split
        directory.mkdir(parents=True, exist_ok=True)
        self._frames = _TableStream(
            directory / f"frames-{index:05d}.parquet", with_metadata(table_schema("frames"), metadata), True
        )
        self._objects_path = directory / f"objects-{index:05d}.parquet"
        self._objects_schema = with_metadata(table_schema("objects"), metadata)
        self._objects: _TableStream | None = None
        self._pending: list[SceneRecord] = []
        self._scenes: list[list[Any]] = []
        self._skips: list[Skip] = []
        self._seen: set[str] = set()

    def add_scene(self, record: SceneRecord) -> None:
        if record.scene_id in self._seen:
            raise ValueError(f"scene {record.scene_id!r} added twice to shard {self.split}/{self.index}")
        views = [f["view_id"] for f in record.frames]
        if views != sorted(views) or len(set(views)) != len(views):
            raise ValueError(f"scene {record.scene_id!r}: frames must have unique, ascending view_id")
        if any(f["scene_id"] != record.scene_id for f in record.frames):
            raise ValueError(f"scene {record.scene_id!r}: a frame row carries another scene_id")
        self._seen.add(record.scene_id)
        self._skips.extend(record.skips)
        if not record.frames:
            return
        self._pending.append(record)
        if len(self._pending) >= MAX_SCENES_PER_GROUP or sum(len(r.frames) for r in self._pending) >= MAX_ROWS_PER_GROUP:
            self._flush()

    def _flush(self) -> None:
        if not self._pending:
            return
        frames: list[dict[str, Any]] = []
        objects: list[dict[str, Any]] = []
        for record in self._pending:
            self._scenes.append([record.scene_id, self._frames.rows + len(frames), len(record.frames)])
            frames.extend(record.frames)
            objects.extend(record.objects)
        self._frames.write(frames_table(frames, self._frames.schema))
        if objects:
            if self._objects is None:
                self._objects = _TableStream(self._objects_path, self._objects_schema, False)
            self._objects.write(objects_table(objects, self._objects_schema))
        self._pending.clear()

    def close(self) -> ShardResult:
        self._flush()
        objects = self._objects.commit() if self._objects is not None else None
        frames = self._frames.commit()
        skips = [{"reason": s.reason, "path": s.path, "count": s.count} for s in self._skips]
        return ShardResult(self.split, self.index, frames, objects, self._scenes, skips)

    def abort(self) -> None:
        self._frames.abort()
        if self._objects is not None:
            self._objects.abort()

    def __enter__(self) -> "ShardWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is not None:
            self.abort()


def verify_file(root: Path, info: dict[str, Any]) -> str | None:
    """Why a shard file does not match its recorded size/checksum/footer, or None if it does."""
    path = Path(root) / info["file"]
    if not path.exists():
        return f"{path}: missing"
    if path.stat().st_size != info["bytes"]:
        return f"{path}: size {path.stat().st_size} bytes, expected {info['bytes']} (truncated or replaced)"
    try:
        rows = pq.ParquetFile(path).metadata.num_rows
    except Exception as exc:  # pyarrow raises several types for broken footers
        return f"{path}: unreadable Parquet footer ({exc})"
    if rows != info["rows"]:
        return f"{path}: {rows} rows, expected {info['rows']}"
    if sha256_file(path) != info["sha256"]:
        return f"{path}: sha256 does not match the recorded checksum"
    return None


def remove_stale_temp_files(root: Path) -> int:
    stale = list(Path(root).glob(f"*/*.parquet{TMP_SUFFIX}-*"))
    for path in stale:
        path.unlink(missing_ok=True)
    return len(stale)


def raise_if_invalid(root: Path, info: dict[str, Any]) -> None:
    problem = verify_file(root, info)
    if problem:
        raise UslError(problem)
