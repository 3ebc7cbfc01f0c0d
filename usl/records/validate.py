"""Checking a dataset folder against the record spec (docs/design.md §3), shard by shard.

Returns every problem found rather than stopping at the first, each naming the shard file and,
where it applies, the scene and view, so a broken conversion can be fixed in one pass.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import yaml
from tqdm import tqdm

from usl.errors import UslError, one_line

from .card import CARD, card_configs
from .encode import decode_depth, decode_image, decode_mask, encode_mask
from .manifest import load_manifest
from .schema import (
    HF_METADATA_KEY,
    hf_features,
    legacy_hf_features,
    read_metadata,
    required_fields,
    table_schema,
)
from .shards import verify_file
from .upgrade import upgrade_table

ORTHONORMAL_TOL = 1e-4
MAX_PROBLEMS_PER_SHARD = 50


def _check_camera(row: dict[str, Any]) -> list[str]:
    problems = []
    K = np.asarray(row["K"], dtype=np.float64).reshape(3, 3)
    pose = np.asarray(row["cam_to_world"], dtype=np.float64).reshape(4, 4)
    if not np.isfinite(K).all():
        problems.append("K has non-finite entries")
    elif abs(np.linalg.det(K)) < 1e-12:
        problems.append("K is singular")
    if not np.isfinite(pose).all():
        return problems + ["cam_to_world has non-finite entries"]
    rot = pose[:3, :3]
    if np.abs(rot.T @ rot - np.eye(3)).max() > ORTHONORMAL_TOL or np.linalg.det(rot) < 0:
        problems.append("cam_to_world rotation is not orthonormal with det +1")
    if np.abs(pose[3] - [0, 0, 0, 1]).max() > 0:
        problems.append("cam_to_world last row is not [0, 0, 0, 1]")
    return problems


def _check_instance(inst: dict[str, Any], height: int, width: int) -> list[str]:
    where = f"instance {inst['instance_id']}"
    missing = sorted(k for k, v in inst.items() if v is None)
    if missing:
        return [f"{where}: null {', '.join(missing)}"]
    if list(inst["mask"]["size"]) != [height, width]:
        return [f"{where}: mask size {inst['mask']['size']} != image size [{height}, {width}]"]
    try:
        mask = decode_mask(inst["mask"])
    except UslError as exc:
        return [f"{where}: {exc}"]
    problems = []
    if encode_mask(mask)["counts"] != inst["mask"]["counts"]:  # pycocotools decodes a cut RLE silently
        problems.append(f"{where}: mask RLE is corrupt (it does not re-encode to itself)")
    if int(mask.sum()) != inst["area"]:
        problems.append(f"{where}: area {inst['area']} != mask pixel count {int(mask.sum())}")
    x0, y0, x1, y1 = inst["box_xyxy"]
    if not (0 <= x0 < x1 <= width and 0 <= y0 < y1 <= height):
        problems.append(f"{where}: box_xyxy {inst['box_xyxy']} is not inside the {width}x{height} image")
    return problems


def _check_pictures(row: dict[str, Any]) -> list[str]:
    """The image, and the depth map where there is one, decode at the row's size."""
    problems = []
    for name, decode in (("image", decode_image), ("depth", decode_depth)):
        if row[name] is None:
            continue
        try:
            shape = decode(row[name]).shape[:2]
        except UslError as exc:
            problems.append(str(exc))
            continue
        if shape != (row["height"], row["width"]):
            problems.append(f"{name} is {shape[1]}x{shape[0]}, row says {row['width']}x{row['height']}")
    return problems


def _open_table(path: Path, table: str) -> tuple[pq.ParquetFile, int, list[str]]:
    """The file, its schema version, and what is wrong with its Arrow schema or metadata."""
    file = pq.ParquetFile(path, page_checksum_verification=True)
    meta = read_metadata(file.schema_arrow, str(path))
    version = meta["schema_version"]
    if not file.schema_arrow.remove_metadata().equals(table_schema(table, version)):
        return file, version, [f"{path}: Arrow schema differs from the {table} schema v{version}"]
    if version >= 2:
        stored = json.loads((file.schema_arrow.metadata or {}).get(HF_METADATA_KEY, b"null"))
        accepted = [hf_features(table, version)]
        if version == 2:
            accepted.append(legacy_hf_features(table, meta["categories"]))
        if not isinstance(stored, dict) or stored.get("info", {}).get("features") not in accepted:
            return file, version, [f"{path}: '{HF_METADATA_KEY.decode()}' features metadata missing or stale"]
    return file, version, []


def _null_fields(row: dict[str, Any], table: str, version: int) -> list[str]:
    missing = [name for name in required_fields(table, version) if name in row and row[name] is None]
    return [f"null {', '.join(missing)}"] if missing else []


