"""Command lines as the docs write them, parsed by the project's real argparse parsers (nothing runs).

A command is one of the console scripts of pyproject.toml, ``python -m MODULE`` of a project module,
or ``torchrun ... -m MODULE`` (torchrun's own parser reads its part). Placeholders are allowed where
a value goes (``DIR``, ``HOST:PORT``, ``<file>``), and ``...`` elides arguments: an elided or
inline (``usl-eval --no-occlusion``) command may leave out what the parser requires, never name an
option it lacks.
"""

from __future__ import annotations

import argparse
import functools
import importlib
import importlib.util
import inspect
import re
import shlex
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
PROJECT_PACKAGES = ("usl", "pipelines", "data_specs")
ELISION = ("...", "…")
_PLACEHOLDER = re.compile(r"^(?:[A-Z][A-Z0-9_]*(?:[:.][A-Z0-9_]+)*|[A-Z]x[A-Z]|<[^>]+>)$")
_SEPARATORS = ("&&", "||", "|", ";")


class ParseFailure(Exception):
    """What argparse would have printed before exiting."""


@dataclass
class Invocation:
    """A project command found in a command line: what the reader types, the module whose
    ``parser()`` reads the arguments, and those arguments."""

    program: str  # e.g. "usl-train", "python -m usl.cli.train", "torchrun -m usl.cli.train"
    module: str
    args: list[str]


@functools.cache
def console_scripts() -> dict[str, str]:
    """Console script -> the module of its ``main``, from pyproject.toml's ``[project.scripts]``."""
    text = (REPO / "pyproject.toml").read_text()
    section = text.split("[project.scripts]", 1)[1].split("\n[", 1)[0]
    return dict(re.findall(r'^([\w-]+)\s*=\s*"([\w.]+):main"', section, re.M))


def is_placeholder(token: str) -> bool:
    return bool(_PLACEHOLDER.match(token)) or any(e in token for e in ELISION)


def invocations(line: str) -> tuple[list[Invocation], list[str]]:
    """The project commands in a shell line (``a && b | c`` has up to three) and the problems found
    reading it (a module that ``-m`` cannot run, a script path that does not exist)."""
    try:
        tokens = shlex.split(line, comments=True)
    except ValueError as exc:
        return [], [f"not a shell command line ({exc})"]
    found, problems = [], []
    segment: list[str] = []
    for token in [*tokens, ";"]:
        if token not in _SEPARATORS:
            segment.append(token)
            continue
        while segment and re.match(r"^[A-Za-z_]\w*=", segment[0]):  # VAR=value before the command
            segment.pop(0)
        if segment:
            invocation, problem = _invocation(segment)
            found += [invocation] if invocation else []
            problems += [problem] if problem else []
        segment = []
    return found, problems


def _invocation(tokens: list[str]) -> tuple[Invocation | None, str | None]:
    head = tokens[0]
    scripts = [t for t in tokens if re.match(r"^(?:\./)?scripts/[\w/.-]+\.(?:sh|py)$", t)]
    missing = [s for s in scripts if not (REPO / s).is_file()]
    if missing:
        return None, f"{missing[0]} does not exist"
    if head in console_scripts():
        return Invocation(head, console_scripts()[head], tokens[1:]), None
    if re.fullmatch(r"python[\d.]*", head) and "-m" in tokens:
        at = tokens.index("-m")
        module = tokens[at + 1]
        if module.split(".")[0] not in PROJECT_PACKAGES:
            return None, None
        problem = runnable_problem(module)
        return (None, problem) if problem else (Invocation(f"python -m {module}", module, tokens[at + 2 :]), None)
    if head == "torchrun":
        try:
            parsed = parse(_torchrun_parser(), [t for t in tokens[1:] if t not in ELISION], partial=True)
        except ParseFailure as exc:
            return None, f"torchrun: {exc}"
        if not parsed.module or parsed.training_script.split(".")[0] not in PROJECT_PACKAGES:
            return None, None
        module = parsed.training_script
        problem = runnable_problem(module)
        return (
            (None, problem)
            if problem
            else (Invocation(f"torchrun -m {module}", module, parsed.training_script_args), None)
        )
    return None, None


