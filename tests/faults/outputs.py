"""What a fault may not touch: the finished files of an output folder, and how to compare them."""

from __future__ import annotations

import errno
import re
from pathlib import Path

from usl.records.tempfiles import TMP_MARK

FAULTS = [(errno.ENOSPC, "no space left"), (errno.EACCES, "permission denied")]  # errno, its words in the line
PROGRESS_BAR = re.compile(r"\d+%\|")


def finished_files(root: Path) -> dict[str, bytes]:
    """Every finished file under ``root`` (shards, markers, card, manifest, build description),
    by relative path; temp files and the owner/claim registry (which come and go) are left out."""
    found = {}
    for path in sorted(Path(root).rglob("*")):
        relative = path.relative_to(root).as_posix()
        if path.is_file() and TMP_MARK not in path.name and not relative.startswith((".build/owners", ".build/claims")):
            found[relative] = path.read_bytes()
    return found


def temp_files(root: Path) -> list[str]:
    return sorted(p.relative_to(root).as_posix() for p in Path(root).rglob(f"*{TMP_MARK}*"))


def bytes_lost(earlier: dict[str, bytes], later: dict[str, bytes]) -> int:
    """Bytes of ``earlier``'s files that ``later`` lacks or holds changed (lost or overwritten)."""
    return sum(len(data) for name, data in earlier.items() if later.get(name) != data)


def one_line_error(text: str) -> str:
    """The single line a CLI printed on stderr (besides progress bars); fails on a traceback or several lines."""
    lines = [line for line in re.split(r"[\r\n]", text) if line.strip() and not PROGRESS_BAR.search(line)]
    assert len(lines) == 1 and "Traceback" not in text, text
    return lines[0]
