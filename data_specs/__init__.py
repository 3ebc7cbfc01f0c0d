"""Machine-readable data contracts (docs/design.md §3-4): the record schema and one spec per dataset.

The YAML files beside this module are the single source of truth; code loads them from here.
"""

from __future__ import annotations

from functools import cache
from pathlib import Path
from typing import Any

import yaml

SPEC_DIR = Path(__file__).resolve().parent
DATASETS = ("scene_shapes", "hypersim", "scannet", "captures")


@cache
def load_schema_spec(version: int = 3) -> dict[str, Any]:
    """The record schema of the given version, as declared in ``schema_v<version>.yaml``."""
    path = SPEC_DIR / f"schema_v{version}.yaml"
    if not path.exists():
        raise ValueError(f"unknown record schema version {version} (no {path.name} in {SPEC_DIR})")
    return yaml.safe_load(path.read_text())


@cache
def load_dataset_spec(name: str) -> dict[str, Any]:
    """Categories, layout ranges and baseline parameters of one dataset."""
    path = SPEC_DIR / f"{name}.yaml"
    if not path.exists():
        raise ValueError(f"unknown dataset spec {name!r}; known: {', '.join(DATASETS)}")
    return yaml.safe_load(path.read_text())


@cache
def coco_category_ids() -> tuple[int, ...]:
    """COCO's 80 category ids in the contiguous order COCO-trained segmenters number their classes."""
    return tuple(int(c["id"]) for c in yaml.safe_load((SPEC_DIR / "coco.yaml").read_text())["categories"])
