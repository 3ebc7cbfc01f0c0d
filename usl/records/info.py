"""Summaries of a dataset folder: counts per split and category, and a contact sheet to look at."""

from __future__ import annotations

from collections import Counter
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from usl.errors import UslError, one_line

from .encode import decode_image, decode_mask, decoding
from .manifest import load_manifest
from .reader import RecordsDataset
from .shards import read_shard_table


def dataset_counts(root: str | Path) -> dict[str, Any]:
    """Scenes, views, instances (visible object-views) and objects per category, per split."""
    root = Path(root)
    manifest = load_manifest(root)
    names = {int(c["id"]): c["name"] for c in manifest["categories"]}
    counts: dict[str, Any] = {"name": manifest["name"], "splits": {}, "skipped": manifest.get("num_skipped", 0)}
    for split, entry in manifest["splits"].items():
        per_category: Counter[str] = Counter()
        objects: set[tuple[str, int]] = set()
        for shard in entry["shards"]:
            table = read_shard_table(root, shard["frames"], columns=["scene_id", "instances"])
            for row in table.to_pylist():
                for inst in row["instances"]:
                    per_category[names.get(inst["category_id"], str(inst["category_id"]))] += 1
                    objects.add((row["scene_id"], inst["instance_id"]))
        counts["splits"][split] = {
            "scenes": entry["num_scenes"],
            "views": entry["num_frames"],
            "objects": len(objects),
            "instances_per_category": dict(sorted(per_category.items())),
        }
    return counts


def format_counts(counts: dict[str, Any]) -> str:
    lines = [f"dataset {counts['name']}: {counts['skipped']} skipped item(s) recorded in the manifest"]
    for split, c in counts["splits"].items():
        lines.append(f"  {split}: {c['scenes']} scenes, {c['views']} views, {c['objects']} objects")
        for name, n in c["instances_per_category"].items():
            lines.append(f"    {name:<16} {n} object-views")
    return "\n".join(lines)


def _palette(n: int) -> np.ndarray:
    hues = (np.arange(n) * 47) % 180
    hsv = np.stack([hues, np.full(n, 200), np.full(n, 255)], axis=1).astype(np.uint8)[None]
    return cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)[0]


def overlay_instances(image: np.ndarray, instances: list[dict[str, Any]], names: dict[int, str]) -> np.ndarray:
    """Image with each instance's mask tinted, its box drawn and its category written."""
    out = image.astype(np.float32)
    colours = _palette(max(len(instances), 1))
    for colour, inst in zip(colours, instances, strict=True):
        mask = decode_mask(inst["mask"])
        out[mask] = 0.5 * out[mask] + 0.5 * colour
    out = out.astype(np.uint8)
    for colour, inst in zip(colours, instances, strict=True):
        x0, y0, x1, y1 = (int(round(v)) for v in inst["box_xyxy"])
        cv2.rectangle(out, (x0, y0), (x1 - 1, y1 - 1), tuple(int(c) for c in colour), 1)
        label = f"{names.get(inst['category_id'], inst['category_id'])}#{inst['instance_id']}"
        cv2.putText(
            out, label, (x0 + 2, max(y0 + 10, 10)), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (255, 255, 255), 1, cv2.LINE_AA
        )
    return out


def contact_sheet(
    root: str | Path,
    out_png: str | Path,
    split: str | None = None,
    num_scenes: int = 4,
    views_per_scene: int = 4,
    tile: int = 256,
) -> Path:
    """A grid PNG: one row per scene, evenly spaced views, masks and boxes overlaid."""
    manifest = load_manifest(root)
    split = split or next(iter(manifest["splits"]))
    dataset = RecordsDataset(root, split)
    names = {int(c["id"]): c["name"] for c in manifest["categories"]}
    rows = []
    for scene_id in dataset.scene_ids[:num_scenes]:
        n = dataset.num_views(scene_id)
        picks = sorted(set(np.linspace(0, n - 1, min(views_per_scene, n)).round().astype(int).tolist()))
        tiles = []
        for row in dataset.read_scene(scene_id, views=picks):
            with decoding(row, dataset.source(scene_id)):
                image = overlay_instances(decode_image(row["image"]), row["instances"], names)
            scale = tile / max(image.shape[:2])
            image = cv2.resize(
                image, (round(image.shape[1] * scale), round(image.shape[0] * scale)), interpolation=cv2.INTER_AREA
            )
            canvas = np.zeros((tile, tile, 3), np.uint8)
            canvas[: image.shape[0], : image.shape[1]] = image
            cv2.putText(
                canvas,
                f"{scene_id} v{row['view_id']}",
                (4, tile - 6),
                cv2.FONT_HERSHEY_SIMPLEX,
                0.35,
                (255, 255, 0),
                1,
                cv2.LINE_AA,
            )
            tiles.append(canvas)
        tiles += [np.zeros((tile, tile, 3), np.uint8)] * (views_per_scene - len(tiles))
        rows.append(np.concatenate(tiles, axis=1))
    sheet = np.concatenate(rows, axis=0) if rows else np.zeros((tile, tile, 3), np.uint8)
    out_png = Path(out_png)
    try:
        out_png.parent.mkdir(parents=True, exist_ok=True)
        written = cv2.imwrite(str(out_png), cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR))
    except (OSError, cv2.error) as exc:
        raise UslError(f"{out_png}: cannot write the contact sheet ({one_line(exc)})") from None
    if not written:
        raise UslError(f"{out_png}: cannot write the contact sheet (not writable, or not a .png/.jpg name)")
    return out_png
