"""One command-line style for every usl and pipelines tool.

* ``make_parser``: the module docstring as the description, kept verbatim (its examples too), and
  every option's default in its help.
* ``common_options``: a parent parser with the options tools share, under one name each
  (``--out``, ``--workers``, ``--device``, ``--seed``, ``--quiet``).
* ``resolution`` (``WxH`` or one int for a square).
* ``warning_lines``: a ``usl.errors.UslWarning`` raised while it is active prints as one
  ``COMMAND: warning: ...`` line.

This module imports only the standard library and ``usl.errors`` (which imports nothing):
``--help`` must answer before torch loads, so every CLI parses its arguments first and imports the
heavy modules afterwards. It lives in ``usl`` so that the pipelines (which may import usl) and usl
(which never imports pipelines) share it.
"""

from __future__ import annotations

import argparse
import contextlib
import re
import sys
import warnings
from collections.abc import Iterator, Sequence
from pathlib import Path

from usl.errors import UslWarning

DEVICE_CHOICES = ("auto", "cpu", "cuda")


class HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Descriptions and epilogs as written; ``(default: X)`` after every option that has one."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        default = action.default
        if "%(default)" in text or default is None or default is False or default is argparse.SUPPRESS or default == []:
            return text
        if action.option_strings or action.nargs in (argparse.OPTIONAL, argparse.ZERO_OR_MORE):
            return f"{text} (default: %(default)s)"
        return text


def make_parser(
    prog: str,
    doc: str | None,
    parents: Sequence[argparse.ArgumentParser] = (),
    epilog: str | None = None,
) -> argparse.ArgumentParser:
    """A parser in the house style; ``doc`` is normally the CLI module's ``__doc__``."""
    return argparse.ArgumentParser(
        prog=prog,
        description=(doc or "").strip("\n"),
        epilog=epilog,
        formatter_class=HelpFormatter,
        parents=list(parents),
    )


def common_options(
    *,
    out: str | None = None,
    out_default: str | None = None,
    out_required: bool = False,
    workers: str | None = None,
    workers_default: int | None = 1,
    device: str | None = None,
    device_default: str | None = "auto",
    seed: str | None = None,
    seed_default: int | None = 0,
    quiet: str | None = "no progress bar",
) -> argparse.ArgumentParser:
    """The shared options a tool asks for, each with its help text for that tool (None leaves it out)."""
    parent = argparse.ArgumentParser(add_help=False)
    group = parent.add_argument_group("common options")
    if out is not None:
        group.add_argument("--out", type=Path, default=out_default, required=out_required, help=out)
    if workers is not None:
        group.add_argument("--workers", type=int, default=workers_default, help=workers)
    if device is not None:
        group.add_argument("--device", choices=DEVICE_CHOICES, default=device_default, help=device)
    if seed is not None:
        group.add_argument("--seed", type=int, default=seed_default, help=seed)
    if quiet is not None:
        group.add_argument("--quiet", action="store_true", help=quiet)
    return parent


def resolve_device(device: str) -> str:
    """``auto`` -> ``cuda`` when available, else ``cpu`` (imports torch: call after parsing)."""
    if device != "auto":
        return device
    import torch

    return "cuda" if torch.cuda.is_available() else "cpu"


def resolution(text: str) -> tuple[int, int]:
    """``WxH`` (``640x480``) or one int for a square image (``512``) -> ``(width, height)``."""
    match = re.fullmatch(r"\s*(\d+)\s*(?:[xX]\s*(\d+))?\s*", text)
    if not match:
        raise argparse.ArgumentTypeError(
            f"{text!r} is not WIDTHxHEIGHT (e.g. 640x480) or one size for a square (e.g. 512)"
        )
    width = int(match[1])
    height = int(match[2]) if match[2] else width
    if min(width, height) < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: width and height must be >= 1")
    return width, height


@contextlib.contextmanager
def warning_lines(command: str, show_usl_warnings: bool = True) -> Iterator[None]:
    """Show each ``UslWarning`` as one ``COMMAND: warning: MESSAGE`` line on stderr, as it happens
    (or not at all: ``show_usl_warnings=False``); other warnings as Python shows them."""
    with warnings.catch_warnings():
        show = warnings.showwarning

        def show_line(message, category, filename, lineno, file=None, line=None):  # type: ignore[no-untyped-def]
            if issubclass(category, UslWarning):
                if show_usl_warnings:
                    print(f"{command}: warning: {message}", file=sys.stderr)
            else:
                show(message, category, filename, lineno, file, line)

        warnings.showwarning = show_line
        yield
