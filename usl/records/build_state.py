"""The resumable state of a build: which dataset a folder holds and which shards are finished.

Lives in ``<out>/.build/``: ``build.json`` (the build's identity: dataset name, fingerprint of
everything that determines the output, the shard plan; plus the dataset spec and creator, so that
``usl-records gather`` can write the manifest of folders built apart) and one marker per finished
shard (its ShardResult, checksums included). A marker is written only after the shard files were
renamed into place, so marker present + checksum match means the shard is complete. ``owners/``
and ``claims/`` say who builds what (``usl.records.claims``); ``spill/`` holds frame rows of long
scenes on their way from a worker to a shard.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable
from dataclasses import asdict
from pathlib import Path
from typing import Any

from usl.errors import UslError

from .atomic import write_json_atomic
from .schema import SCHEMA_VERSION, file_schema_version, shard_file
from .shards import ShardResult, shard_paths, shard_temp_path, verify_file
from .tempfiles import temp_path

STATE_DIR = ".build"
BUILD_FILE = "build.json"
IDENTITY_KEYS = ("dataset", "fingerprint", "shards")


def shard_name(split: str, index: int) -> str:
    return f"{split}-{index:05d}"


def read_build_file(root: Path) -> dict[str, Any]:
    path = Path(root) / STATE_DIR / BUILD_FILE
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise UslError(f"{path}: missing; {root} is not a usl build folder") from None
    except ValueError as exc:
        raise UslError(f"{path}: not valid JSON ({exc})") from None
    if not isinstance(data, dict) or any(k not in data for k in IDENTITY_KEYS):
        raise UslError(f"{path}: not a build description (needs {', '.join(IDENTITY_KEYS)})")
    return data


def identity_difference(existing: dict[str, Any], wanted: dict[str, Any]) -> str | None:
    """What makes two builds differ, in words, or None if they are the same build."""
    if existing.get("dataset") != wanted["dataset"]:
        return f"dataset {existing.get('dataset')!r}"
    old, new = existing.get("fingerprint", {}), wanted["fingerprint"]
    changed = sorted(k for k in set(old) | set(new) if old.get(k) != new.get(k))
    if existing.get("shards") != wanted["shards"]:
        changed.append("shard plan")
    return f"a build with other arguments ({', '.join(changed)})" if changed else None


class BuildState:
    def __init__(
        self,
        root: Path,
        dataset: str,
        fingerprint: dict[str, Any],
        shards: Iterable[tuple[str, int]] = (),
        about: dict[str, Any] | None = None,
    ):
        self.root = Path(root)
        self.dir = self.root / STATE_DIR
        self.dataset = dataset
        self.fingerprint = json.loads(json.dumps(fingerprint))  # normalise tuples etc. as JSON sees them
        self.shards = [[split, index] for split, index in shards]
        self.about = json.loads(json.dumps(about or {}))  # spec and creator: kept, not compared

    @property
    def identity(self) -> dict[str, Any]:
        return {"dataset": self.dataset, "fingerprint": self.fingerprint, "shards": self.shards}

    def check(self) -> None:
        """Refuse, before anything is written, a folder that holds something other than this build."""
        if self.root.exists() and not self.root.is_dir():
            raise UslError(f"{self.root}: --out is a file, not a folder")
        if (self.dir / BUILD_FILE).exists():
            difference = identity_difference(read_build_file(self.root), self.identity)
            if difference:
                raise UslError(f"{self.root}: output folder holds {difference}; choose a new --out or delete it")
        elif self.root.exists() and any(p.name != STATE_DIR for p in self.root.iterdir()):
            raise UslError(
                f"{self.root}: output folder is not empty and was not made by this build; choose a new --out"
            )

    def open(self) -> bool:
        """Create or re-open the output folder (True: created it); refuse one that holds something else.

        Call it as a registered ``claims.Owner`` (after ``check``), so that a temp file a killed run
        leaves here is reaped. ``build.json`` is created no-clobber, so of two builds with different
        arguments started together on one folder, one is refused.
        """
        self.check()
        build_file = self.dir / BUILD_FILE
        created = False
        if not build_file.exists():
            self.dir.mkdir(parents=True, exist_ok=True)
            tmp = temp_path(build_file, hidden=True)
            try:
                tmp.write_text(json.dumps({**self.identity, **self.about}, indent=1) + "\n")
                os.link(tmp, build_file)  # fails if another build created it first
                created = True
            except FileExistsError:
                pass
            finally:
                tmp.unlink(missing_ok=True)
        difference = identity_difference(read_build_file(self.root), self.identity)
        if difference:
            raise UslError(f"{self.root}: output folder holds {difference}; choose a new --out or delete it")
        return created

    def forget(self) -> None:
        """Undo ``open`` of a fresh folder whose build failed before any shard: a re-run with fixed
        inputs (other arguments) is then not refused."""
        if not any(path.name != BUILD_FILE for path in self.dir.glob("*.json")):  # no shard marker
            (self.dir / BUILD_FILE).unlink(missing_ok=True)

    @property
    def spill_dir(self) -> Path:
        return self.dir / "spill"

    def _marker(self, split: str, index: int) -> Path:
        return self.dir / f"{shard_name(split, index)}.json"

    def marker(self, split: str, index: int) -> dict[str, Any] | None:
        """The shard's recorded result, trusting the marker (it is written after the files)."""
        try:
            return json.loads(self._marker(split, index).read_text())
        except (FileNotFoundError, ValueError):
            return None

    def finished(self, split: str, index: int) -> dict[str, Any] | None:
        """The shard's recorded result if its files are present and intact (checksums), else None."""
        result = self.marker(split, index)
        if result is None:
            return None
        files = [result["frames"]] + ([result["objects"]] if result["objects"] else [])
        # A shard of an older schema (a build begun by an older usl) is rebuilt, not mixed in.
        stale_layout = result["frames"]["file"] != shard_file("frames", split, index)
        if (
            stale_layout
            or any(verify_file(self.root, info) for info in files)
            or any(file_schema_version(self.root / info["file"]) != SCHEMA_VERSION for info in files)
        ):
            self._marker(split, index).unlink(missing_ok=True)
            return None
        return result

    def record(self, result: ShardResult) -> dict[str, Any]:
        data = asdict(result)
        write_json_atomic(self._marker(result.split, result.index), data)
        return data

    def remove_temp_files(self, split: str, index: int, token: str) -> None:
        """Delete the partial files of one shard that the (gone) process ``token`` was writing."""
        for final in shard_paths(self.root, split, index).values():
            shard_temp_path(final, token).unlink(missing_ok=True)