def _check_frames(path: Path, shard: dict[str, Any], categories: set[int], decode_images: bool) -> list[str]:
    file, version, problems = _open_table(path, "frames")
    if problems:
        return problems
    expected = {scene: (first, count) for scene, first, count in shard["scenes"]}
    seen: dict[str, list[int]] = {}
    categories_of: dict[tuple[str, int], int] = {}
    previous: tuple[str, int] | None = None
    row_index = 0
    for batch in file.iter_batches(batch_size=64):
        for row in upgrade_table(pa.Table.from_batches([batch]), "frames", version).to_pylist():
            key = (row["scene_id"], row["view_id"])
            where = f"{path}: scene {row['scene_id']!r} view {row['view_id']}"
            nulls = _null_fields(row, "frames", version)
            if nulls:
                problems += [f"{where}: {p}" for p in nulls]
                continue
            if previous is not None and key <= previous:
                problems.append(f"{where}: rows not sorted by (scene_id, view_id) or duplicated")
            if previous is not None and row["scene_id"] != previous[0] and row["scene_id"] in seen:
                problems.append(f"{where}: scene rows are not contiguous")
            previous = key
            seen.setdefault(row["scene_id"], []).append(row_index)
            problems += [f"{where}: {p}" for p in _check_camera(row)]
            if decode_images:
                problems += [f"{where}: {p}" for p in _check_pictures(row)]
            ids = [inst["instance_id"] for inst in row["instances"]]
            if len(ids) != len(set(ids)):
                problems.append(f"{where}: duplicate instance ids {ids}")
            for inst in row["instances"]:
                problems += [f"{where}: {p}" for p in _check_instance(inst, row["height"], row["width"])]
                if inst["category_id"] not in categories:
                    problems.append(
                        f"{where}: instance {inst['instance_id']} has unknown category {inst['category_id']}"
                    )
                first_cat = categories_of.setdefault((row["scene_id"], inst["instance_id"]), inst["category_id"])
                if first_cat != inst["category_id"]:
                    problems.append(
                        f"{where}: instance {inst['instance_id']} is category {inst['category_id']} here but {first_cat} in another view"
                    )
            row_index += 1
            if len(problems) > MAX_PROBLEMS_PER_SHARD:
                return problems + [f"{path}: stopped after {MAX_PROBLEMS_PER_SHARD} problems"]
    for scene, rows in seen.items():
        if scene not in expected or expected[scene] != (rows[0], len(rows)):
            problems.append(f"{path}: scene {scene!r} rows {rows[0]}+{len(rows)} do not match the manifest index")
    for scene in set(expected) - set(seen):
        problems.append(f"{path}: manifest lists scene {scene!r} but the shard has no rows for it")
    return problems


def _check_objects(path: Path, frames_path: Path) -> list[str]:
    file, version, problems = _open_table(path, "objects")
    if problems:
        return problems
    objects = file.read().to_pylist()
    frames = pq.read_table(frames_path, columns=["scene_id", "instances"]).to_pylist()
    seen = {(f["scene_id"], i["instance_id"]): i["category_id"] for f in frames for i in f["instances"]}
    for obj in objects:
        where = f"{path}: scene {obj['scene_id']!r} object {obj['instance_id']}"
        nulls = _null_fields(obj, "objects", version)
        if nulls:
            problems += [f"{where}: {p}" for p in nulls]
            continue
        verts = np.asarray(obj["vertices"], dtype=np.float64).reshape(-1, 3)
        faces = np.asarray(obj["faces"], dtype=np.int64).reshape(-1, 3)
        if len(verts) == 0 or len(faces) == 0 or not np.isfinite(verts).all():
            problems.append(f"{where}: empty mesh or non-finite vertices")
        elif faces.min() < 0 or faces.max() >= len(verts):
            problems.append(f"{where}: face indices outside [0, {len(verts)})")
        category = seen.get((obj["scene_id"], obj["instance_id"]))
        if category is not None and category != obj["category_id"]:
            problems.append(f"{where}: category {obj['category_id']} but its masks say {category}")
    return problems


def _check_card(root: Path, manifest: dict[str, Any]) -> list[str]:
    """A v2 dataset has a dataset card whose Hugging Face configs match the manifest."""
    if manifest["schema_version"] < 2:
        return []
    path = root / CARD
    if not path.exists():
        return [f"{path}: missing dataset card (usl-records migrate {root} writes it)"]
    text = path.read_text(errors="replace")
    try:
        front = yaml.safe_load(text.split("---", 2)[1]) if text.startswith("---") else None
    except yaml.YAMLError:
        front = None
    if not isinstance(front, dict) or front.get("configs") != card_configs(manifest):
        return [f"{path}: YAML front matter 'configs' missing or not matching manifest.json"]
    return []


def validate_dataset(
    root: str | Path, splits: list[str] | None = None, decode_images: bool = True, progress: bool = False
) -> list[str]:
    """All problems of a dataset folder as one-line messages; an empty list means it is valid."""
    root = Path(root)
    try:
        manifest = load_manifest(root)
    except UslError as exc:
        return [str(exc)]
    categories = {int(c["id"]) for c in manifest["categories"]}
    problems: list[str] = _check_card(root, manifest)
    jobs: list[tuple[str, Callable[[], list[str]]]] = []
    for split, entry in manifest["splits"].items():
        if splits and split not in splits:
            continue
        for shard in entry["shards"]:
            frames_path = root / shard["frames"]["file"]
            files = [shard["frames"]] + ([shard["objects"]] if shard["objects"] else [])
            integrity = [p for p in (verify_file(root, info) for info in files) if p]
            if integrity:
                problems += integrity
                continue
            jobs.append(
                (str(frames_path), lambda s=shard, p=frames_path: _check_frames(p, s, categories, decode_images))
            )
            if shard["objects"]:
                objects_path = root / shard["objects"]["file"]
                jobs.append((str(objects_path), lambda o=objects_path, p=frames_path: _check_objects(o, p)))
    for name, job in tqdm(jobs, desc="validate", unit="file", disable=not progress):
        try:
            problems += job()
        except UslError as exc:
            problems.append(str(exc))
        except Exception as exc:  # a shard that breaks pyarrow must still be reported, not crash the check
            problems.append(f"{name}: unreadable ({type(exc).__name__}: {one_line(exc)})")
    return problems
