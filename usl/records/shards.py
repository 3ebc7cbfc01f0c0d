"""Writing one shard atomically: streamed row groups into a temp file, checksum, then rename.

A shard is a ``frames/<split>/frames-NNNNN.parquet`` file and, when the dataset has 3D ground
truth, a matching ``objects/<split>/objects-NNNNN.parquet`` (``schema.shard_file``, via
``shard_paths``). Nothing appears under its final name until it is complete, so a killed build
leaves only temp files named after their writer (``usl.records.tempfiles``), which a later run
removes once it knows the writer is gone, and redoes. Temp files are hidden (leading dot), so
pandas, pyarrow.dataset and Hugging Face never read a half-written shard beside finished ones.
Pages carry CRC checksums that every reader verifies, so flipped bytes fail loudly even where no
sha256 is computed.

A long scene (a whole video) need not be in memory at once: a ``FrameSink`` in the worker spills
its rows to a Parquet file group by group, and ``ShardWriter`` copies that file group by group.
Row groups are cut the same way whichever path a scene takes, so the shard bytes do not depend on it.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import uuid
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import quote

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from usl.errors import UslError, one_line

from .encode import SceneRecord, Skip
from .schema import dataset_schema, required_fields, shard_file, table_schema
from .tempfiles import process_token, temp_path

# Small row groups keep "read one scene" cheap; a long video scene spans several groups.
MAX_ROWS_PER_GROUP = 64
MAX_SCENES_PER_GROUP = 4
PAYLOAD_COLUMNS = ("image.bytes", "depth.bytes")  # encoded images: already compressed, stored PLAIN
# Instances (RLE strings, ids, boxes) are left uncompressed: ZSTD shrinks a frames shard by only
# ~3% but costs ~20% more CPU per random read (measured on Scene-Shapes, 256 px).
UNCOMPRESSED_FIELDS = ("instances",)


def shard_temp_path(final: Path, token: str | None = None) -> Path:
    """Where this process (or the one with ``token``) writes a shard file before renaming it."""
    return temp_path(final, hidden=True, token=token)


def shard_paths(root: Path, split: str, index: int) -> dict[str, Path]:
    """Final paths of one shard's tables (the layout is ``schema.shard_file``'s)."""
    return {table: Path(root) / shard_file(table, split, index) for table in ("frames", "objects")}


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
        table = pa.Table.from_pylist(rows, schema=schema)
    except (pa.ArrowInvalid, pa.ArrowTypeError, KeyError) as exc:
        raise ValueError(f"frame rows do not match the frames record schema: {exc}") from exc
    # Arrow fields are all nullable (schema.table_schema), so a missing required value is caught here.
    missing = [name for name in required_fields("frames") if table.column(name).null_count]
    if missing:
        raise ValueError(f"frame rows lack required field(s) {', '.join(missing)}")
    return table


@dataclass
class ShardResult:
    """What a finished shard is: kept in the build state and copied into the manifest."""

    split: str
    index: int
    frames: dict[str, Any]
    objects: dict[str, Any] | None
    scenes: list[list[Any]]  # [scene_id, first_row, num_rows]
    skips: list[dict[str, Any]] = field(default_factory=list)
    provenance: dict[str, dict[str, Any]] = field(default_factory=dict)  # scene_id -> SceneRecord.provenance


def _leaf_paths(prefix: str, type_: pa.DataType) -> list[str]:
    """Parquet column paths under a field (per-column writer options are keyed by these)."""
    if pa.types.is_struct(type_):
        return [p for child in type_ for p in _leaf_paths(f"{prefix}.{child.name}", child.type)]
    if pa.types.is_list(type_) or pa.types.is_fixed_size_list(type_):
        return _leaf_paths(f"{prefix}.list.element", type_.value_type)
    return [prefix]


class _TableStream:
    """A ParquetWriter on a hidden temp path that becomes ``final`` on ``commit``."""

    def __init__(self, final: Path, schema: pa.Schema, binary_plain: bool):
        self.final = final
        self.tmp = shard_temp_path(final)
        self.schema = schema
        self.rows = 0
        leaves = {f.name: _leaf_paths(f.name, f.type) for f in schema}
        payload = [p for p in PAYLOAD_COLUMNS if any(p in paths for paths in leaves.values())] if binary_plain else []
        self.writer = pq.ParquetWriter(
            self.tmp,
            schema,
            compression={
                p: ("NONE" if p in payload or n in UNCOMPRESSED_FIELDS else "ZSTD")
                for n, paths in leaves.items()
                for p in paths
            },
            use_dictionary=[
                p for n, paths in leaves.items() if n not in UNCOMPRESSED_FIELDS for p in paths if p not in payload
            ],
            column_encoding={p: "PLAIN" for p in payload} or None,
            write_statistics=["scene_id", "view_id"] if "view_id" in leaves else ["scene_id"],
            write_page_checksum=True,
        )

    def write(self, table: pa.Table) -> None:
        self.writer.write_table(table, row_group_size=MAX_ROWS_PER_GROUP)
        self.rows += table.num_rows

    def publish(self) -> Path:
        """Close and rename without fsync or checksum: a spill never outlives the run that wrote it."""
        self.writer.close()
        os.replace(self.tmp, self.final)
        return self.final

    def commit(self, file: str) -> dict[str, Any]:
        """Close, fsync, checksum and rename; ``file`` is the path the manifest lists."""
        self.writer.close()
        with open(self.tmp, "rb") as f:
            os.fsync(f.fileno())
        info = {
            "file": file,
            "rows": self.rows,
            "bytes": self.tmp.stat().st_size,
            "sha256": sha256_file(self.tmp),
        }
        os.replace(self.tmp, self.final)
        return info

    def abort(self) -> None:
        """Discard the temp file, also when the writer cannot even close (a full disk)."""
        with contextlib.suppress(OSError):
            self.writer.close()
        self.tmp.unlink(missing_ok=True)


def check_view_order(scene_id: str, scene_ids: Sequence[str], views: Sequence[int], last: int | None) -> int | None:
    """Raise unless the rows belong to ``scene_id`` and their views ascend strictly after ``last``.

    Returns the new last view, so a scene can be checked piece by piece as it streams.
    """
    for row_scene, view in zip(scene_ids, views, strict=True):
        if row_scene != scene_id:
            raise ValueError(f"scene {scene_id!r}: a frame row carries another scene_id ({row_scene!r})")
        if last is not None and view <= last:
            raise ValueError(f"scene {scene_id!r}: frames must have unique, ascending view_id ({view} after {last})")
        last = view
    return last


class FrameSink:
    """Collects one scene's frame rows so that a long scene is never whole in memory.

    The first ``MAX_ROWS_PER_GROUP`` rows stay in memory (a short scene costs no disk round trip).
    Past that, with a ``spill_dir``, rows go to a spill file there in row groups, and ``finish``
    returns a ``SceneRecord`` that names the file instead of holding the rows. Without a spill dir
    (``build_scene`` called outside a build) everything stays in memory. Rows are checked as they
    come, so a pipeline bug fails at the offending row, not after the whole scan.
    """

    def __init__(self, scene_id: str, spill_dir: Path | None):
        self.scene_id = scene_id
        self._spill_dir = spill_dir
        self._rows: list[dict[str, Any]] = []
        self._spill: _TableStream | None = None
        self._last_view: int | None = None

    def add(self, row: dict[str, Any]) -> None:
        self._last_view = check_view_order(self.scene_id, [row["scene_id"]], [row["view_id"]], self._last_view)
        self._rows.append(row)
        if len(self._rows) > MAX_ROWS_PER_GROUP and self._spill_dir is not None:
            if self._spill is None:
                # ids may hold "/"; the token names the writer, so only a gone writer's spills are reaped
                name = f"{quote(self.scene_id, safe='')}-{uuid.uuid4().hex[:12]}.{process_token()}.parquet"
                Path(self._spill_dir).mkdir(parents=True, exist_ok=True)
                self._spill = _TableStream(Path(self._spill_dir) / name, table_schema("frames"), True)
            self._spill.write(frames_table(self._rows[:MAX_ROWS_PER_GROUP], self._spill.schema))
            del self._rows[:MAX_ROWS_PER_GROUP]

    def finish(
        self,
        objects: Iterable[dict[str, Any]] = (),
        skips: Iterable[Skip] = (),
        provenance: dict[str, Any] | None = None,
    ) -> SceneRecord:
        """The scene's record; its spill file (if any) is complete and belongs to the shard writer now."""
        about = dict(provenance or {})
        if self._spill is None:
            return SceneRecord(self.scene_id, self._rows, list(objects), list(skips), provenance=about)
        if self._rows:
            self._spill.write(frames_table(self._rows, self._spill.schema))
            self._rows = []
        return SceneRecord(
            self.scene_id, [], list(objects), list(skips), frames_file=self._spill.publish(), provenance=about
        )

    def abort(self) -> None:
        if self._spill is not None:
            self._spill.abort()

    def __enter__(self) -> FrameSink:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is not None:
            self.abort()


