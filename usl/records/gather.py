"""``usl-records gather``: merge build folders made apart into one dataset folder.

For clusters without a shared disk: each machine builds its part (``--num-shards N --shard-index
i --out part_i``), the parts are copied together, and ``gather`` checks that they are parts of one
build (same dataset, arguments and shard plan), copies every finished shard into the output with
its checksum verified on the way, and writes the manifest once every planned shard is there.
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from tqdm import tqdm

from usl.errors import UslError

from .build_state import BUILD_FILE, STATE_DIR, BuildState, identity_difference, read_build_file, shard_name
from .claims import Owner
from .manifest import SHARD_FILE_KEYS, build_manifest, check_relative, publish_dataset
from .names import check_name
from .schema import SCHEMA_VERSION, file_schema_version, shard_file
from .shards import ShardResult, size_problem
from .storage_faults import storage_faults
from .tempfiles import temp_path

CHUNK = 1 << 20


@dataclass
class GatherSummary:
    copied: int = 0
    kept: int = 0
    missing: list[str] = field(default_factory=list)


def _copy_verified(source: Path, target: Path, info: dict[str, Any]) -> None:
    """Copy ``source`` to ``target`` through a temp file, hashing on the way; refuse a mismatch."""
    problem = size_problem(source, info)
    if problem:
        raise UslError(problem)
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = temp_path(target)
    digest = hashlib.sha256()
    try:
        with open(source, "rb") as src, open(tmp, "wb") as dst:
            while block := src.read(CHUNK):
                digest.update(block)
                dst.write(block)
            dst.flush()
            os.fsync(dst.fileno())
        if digest.hexdigest() != info["sha256"]:
            raise UslError(f"{source}: sha256 does not match the checksum its build recorded")
        os.replace(tmp, target)
    finally:
        tmp.unlink(missing_ok=True)


def _part_shard(part: Path, state: BuildState, split: str, index: int) -> dict[str, Any] | None:
    """A part's record of one finished shard, None if it has none; refused unless it describes that
    shard, with files that stay inside the part (a part is input: its records are checked like a manifest)."""
    marker = state.marker(split, index)
    if marker is None:
        return None
    where = f"{part / STATE_DIR / shard_name(split, index)}.json"
    try:
        result = ShardResult(**marker)
    except TypeError:
        raise UslError(f"{where}: not a shard record (needs {', '.join(ShardResult.__dataclass_fields__)})") from None
    if (result.split, result.index) != (split, index):
        raise UslError(f"{where}: records shard {result.split!r}/{result.index!r}, not {split}/{index}")
    for table, info in _shard_files(marker):
        if not isinstance(info, dict) or any(k not in info for k in SHARD_FILE_KEYS):
            raise UslError(f"{where}: {table} needs {', '.join(SHARD_FILE_KEYS)}")
        check_relative(info["file"], f"{where} {table}")
        if info["file"] != shard_file(table, split, index):
            raise UslError(f"{where}: {table} file {info['file']!r} is not {shard_file(table, split, index)!r}")
        _check_current_schema(part / info["file"], info)
    return marker


def _check_current_schema(path: Path, info: dict[str, Any]) -> None:
    """A part built by an older usl is refused: its shards would mix schema versions in one dataset."""
    if size_problem(path, info):
        return  # missing or truncated: reported when copied
    version = file_schema_version(path)
    if version != SCHEMA_VERSION:
        raise UslError(
            f"{path}: record schema v{version}, but this usl writes v{SCHEMA_VERSION}; rebuild the part "
            "with this usl, or gather with the usl that built it and then run usl-records migrate"
        )


def _shard_files(marker: dict[str, Any]) -> list[tuple[str, dict[str, Any]]]:
    return [("frames", marker["frames"])] + ([("objects", marker["objects"])] if marker["objects"] else [])


def _checksums(marker: dict[str, Any]) -> list[tuple[str, Any]]:
    return [(table, info["sha256"]) for table, info in _shard_files(marker)]


def _one_copy(split: str, index: int, copies: list[tuple[Path, dict[str, Any]]]) -> tuple[Path, dict[str, Any]]:
    """The copy of a shard to take; parts of one build hold identical copies, so differing ones are an error."""
    first_part, first = copies[0]
    for part, marker in copies[1:]:
        if _checksums(marker) != _checksums(first):
            raise UslError(
                f"shard {split}/{index}: {first_part} and {part} hold different copies (sha256 differs); "
                "they were not built by one build: remove the wrong copy's part and gather again"
            )
    return copies[0]


def gather(parts: list[Path], out: Path, progress: bool = False) -> GatherSummary:
    """Copy the parts' shards into ``out`` and write its manifest once all are there."""
    if not parts:
        raise UslError("gather needs at least one part folder")
    descriptions = [read_build_file(part) for part in parts]
    first = descriptions[0]
    for part, description in zip(parts[1:], descriptions[1:], strict=True):
        difference = identity_difference(description, first)
        if difference:
            raise UslError(f"{part}: holds {difference} than {parts[0]}; gather only parts of one build")
    if "spec" not in first or "creator" not in first:
        raise UslError(f"{parts[0]}: made by an older usl that did not record the dataset spec; rebuild it")
    where = parts[0] / STATE_DIR / BUILD_FILE
    shards = first["shards"]
    if not isinstance(shards, list) or not all(
        isinstance(s, list) and len(s) == 2 and isinstance(s[1], int) for s in shards
    ):
        raise UslError(f"{where}: 'shards' is not a list of [split, index] pairs")
    for split, _ in shards:
        check_name(split, "split", where)
    creator = {**first["creator"], "gathered_from": [str(p) for p in parts]}
    state = BuildState(
        out,
        first["dataset"],
        first["fingerprint"],
        [tuple(s) for s in shards],
        about={"spec": first["spec"], "creator": first["creator"]},
    )
    state.check()
    sources = [BuildState(part, first["dataset"], first["fingerprint"]) for part in parts]
    plan: dict[tuple[str, int], tuple[Path, dict[str, Any]] | None] = {}
    for split, index in state.shards:  # every part checked before anything is written
        copies = [(s.root, m) for s in sources if (m := _part_shard(s.root, s, split, index)) is not None]
        plan[split, index] = _one_copy(split, index, copies) if copies else None
    with storage_faults(out, "the shards gathered so far are kept"):
        return _gather(state, plan, out, first, creator, progress)


def _gather(
    state: BuildState,
    plan: dict[tuple[str, int], tuple[Path, dict[str, Any]] | None],
    out: Path,
    first: dict[str, Any],
    creator: dict[str, Any],
    progress: bool,
) -> GatherSummary:
    summary = GatherSummary()
    with Owner(state.dir):
        state.open()
        for (split, index), found in tqdm(plan.items(), desc="gather", unit="shard", disable=not progress):
            kept = state.finished(split, index)
            if kept is not None:
                if found is not None:
                    _one_copy(split, index, [(out, kept), found])
                summary.kept += 1
                continue
            if found is None:
                summary.missing.append(f"{split}/{index}")
                continue
            source, marker = found
            for _, info in _shard_files(marker):
                _copy_verified(source / info["file"], out / info["file"], info)
            state.record(ShardResult(**marker))
            summary.copied += 1
        if not summary.missing:
            results = [state.marker(split, index) for split, index in state.shards]
            publish_dataset(out, build_manifest(first["spec"], results, creator, first["fingerprint"]))
    return summary
