"""The resumable state of a build: which dataset a folder holds and which shards are finished.

Lives in ``<out>/.build/``: ``build.json`` (dataset name + fingerprint of everything that determines
the output) and one marker per finished shard (its ShardResult, checksums included). A marker is
written only after the shard files were renamed into place, so marker present + checksum match
means the shard is complete. ``spill/`` holds frame rows of long scenes on their way from a worker
to a shard; it never outlives a run, so a new run empties it.
"""
from __future__ import annotations

import json
import shutil
from dataclasses import asdict
from pathlib import Path
from typing import Any

from usl.records.errors import UslError
from usl.records.manifest import write_json_atomic
from usl.records.schema import shard_file
from usl.records.shards import ShardResult, verify_file

STATE_DIR = ".build"


class BuildState:
    def __init__(self, root: Path, dataset: str, fingerprint: dict[str, Any]):
        self.root = Path(root)
        self.dir = self.root / STATE_DIR
        self.dataset = dataset
        self.fingerprint = json.loads(json.dumps(fingerprint))  # normalise tuples etc. as JSON sees them

    def claim(self) -> None:
        """Create or re-open the output folder; refuse one that holds a different dataset."""
        identity = {"dataset": self.dataset, "fingerprint": self.fingerprint}
        build_file = self.dir / "build.json"
        if build_file.exists():
            existing = json.loads(build_file.read_text())
            if existing != identity:
                changed = sorted(
                    k
                    for k in set(existing.get("fingerprint", {})) | set(self.fingerprint)
                    if existing.get("fingerprint", {}).get(k) != self.fingerprint.get(k)
                )
                what = f"dataset {existing.get('dataset')!r}" if existing.get("dataset") != self.dataset else (
                    f"a build with other arguments ({', '.join(changed)})"
                )
                raise UslError(f"{self.root}: output folder holds {what}; choose a new --out or delete it")
            return
        if self.root.exists() and any(p.name != STATE_DIR for p in self.root.iterdir()):
            raise UslError(f"{self.root}: output folder is not empty and was not made by this build; choose a new --out")
        self.dir.mkdir(parents=True, exist_ok=True)
        write_json_atomic(build_file, identity)

    @property
    def spill_dir(self) -> Path:
        return self.dir / "spill"

    def clear_spills(self) -> None:
        """Remove spill files a killed or failed run left behind (nothing ever reads them again)."""
        shutil.rmtree(self.spill_dir, ignore_errors=True)

    def _marker(self, split: str, index: int) -> Path:
        return self.dir / f"{split}-{index:05d}.json"

    def finished(self, split: str, index: int) -> dict[str, Any] | None:
        """The shard's recorded result if its files are present and intact, else None."""
        marker = self._marker(split, index)
        if not marker.exists():
            return None
        result = json.loads(marker.read_text())
        files = [result["frames"]] + ([result["objects"]] if result["objects"] else [])
        # A shard of an older schema's layout (a build begun by an older usl) is rebuilt, not mixed in.
        stale_layout = result["frames"]["file"] != shard_file("frames", split, index)
        if stale_layout or any(verify_file(self.root, info) for info in files):
            marker.unlink()
            return None
        return result

    def record(self, result: ShardResult) -> dict[str, Any]:
        data = asdict(result)
        write_json_atomic(self._marker(result.split, result.index), data)
        return data
