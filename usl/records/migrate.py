"""``usl-records migrate``: convert a schema v1 dataset folder to v2 in place, atomically and resumably.

Every step is idempotent and ``manifest.json`` is the commit point, so a crash anywhere leaves a
complete, readable dataset and a rerun finishes the job:

1. each v1 shard is checked against its manifest checksum, then rewritten in the v2 layout (hidden
   temp file, fsync, rename) and its new size/checksum recorded in ``.migrate.json``; a rerun keeps
   the files whose record still matches. Row groups and row order are kept, so the manifest's
   scene index stays valid. Until step 3 the folder is the intact v1 dataset plus new files.
2. the dataset card ``README.md`` (atomic); 3. the v2 ``manifest.json`` (atomic);
4. the v1 shard files (and emptied split folders) are deleted, then ``.migrate.json``.
"""

from __future__ import annotations

import copy
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pyarrow.parquet as pq
from tqdm import tqdm

from .atomic import write_json_atomic
from .card import check_card_writable
from usl.errors import UslError
from .output_folder import output_folder
from .manifest import SHARD_FILE_KEYS, check_relative, dataset_metadata, load_manifest, publish_dataset
from .schema import SCHEMA_VERSION, dataset_schema, read_metadata, shard_file
from .shards import _TableStream, raise_if_invalid, verify_file
from .upgrade import upgrade_table

STATE = ".migrate.json"
TABLES = ("frames", "objects")


@dataclass
class MigrationSummary:
    files: int = 0
    reused: int = 0
    removed: int = 0
    already_current: bool = False

    def describe(self, root: Path) -> str:
        if self.already_current:
            return f"{root}: already schema v{SCHEMA_VERSION}" + (
                f"; removed {self.removed} v1 file(s) left over" if self.removed else ""
            )
        return (
            f"{root}: migrated to schema v{SCHEMA_VERSION}: {self.files} shard file(s) rewritten, "
            f"{self.reused} kept from an interrupted run, {self.removed} v1 file(s) removed"
        )


def _convert_file(
    root: Path, old: dict[str, Any], table: str, new_file: str, metadata: dict[str, Any]
) -> dict[str, Any]:
    """Rewrite one v1 shard file as v2, row group by row group; its new manifest entry."""
    source = pq.ParquetFile(root / old["file"])
    version = read_metadata(source.schema_arrow, old["file"])["schema_version"]
    target = root / new_file
    target.parent.mkdir(parents=True, exist_ok=True)
    stream = _TableStream(target, dataset_schema(table, metadata), binary_plain=table == "frames")
    try:
        for group in range(source.num_row_groups):
            upgraded = upgrade_table(source.read_row_group(group), table, version)
            stream.write(upgraded.replace_schema_metadata(stream.schema.metadata))
        return stream.commit(new_file)
    except BaseException:
        stream.abort()
        raise


def _remove_old(root: Path, old_files: list[str]) -> int:
    removed = 0
    for file in old_files:
        path = root / file
        if path.exists():
            path.unlink()
            removed += 1
        try:
            path.parent.rmdir()  # the v1 split folder, once empty
        except OSError:
            pass
    return removed


def migrate_dataset(root: str | Path, progress: bool = False) -> MigrationSummary:
    """Migrate ``root`` in place; one process at a time (another one's migration is a UslError)."""
    root = Path(root)
    load_manifest(root)  # not a dataset: refused before the folder is touched
    with output_folder(root, "usl-records migrate", "the dataset is intact and the shards converted so far are kept"):
        return _migrate(root, progress)


def _read_state(path: Path) -> dict[str, Any]:
    """What an interrupted run converted; an unreadable record only means converting again."""
    try:
        state = json.loads(path.read_text())
    except (FileNotFoundError, ValueError):
        return {"old_files": [], "new": {}}
    if (
        not isinstance(state, dict)
        or not isinstance(state.get("old_files"), list)
        or not isinstance(state.get("new"), dict)
    ):
        return {"old_files": [], "new": {}}
    for file in state["old_files"]:  # deleted at the end: never anything outside the dataset
        check_relative(file, str(path))
    for old, done in state["new"].items():
        if not isinstance(done, dict) or any(k not in done for k in SHARD_FILE_KEYS):
            raise UslError(f"{path}: the record of {old!r} needs {', '.join(SHARD_FILE_KEYS)}")
        check_relative(done["file"], str(path))
    return state


def _migrate(root: Path, progress: bool) -> MigrationSummary:
    manifest = load_manifest(root)  # again: a migration that held the folder before may have finished it
    state_path = root / STATE
    state = _read_state(state_path)
    summary = MigrationSummary()
    if manifest["schema_version"] == SCHEMA_VERSION:
        summary.already_current = True
        summary.removed = _remove_old(root, state["old_files"])  # a run that stopped after step 3
        state_path.unlink(missing_ok=True)
        return summary
    check_card_writable(root)
    metadata = {**dataset_metadata(manifest), "schema_version": SCHEMA_VERSION}
    new_manifest = copy.deepcopy(manifest)
    new_manifest.update(schema_version=SCHEMA_VERSION, migrated_from_schema_version=manifest["schema_version"])
    jobs = [
        (split, shard, table)
        for split, entry in new_manifest["splits"].items()
        for shard in entry["shards"]
        for table in TABLES
        if shard[table]
    ]
    for split, shard, table in tqdm(jobs, desc="migrate", unit="file", disable=not progress):
        old = shard[table]
        new_file = shard_file(table, split, shard["index"])
        done = state["new"].get(old["file"])
        if done is not None and verify_file(root, done) is None:
            summary.reused += 1
        else:
            raise_if_invalid(root, old)  # never convert a damaged shard: the v1 copy stays as it is
            done = _convert_file(root, old, table, new_file, metadata)
            summary.files += 1
            if old["file"] not in state["old_files"]:
                state["old_files"].append(old["file"])
            state["new"][old["file"]] = done
            write_json_atomic(state_path, state)
        shard[table] = done
    publish_dataset(root, new_manifest)  # the commit point: from here on the folder is v2
    summary.removed = _remove_old(root, state["old_files"])
    state_path.unlink(missing_ok=True)
    return summary
