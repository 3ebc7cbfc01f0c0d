"""Names read from input files (splits, scenes, cameras, scan ids, category folders, image files)
end up as path components of what usl reads and writes, so each is checked before it is used.

A name must be one plain path component: ``../../x`` or ``/etc`` in a split CSV would otherwise
write shards outside ``--out``. Hidden names are refused too: a leading dot marks usl's own temp
and state files (``.build``, ``.x.tmp-<token>``), which a split or scene must never shadow.
"""

from __future__ import annotations

from typing import Any

from usl.errors import UslError

MAX_NAME_BYTES = 255  # the longest file name Linux, macOS and Windows file systems take


def name_problem(name: Any) -> str | None:
    """Why ``name`` cannot be one path component, or None if it can."""
    if not isinstance(name, str):
        return f"is a {type(name).__name__}, not text"
    if not name or name.strip() != name:
        return "is empty or starts or ends with white space"
    if "/" in name or "\\" in name:
        return "holds a path separator"
    if name.startswith("."):
        return "starts with '.' (a hidden file, or '..': the folder above)"
    if any(ord(c) < 32 or ord(c) == 127 for c in name):
        return "holds a control character"
    if len(name.encode("utf-8", "surrogatepass")) > MAX_NAME_BYTES:
        return f"is longer than {MAX_NAME_BYTES} bytes"
    return None


def check_name(name: Any, what: str, where: object) -> str:
    """``name`` if it is safe as a path component, else a UslError: ``<where>: <what> <name> ...``.

    ``what`` says which kind of name it is (``split``, ``scan id``), ``where`` the file (and line)
    it came from.
    """
    problem = name_problem(name)
    if problem is not None:
        shown = str(where) if str(where).isprintable() else repr(str(where))  # the error stays one line
        raise UslError(f"{shown}: {what} {name!r} {problem}; it would become a path, so it must be a plain name")
    return name
