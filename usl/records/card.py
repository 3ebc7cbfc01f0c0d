"""The dataset card ``README.md`` at a dataset's root: what Hugging Face ``datasets`` and people read.

Its YAML front matter declares the configs (``frames``, the default, and ``objects``) with one
data-files glob per split, so ``datasets.load_dataset(root, split="train")`` loads the frames
table; the body says what the dataset is, how to load it, and documents every field.
"""

from __future__ import annotations

import json
import shlex
from pathlib import Path
from typing import Any

import yaml

from data_specs import load_dataset_spec, load_schema_spec
from usl.errors import UslError

from .atomic import write_text_atomic
from .schema import SCHEMA_VERSION

CARD = "README.md"
MARKER = "<!-- usl dataset card: written by usl; rewritten by every build and migration -->"
TABLES = ("frames", "objects")


def card_configs(manifest: dict[str, Any]) -> list[dict[str, Any]]:
    """Hugging Face ``configs``: one per table that has files, frames first and the default."""
    configs = []
    for table in TABLES:
        files = [
            {"split": split, "path": f"{table}/{split}/*.parquet"}
            for split, entry in manifest["splits"].items()
            if any(shard[table] for shard in entry["shards"])
        ]
        if files:
            configs.append(
                {"config_name": table, **({"default": True} if table == "frames" else {}), "data_files": files}
            )
    return configs


def _type_name(spec: Any) -> str:
    if isinstance(spec, str):
        return spec
    if "list" in spec:
        item = _type_name(spec["list"])
        return f"{item}[{spec['size']}]" if "size" in spec else f"list<{item}>"
    return "struct"


def _field_lines(fields: list[dict[str, Any]], prefix: str = "") -> list[str]:
    """Markdown table rows for the fields, nested struct fields as ``parent.child``; types in code
    spans, where ``<struct>`` is text and not an HTML tag the page would swallow."""
    lines = []
    for field in fields:
        type_ = field["type"]
        optional = " (may be null)" if field.get("nullable") else ""
        doc = field.get("doc", "").replace("|", "\\|")
        lines.append(f"| `{prefix}{field['name']}` | `{_type_name(type_)}` | {doc}{optional} |")
        inner = type_.get("list", type_) if isinstance(type_, dict) else None
        if isinstance(inner, dict) and "struct" in inner:
            lines += _field_lines(inner["struct"], f"{prefix}{field['name']}.")
    return lines


def dataset_license(name: str) -> dict[str, str]:
    """Hugging Face ``license`` keys of a dataset usl knows (its data spec's ``license``); ``other`` else."""
    try:
        license_ = load_dataset_spec(name).get("license")
    except ValueError:  # a dataset of someone else's spec
        license_ = None
    return dict(license_) if license_ else {"license": "other", "license_name": "unknown"}


def _provenance(creator: dict[str, Any]) -> list[str]:
    """How the dataset was made: the command line, its seed, every argument."""
    command = " ".join([creator.get("command", "?"), *map(shlex.quote, creator.get("argv", []))])
    arguments = creator.get("arguments", {})
    lines = [
        "## Provenance",
        "",
        f"Made with usl {creator.get('usl_version', '?')} by",
        "",
        "```bash",
        command,
        "```",
        "",
    ]
    if "seed" in arguments:
        lines += [f"Seed: {arguments['seed']} (it fixes the splits and every random choice of the build).", ""]
    if arguments:
        lines += [
            "| argument | value |",
            "|---|---|",
            *(f"| `{k}` | `{json.dumps(v)}` |" for k, v in arguments.items()),
            "",
        ]
    return lines + ["Skipped items and the shards' checksums are in `manifest.json`.", ""]


def _scene_provenance(provenance: dict[str, dict[str, Any]]) -> list[str]:
    """Per-scene facts the pipeline reported (e.g. a capture's pose source and metric scale)."""
    keys = sorted({key for about in provenance.values() for key in about})
    return [
        "### Scenes",
        "",
        "| scene | " + " | ".join(keys) + " |",
        "|---|" + "---|" * len(keys),
        *(
            f"| {scene} | " + " | ".join(f"`{json.dumps(about.get(k))}`" for k in keys) + " |"
            for scene, about in provenance.items()
        ),
        "",
    ]


def dataset_card(manifest: dict[str, Any]) -> str:
    spec = load_schema_spec(SCHEMA_VERSION)
    front = {
        "pretty_name": manifest["name"],
        **dataset_license(manifest["name"]),
        "task_categories": ["image-segmentation", "object-detection", "image-to-3d"],
        "tags": ["usl", "multi-view", "instance-segmentation", "3d"],
        "configs": card_configs(manifest),
    }
    lines = [
        "---",
        yaml.safe_dump(front, sort_keys=False).rstrip(),
        "---",
        MARKER,
        "",
        f"# {manifest['name']}",
        "",
        f"Multi-view records made with usl (record schema version {SCHEMA_VERSION}): "
        "one row per view with its image, camera and instance masks (COCO RLE), and, where the dataset "
        "has them, the 3D ground-truth objects. Conventions: metres, OpenCV camera axes, pixel centres at +0.5; "
        "`depth` is a 16-bit image of millimetres (PIL mode I;16, 0 = unknown): `np.asarray(row['depth']) / 1000` "
        "is metres.",
        "",
        "| split | scenes | views | objects (3D) |",
        "|---|---|---|---|",
        *(
            f"| {split} | {e['num_scenes']} | {e['num_frames']} | {e['num_objects']} |"
            for split, e in manifest["splits"].items()
        ),
        "",
        "Categories (`category_id`, the same ids in `manifest.json`, the COCO export and usl's predictions):",
        "",
        "| id | name |",
        "|---|---|",
        *(f"| {c['id']} | {c['name']} |" for c in manifest["categories"]),
        "",
        "## Loading",
        "",
        "```python",
        "from datasets import load_dataset            # Hugging Face: image and depth decode to PIL",
        'frames = load_dataset(ROOT, split="train")   # the objects table: load_dataset(ROOT, "objects", split="train")',
        "import pandas as pd",
        'df = pd.read_parquet(f"{ROOT}/frames/train")',
        "from usl.records import RecordsDataset        # by scene, checksummed against manifest.json",
        'scenes = RecordsDataset(ROOT, "train")',
        "```",
        "",
        "COCO instances JSON (detectron2, pycocotools, FiftyOne): "
        "`usl-records export-coco ROOT --split train --out train.json --images-dir images`.",
        "",
    ]
    for table in TABLES:
        if not any(c["config_name"] == table for c in front["configs"]):
            continue
        table_spec = spec["tables"][table]
        lines += [
            f"## `{table}`: {table_spec['doc']}",
            "",
            "| field | type | meaning |",
            "|---|---|---|",
            *_field_lines(table_spec["fields"]),
            "",
        ]
    if manifest.get("creator"):
        lines += _provenance(manifest["creator"])
    if manifest.get("provenance"):
        lines += _scene_provenance(manifest["provenance"])
    return "\n".join(lines)


def check_card_writable(root: str | Path) -> None:
    """Refuse to overwrite a README.md that usl did not write."""
    path = Path(root) / CARD
    if path.exists() and MARKER not in path.read_text(errors="replace"):
        raise UslError(f"{path}: exists and is not a usl dataset card; move it away (usl writes the card there)")


def write_dataset_card(root: str | Path, manifest: dict[str, Any]) -> Path:
    check_card_writable(root)
    path = Path(root) / CARD
    write_text_atomic(path, dataset_card(manifest))
    return path
