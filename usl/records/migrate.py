"""``usl-records migrate``: convert a dataset folder of an older record schema (v1 or v2) to the
current one in place, atomically and resumably.

Every step is idempotent and ``manifest.json`` is the commit point, so a crash anywhere leaves a
dataset that a rerun finishes:

1. each old shard is checked against its manifest checksum, then rewritten in the current schema
   into a hidden staged file beside its new path (temp file, fsync, rename), and the staged file's
   size/checksum recorded in ``.migrate.json``; a rerun keeps the staged files whose record still
   matches. Row groups and row order are kept, so the manifest's scene index stays valid. pandas,
   pyarrow.dataset and Hugging Face skip hidden files: until step 2 the folder is the intact old
   dataset plus staged files.
2. the staged files are renamed to their new paths. From v1 these are new paths and the v1 dataset
   stays intact; from v2 they are the v2 paths, so each rename replaces a v2 shard by its converted
   copy, and until step 4 usl's readers refuse the replaced shards (their size is not the
   manifest's). This step is renames only; a rerun finishes it.
3. the dataset card ``README.md`` (atomic); 4. the new ``manifest.json`` (atomic);
5. the old shard files that no new shard took the place of (and emptied split folders) are
   deleted, then ``.migrate.json``.
"""

from __future__ import annotations

import copy
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pyarrow.parquet as pq
from tqdm import tqdm

from usl.errors import UslError

from .atomic import write_json_atomic
from .card import check_card_writable
from .manifest import SHARD_FILE_KEYS, check_relative, dataset_metadata, load_manifest, publish_dataset
from .output_folder import output_folder
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
    from_version: int = SCHEMA_VERSION
    already_current: bool = False

    def describe(self, root: Path) -> str:
        if self.already_current:
            return f"{root}: already schema v{SCHEMA_VERSION}" + (
                f"; removed {self.removed} old file(s) left over" if self.removed else ""
            )
        return (
            f"{root}: migrated from schema v{self.from_version} to v{SCHEMA_VERSION}: {self.files} shard file(s) "
            f"rewritten, {self.reused} kept from an interrupted run, {self.removed} old file(s) removed"
        )


def staged_file(new_file: str) -> str:
    """Where a converted shard waits, hidden, until the staged files are renamed into place."""
    path = Path(new_file)
    return str(path.with_name(f".{path.name}.v{SCHEMA_VERSION}"))


def _convert_file(
    root: Path, old: dict[str, Any], table: str, new_file: str, metadata: dict[str, Any]
) -> dict[str, Any]:
    """Rewrite one old shard file in the current schema, row group by row group, as ``new_file``'s
    staged file; its new manifest entry (``file`` is ``new_file``, size and checksum the staged file's)."""
    source = pq.ParquetFile(root / old["file"])
    version = read_metadata(source.schema_arrow, old["file"])["schema_version"]
    target = root / staged_file(new_file)
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
    manifest = load_manifest(root)  # not a dataset: refused before the folder is touched
    # a killed migration's temp files lie beside the shards: the next holder reaps them
    shard_dirs = {
        (root / shard_file(table, split, shard["index"])).parent
        for split, entry in manifest["splits"].items()
        for shard in entry["shards"]
        for table in TABLES
    }
    kept = "the shards converted so far are kept and a rerun finishes the migration"
    with output_folder(root, "usl-records migrate", kept, token_dirs=tuple(sorted(shard_dirs))):
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


def _in_place(root: Path, done: dict[str, Any]) -> bool:
    """Whether the converted shard is already at its new path (renamed by an interrupted run)."""
    return verify_file(root, done) is None


def _staged(root: Path, done: dict[str, Any]) -> bool:
    return verify_file(root, {**done, "file": staged_file(done["file"])}) is None


def _migrate(root: Path, progress: bool) -> MigrationSummary:
    manifest = load_manifest(root)  # again: a migration that held the folder before may have finished it
    state_path = root / STATE
    state = _read_state(state_path)
    summary = MigrationSummary(from_version=manifest["schema_version"])
    if manifest["schema_version"] == SCHEMA_VERSION:
        summary.already_current = True
        summary.removed = _remove_old(root, state["old_files"])  # a run that stopped after step 4
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
    new_files = {shard_file(table, split, shard["index"]) for split, shard, table in jobs}
    for split, shard, table in tqdm(jobs, desc="migrate", unit="file", disable=not progress):
        old = shard[table]
        new_file = shard_file(table, split, shard["index"])
        done = state["new"].get(old["file"])
        if done is not None and done["file"] == new_file and (_in_place(root, done) or _staged(root, done)):
            summary.reused += 1
        else:
            raise_if_invalid(root, old)  # never convert a damaged shard: the old copy stays as it is
            done = _convert_file(root, old, table, new_file, metadata)
            summary.files += 1
            if old["file"] not in new_files and old["file"] not in state["old_files"]:
                state["old_files"].append(old["file"])  # a v2 path is taken by its v3 copy: never deleted
            state["new"][old["file"]] = done
            write_json_atomic(state_path, state)
        shard[table] = done
    for _split, shard, table in jobs:  # step 2: only renames (every staged file was verified above)
        staged = root / staged_file(shard[table]["file"])
        if staged.exists():
            os.replace(staged, root / shard[table]["file"])
    publish_dataset(root, new_manifest)  # the commit point: from here on the folder is in the new schema
    summary.removed = _remove_old(root, state["old_files"])
    state_path.unlink(missing_ok=True)
    return summary
