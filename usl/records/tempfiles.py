"""Temp files named after the process that writes them.

In a folder that several processes (on several machines) build together, nobody may delete a temp
file just because it is a temp file: it may be another live process's shard in the making. Every
temp file therefore carries its writer's token, and only files whose writer is gone are removed
(``usl.records.claims`` judges who is gone). Build workers adopt their driver's token, so a spill
a worker leaves behind belongs to the driver that started it.
"""

from __future__ import annotations

import uuid
from pathlib import Path

TMP_MARK = ".tmp-"
_token: str | None = None


def process_token() -> str:
    """This process's token (random, fixed for the process's life unless a driver hands it one)."""
    global _token
    if _token is None:
        _token = uuid.uuid4().hex[:16]
    return _token


def set_process_token(token: str) -> None:
    global _token
    _token = token


def temp_path(final: Path, hidden: bool = False, token: str | None = None) -> Path:
    """Where this process (or the one with ``token``) writes ``final`` before renaming it into place."""
    final = Path(final)
    return final.with_name(f"{'.' if hidden else ''}{final.name}{TMP_MARK}{token or process_token()}")


def temp_files_of(directory: Path, token: str) -> list[Path]:
    """Temp files (hidden or not) that the process with ``token`` left in ``directory``."""
    return sorted(Path(directory).glob(f"*{TMP_MARK}{token}"))