def _frame_chunks(record: SceneRecord, schema: pa.Schema) -> Iterator[pa.Table]:
    """A scene's frame rows as Arrow tables, reading a spill file one row group at a time."""
    if record.frames_file is None:
        if record.frames:
            yield frames_table(record.frames, schema)
        return
    with pq.ParquetFile(record.frames_file) as spill:
        for group in range(spill.num_row_groups):
            yield spill.read_row_group(group).replace_schema_metadata(schema.metadata)


class ShardWriter:
    """Streams scenes into one shard; use as a context manager so failures leave no partial file.

    Row groups hold ``MAX_ROWS_PER_GROUP`` rows; a batch of scenes ends once it holds
    ``MAX_SCENES_PER_GROUP`` scenes or a full group, and its last group may be shorter. Rows are
    cut into groups as they arrive, so at most one group is held, however long a scene is.
    """

    def __init__(self, root: Path, split: str, index: int, metadata: dict[str, Any]):
        self.split, self.index = split, index
        self._files = {table: shard_file(table, split, index) for table in ("frames", "objects")}
        (Path(root) / self._files["frames"]).parent.mkdir(parents=True, exist_ok=True)
        self._frames = _TableStream(Path(root) / self._files["frames"], dataset_schema("frames", metadata), True)
        self._objects_path = Path(root) / self._files["objects"]
        self._objects_schema = dataset_schema("objects", metadata)
        self._objects: _TableStream | None = None
        self._group: list[pa.Table] = []  # pieces of the row group being filled
        self._group_rows = 0
        self._rows = 0  # rows added to the shard so far, written or in the group
        self._batch_scenes = 0
        self._batch_rows = 0
        self._batch_objects: list[dict[str, Any]] = []
        self._scenes: list[list[Any]] = []
        self._skips: list[Skip] = []
        self._provenance: dict[str, dict[str, Any]] = {}
        self._seen: set[str] = set()

    def add_scene(self, record: SceneRecord) -> int:
        """Append one scene (rows in memory or in its spill file, which is then deleted); its row count."""
        if record.scene_id in self._seen:
            raise ValueError(f"scene {record.scene_id!r} added twice to shard {self.split}/{self.index}")
        if record.frames and record.frames_file is not None:
            raise ValueError(f"scene {record.scene_id!r}: frames given both in memory and in {record.frames_file}")
        self._seen.add(record.scene_id)
        self._skips.extend(record.skips)
        if record.provenance:
            self._provenance[record.scene_id] = dict(record.provenance)
        first, last_view = self._rows, None
        for chunk in _frame_chunks(record, self._frames.schema):
            columns = chunk.select(["scene_id", "view_id"]).to_pydict()
            last_view = check_view_order(record.scene_id, columns["scene_id"], columns["view_id"], last_view)
            self._append(chunk)
        if record.frames_file is not None:
            Path(record.frames_file).unlink()  # copied: free the disk now, not at the shard's end
        count = self._rows - first
        if count == 0:
            return 0
        self._scenes.append([record.scene_id, first, count])
        self._batch_scenes += 1
        self._batch_rows += count
        self._batch_objects.extend(record.objects)
        if self._batch_scenes >= MAX_SCENES_PER_GROUP or self._batch_rows >= MAX_ROWS_PER_GROUP:
            self._end_batch()
        return count

    def _append(self, chunk: pa.Table) -> None:
        while chunk.num_rows:
            take = min(chunk.num_rows, MAX_ROWS_PER_GROUP - self._group_rows)
            self._group.append(chunk.slice(0, take))
            self._group_rows += take
            self._rows += take
            chunk = chunk.slice(take)
            if self._group_rows == MAX_ROWS_PER_GROUP:
                self._write_group()

    def _write_group(self) -> None:
        if self._group_rows:
            # One contiguous chunk, so the bytes cannot depend on how the group was pieced together
            # (a Parquet writer may cut pages at input chunk boundaries).
            self._frames.write(pa.concat_tables(self._group).combine_chunks())
        self._group, self._group_rows = [], 0

    def _end_batch(self) -> None:
        self._write_group()
        if self._batch_objects:
            if self._objects is None:
                self._objects_path.parent.mkdir(parents=True, exist_ok=True)
                self._objects = _TableStream(self._objects_path, self._objects_schema, False)
            self._objects.write(objects_table(self._batch_objects, self._objects_schema))
        self._batch_scenes, self._batch_rows, self._batch_objects = 0, 0, []

    def close(self) -> ShardResult:
        self._end_batch()
        objects = self._objects.commit(self._files["objects"]) if self._objects is not None else None
        frames = self._frames.commit(self._files["frames"])
        skips = [{"reason": s.reason, "path": s.path, "count": s.count} for s in self._skips]
        return ShardResult(self.split, self.index, frames, objects, self._scenes, skips, self._provenance)

    def abort(self) -> None:
        self._frames.abort()
        if self._objects is not None:
            self._objects.abort()

    def __enter__(self) -> ShardWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is not None:
            self.abort()


