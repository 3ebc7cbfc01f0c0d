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

from .build_state import BuildState, identity_difference, read_build_file
from .claims import Owner
from usl.errors import UslError
from .manifest import build_manifest, publish_dataset
from .shards import ShardResult, size_problem
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


def gather(parts: list[Path], out: Path, progress: bool = False) -> GatherSummary:
    if not parts:
        raise UslError("gather needs at least one part folder")
    descriptions = [read_build_file(part) for part in parts]
    first = descriptions[0]
    for part, description in zip(parts[1:], descriptions[1:]):
        difference = identity_difference(description, first)
        if difference:
            raise UslError(f"{part}: holds {difference} than {parts[0]}; gather only parts of one build")
    if "spec" not in first or "creator" not in first:
        raise UslError(f"{parts[0]}: made by an older usl that did not record the dataset spec; rebuild it")
    creator = {**first["creator"], "gathered_from": [str(p) for p in parts]}
    state = BuildState(
        out,
        first["dataset"],
        first["fingerprint"],
        [tuple(s) for s in first["shards"]],
        about={"spec": first["spec"], "creator": first["creator"]},
    )
    state.open()
    sources = [BuildState(part, first["dataset"], first["fingerprint"]) for part in parts]
    summary = GatherSummary()
    with Owner(state.dir):
        for split, index in tqdm(state.shards, desc="gather", unit="shard", disable=not progress):
            if state.finished(split, index) is not None:
                summary.kept += 1
                continue
            found = next(((s, m) for s in sources if (m := s.marker(split, index)) is not None), None)
            if found is None:
                summary.missing.append(f"{split}/{index}")
                continue
            source, marker = found
            for info in [marker["frames"]] + ([marker["objects"]] if marker["objects"] else []):
                _copy_verified(source.root / info["file"], out / info["file"], info)
            state.record(ShardResult(**marker))
            summary.copied += 1
        if not summary.missing:
            results = [state.marker(split, index) for split, index in state.shards]
            publish_dataset(out, build_manifest(first["spec"], results, creator, first["fingerprint"]))
    return summary
