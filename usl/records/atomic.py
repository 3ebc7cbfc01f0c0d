"""Atomic file writes: a temp file beside the target, fsync, rename. Readers never see half a file."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from .tempfiles import temp_path


def write_text_atomic(path: Path, text: str) -> None:
    """Write to a hidden temp file, fsync, rename: readers never see a half-written file."""
    path = Path(path)
    tmp = temp_path(path, hidden=True)  # named after this process: only a gone writer's temps are reaped
    try:
        with open(tmp, "w") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)  # a full disk or a kill: the old file (if any) stays as it was
        raise


def write_json_atomic(path: Path, data: Any, indent: int | None = 1) -> None:
    """JSON written atomically; ``indent=None`` for compact files (large COCO exports)."""
    separators = None if indent is not None else (",", ":")
    write_text_atomic(path, json.dumps(data, indent=indent, separators=separators) + "\n")