def size_problem(path: Path, info: dict[str, Any]) -> str | None:
    """Why a shard file is not the size its manifest entry says (missing, truncated, replaced)."""
    try:
        size = path.stat().st_size
    except FileNotFoundError:
        return f"{path}: missing"
    if size != info["bytes"]:
        return f"{path}: size {size} bytes, expected {info['bytes']} (truncated or replaced)"
    return None


def verify_file(root: Path, info: dict[str, Any]) -> str | None:
    """Why a shard file does not match its recorded size/checksum/footer, or None if it does."""
    path = Path(root) / info["file"]
    problem = size_problem(path, info)
    if problem:
        return problem
    try:
        rows = pq.ParquetFile(path).metadata.num_rows
    except Exception as exc:  # pyarrow raises several types for broken footers
        return f"{path}: unreadable Parquet footer ({exc})"
    if rows != info["rows"]:
        return f"{path}: {rows} rows, expected {info['rows']}"
    if sha256_file(path) != info["sha256"]:
        return f"{path}: sha256 does not match the recorded checksum"
    return None


VERIFY_MODES = ("size", "sha256")  # what readers check on open; sha256 reads each shard once more


def raise_if_invalid(root: Path, info: dict[str, Any]) -> None:
    problem = verify_file(root, info)
    if problem:
        raise UslError(problem)


def open_shard(root: Path, info: dict[str, Any]) -> pq.ParquetFile:
    """A manifest's shard file, opened only if its size is what the manifest says (a stat catches
    truncated and replaced files); page checksums are verified on every read from it."""
    path = Path(root) / info["file"]
    problem = size_problem(path, info)
    if problem:
        raise UslError(problem)
    try:
        return pq.ParquetFile(path, page_checksum_verification=True)
    except Exception as exc:  # pyarrow raises several types for broken footers
        raise UslError(f"{path}: cannot open Parquet shard ({one_line(exc)})") from exc


def read_shard_table(root: Path, info: dict[str, Any], columns: Sequence[str] | None = None) -> pa.Table:
    """A whole (size-checked) shard file as one table; any read failure is one line naming the file."""
    file = open_shard(root, info)
    try:
        return file.read(columns=list(columns) if columns else None)
    except Exception as exc:  # corrupt pages: checksum, decompression or decoding errors
        raise UslError(f"{Path(root) / info['file']}: cannot read ({one_line(exc)})") from exc