def runnable_problem(module: str) -> str | None:
    """Why ``python -m module`` would not run the module's command line, or None."""
    try:
        spec = importlib.util.find_spec(module)
    except ModuleNotFoundError:
        spec = None
    if spec is None:
        return f"no module {module}"
    if spec.submodule_search_locations is not None:
        return None if importlib.util.find_spec(f"{module}.__main__") else f"package {module} has no __main__"
    if not re.search(r"^if __name__ == .__main__.:", Path(spec.origin).read_text(), re.M):
        return f"{module} does not run as a program (no __main__ block)"
    if not hasattr(importlib.import_module(module), "parser"):
        return f"{module} has no parser()"
    return None


def _torchrun_parser() -> argparse.ArgumentParser:
    from torch.distributed.run import get_args_parser

    return get_args_parser()


def parser_for(module: str) -> argparse.ArgumentParser:
    """A fresh parser of the command line in ``module`` (its ``parser()``, given the dataset spec
    where it asks for one)."""
    build = importlib.import_module(module).parser
    if "spec" in inspect.signature(build).parameters:
        from data_specs import load_dataset_spec

        return build(load_dataset_spec(module.split(".")[1]))
    return build()


def subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    return {
        name: sub
        for action in parser._actions
        if isinstance(action, argparse._SubParsersAction)
        for name, sub in action.choices.items()
    }


def option_strings(parser: argparse.ArgumentParser) -> set[str]:
    return {s for action in parser._actions for s in action.option_strings}


def parse(parser: argparse.ArgumentParser, args: list[str], partial: bool) -> argparse.Namespace:
    """``args`` parsed by ``parser``; a ``ParseFailure`` instead of argparse's exit. ``partial`` lets
    required arguments be missing (an elided or inline command)."""
    for each in [parser, *subparsers(parser).values()]:
        each.error = _raise  # type: ignore[method-assign]
        if partial:
            _relax(each)
    # "[--flag]" and "[ARG]" are usage notation; a "key=[1,2]" override's brackets are its value
    args = [
        a.strip("[]") if a.startswith("[") or (a.endswith("]") and "=[" not in a) else a
        for a in args
        if a not in ELISION
    ]
    if "-h" in args or "--help" in args:
        args = [a for a in args if a not in ("-h", "--help")]
    namespace, unknown = parser.parse_known_args(args)
    if unknown:
        raise ParseFailure(f"unrecognized arguments: {' '.join(unknown)}")
    return namespace


def _raise(message: str) -> None:
    raise ParseFailure(message)


def _relax(parser: argparse.ArgumentParser) -> None:
    for action in parser._actions:
        action.required = False
        if not action.option_strings and not isinstance(action, argparse._SubParsersAction):
            action.nargs = {None: "?", "+": "*"}.get(action.nargs, action.nargs)
    for group in parser._mutually_exclusive_groups:
        group.required = False


def check(invocation: Invocation, partial: bool) -> argparse.Namespace | str:
    """The parsed arguments, or why they do not parse. A failure caused by a placeholder value
    (``--workers N``) is not one."""
    elided = partial or any(e in a for a in invocation.args for e in ELISION) or "--help" in invocation.args
    parser = parser_for(invocation.module)
    args = list(invocation.args)
    takes_value = {s for a in parser._actions if a.nargs != 0 for s in a.option_strings}
    if partial and args and args[-1] in takes_value:
        args.pop()  # prose naming an option of a command, e.g. `usl-build-scene-shapes --mesh-root`
    try:
        return parse(parser, args, elided)
    except ParseFailure as exc:
        message = str(exc)
        values = re.findall(r"invalid (?:\w+ value|choice): '([^']*)'", message)
        if values and all(is_placeholder(v) for v in values):
            return argparse.Namespace()
        return f"{invocation.program}: {message}"
