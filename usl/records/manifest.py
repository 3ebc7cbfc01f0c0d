"""``manifest.json``: the table of contents of a dataset folder, written last and atomically."""

from __future__ import annotations

import json
from pathlib import Path, PurePosixPath
from typing import Any

from usl.errors import UslError

from .atomic import write_json_atomic
from .card import write_dataset_card
from .schema import SCHEMA_VERSION, check_version

MANIFEST = "manifest.json"


def usl_version() -> str:
    """The installed usl's version, for provenance records ("unknown" when run from a source tree)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("usl")
    except PackageNotFoundError:
        return "unknown"


def dataset_metadata(spec: dict[str, Any]) -> dict[str, Any]:
    """The dataset-level facts stored both in the manifest and in every shard's Arrow schema."""
    return {
        "name": spec["name"],
        "schema_version": SCHEMA_VERSION,
        "categories": spec["categories"],
        "layout": spec["layout"],
    }


def build_manifest(
    spec: dict[str, Any], shards: list[dict[str, Any]], creator: dict[str, Any], fingerprint: dict[str, Any]
) -> dict[str, Any]:
    """Assemble the manifest from finished shard results (dicts of ShardResult fields)."""
    splits: dict[str, Any] = {}
    skips: list[dict[str, Any]] = []
    provenance: dict[str, Any] = {}
    for shard in sorted(shards, key=lambda s: (s["split"], s["index"])):
        entry = splits.setdefault(shard["split"], {"num_scenes": 0, "num_frames": 0, "num_objects": 0, "shards": []})
        entry["num_scenes"] += len(shard["scenes"])
        entry["num_frames"] += shard["frames"]["rows"]
        entry["num_objects"] += shard["objects"]["rows"] if shard["objects"] else 0
        entry["shards"].append({k: shard[k] for k in ("index", "frames", "objects", "scenes")})
        skips.extend(dict(s, split=shard["split"]) for s in shard["skips"])
        provenance.update(shard.get("provenance") or {})
    return {
        **dataset_metadata(spec),
        "baselines": spec.get("baselines", {}),
        "splits": splits,
        "skips": skips,
        "num_skipped": sum(s["count"] for s in skips),
        "creator": creator,
        "fingerprint": fingerprint,
        # per-scene facts of how a scene was made, only from pipelines that report them
        **({"provenance": dict(sorted(provenance.items()))} if provenance else {}),
    }


def publish_dataset(root: str | Path, manifest: dict[str, Any]) -> None:
    """The last step of a build or migration: the dataset card, then manifest.json (the commit point)."""
    write_dataset_card(root, manifest)
    write_json_atomic(Path(root) / MANIFEST, manifest)


def load_manifest(root: str | Path) -> dict[str, Any]:
    """The manifest of a dataset folder, refused unless well-formed with every shard inside the folder."""
    path = Path(root) / MANIFEST
    if not path.exists():
        raise UslError(f"{path}: no manifest; not a usl dataset folder, or its build has not finished")
    try:
        manifest = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise UslError(f"{path}: not valid JSON ({exc})") from exc
    if not isinstance(manifest, dict):
        raise UslError(f"{path}: expected a JSON object, found a {type(manifest).__name__}")
    check_version(manifest.get("schema_version"), str(path))
    check_manifest(manifest, str(path))
    return manifest


SHARD_FILE_KEYS = ("file", "rows", "bytes", "sha256")


def check_manifest(manifest: dict[str, Any], where: str) -> None:
    """Structure a reader relies on: splits -> shards -> files with size and checksum, inside the folder."""
    splits = manifest.get("splits")
    if not isinstance(splits, dict):
        raise UslError(f"{where}: no 'splits' object")
    if not isinstance(manifest.get("categories"), list):
        raise UslError(f"{where}: no 'categories' list")
    for split, entry in splits.items():
        shards = entry.get("shards") if isinstance(entry, dict) else None
        if not isinstance(shards, list):
            raise UslError(f"{where}: split {split!r} has no 'shards' list")
        for position, shard in enumerate(shards):
            label = f"{where}: split {split!r} shard {position}"
            if not isinstance(shard, dict) or not isinstance(shard.get("frames"), dict) or "scenes" not in shard:
                raise UslError(f"{label}: needs 'frames' and 'scenes'")
            for table in ("frames", "objects"):
                info = shard.get(table)
                if info is None and table == "objects":
                    continue
                if not isinstance(info, dict) or any(k not in info for k in SHARD_FILE_KEYS):
                    raise UslError(f"{label}: {table} needs {', '.join(SHARD_FILE_KEYS)}")
                check_relative(info["file"], f"{label} {table}")


def check_relative(name: Any, where: str) -> None:
    """Shard paths are relative and stay inside the dataset folder (no absolute paths, no '..')."""
    if not isinstance(name, str) or not name or "\\" in name:
        raise UslError(f"{where}: file {name!r} is not a relative POSIX path")
    pure = PurePosixPath(name)
    if pure.is_absolute() or ".." in pure.parts:
        raise UslError(f"{where}: file {name!r} points outside the dataset folder; shard paths must be relative")
