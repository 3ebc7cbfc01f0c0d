"""Every config key with its type, value and doc line, for ``usl-train --list-keys``.

The doc line of a field is the comment written beside it in its dataclass (``lr: float = 0.01  #
...``), or the comment block right above it. Reading the comments from the source keeps one place
to document a key, where the key is defined, so the listing cannot drift from the code.
"""

from __future__ import annotations

import ast
import dataclasses
import functools
import inspect
import io
import json
import textwrap
import tokenize
import types
import typing
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

from usl.config import to_dict


@dataclass(frozen=True)
class KeyDoc:
    key: str  # dotted, e.g. "optim.lr"
    type: str
    value: Any
    doc: str


@functools.cache
def field_docs(cls: type) -> dict[str, str]:
    """Field name -> its comment, for a dataclass and the dataclasses it inherits from."""
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if dataclasses.is_dataclass(klass):
            docs.update(_own_field_docs(klass))
    return docs


def _own_field_docs(cls: type) -> dict[str, str]:
    try:
        source = textwrap.dedent(inspect.getsource(cls))
    except (OSError, TypeError):  # no source (e.g. a frozen application): keys still list, undocumented
        return {}
    comments: dict[int, str] = {}
    for token in tokenize.generate_tokens(io.StringIO(source).readline):
        if token.type == tokenize.COMMENT:
            comments[token.start[0]] = token.string.lstrip("#").strip()
    lines = source.splitlines()
    docs = {}
    (node,) = ast.parse(source).body
    for statement in node.body:  # type: ignore[attr-defined]
        if not (isinstance(statement, ast.AnnAssign) and isinstance(statement.target, ast.Name)):
            continue
        trailing = [comments[n] for n in range(statement.lineno, statement.end_lineno + 1) if n in comments]
        if trailing:
            docs[statement.target.id] = trailing[0]
            continue
        above, line = [], statement.lineno - 1
        while line >= 1 and lines[line - 1].strip().startswith("#"):
            above.insert(0, comments.get(line, ""))
            line -= 1
        docs[statement.target.id] = " ".join(above)
    return docs


def type_name(tp: Any) -> str:
    """``int``, ``tuple[str, ...]``, ``float | None``: as the annotation reads."""
    if isinstance(tp, type) and not typing.get_args(tp):
        return tp.__name__
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        return " | ".join("None" if a is type(None) else type_name(a) for a in args)
    if origin is not None:
        inner = ", ".join("..." if a is Ellipsis else type_name(a) for a in args)
        return f"{getattr(origin, '__name__', str(origin))}[{inner}]"
    return str(tp).replace("typing.", "")


def iter_keys(config: Any, prefix: str = "") -> Iterator[KeyDoc]:
    """Every leaf key of a (nested) dataclass instance, in definition order."""
    hints = typing.get_type_hints(type(config))
    docs = field_docs(type(config))
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        key = f"{prefix}{f.name}"
        if dataclasses.is_dataclass(value):
            yield from iter_keys(value, f"{key}.")
        else:
            yield KeyDoc(key, type_name(hints[f.name]), value, docs.get(f.name, ""))


def format_keys(config: Any) -> str:
    """One aligned line per key: ``key  type  value  doc``."""
    rows = [(k.key, k.type, _value_text(k.value), k.doc) for k in iter_keys(config)]
    widths = [max(len(r[i]) for r in rows) for i in range(3)]
    return "\n".join(
        f"{key:<{widths[0]}}  {tp:<{widths[1]}}  {value:<{widths[2]}}  {doc}".rstrip() for key, tp, value, doc in rows
    )


def _value_text(value: Any) -> str:
    """As YAML/JSON spells it (tuples as lists); the empty string as ``""`` so it stays visible."""
    return json.dumps(to_dict(value)) if not isinstance(value, str) else (value or '""')
