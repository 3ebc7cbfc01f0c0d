"""What the docs tests check on one Markdown page, each check a function returning the problems it
finds as ``path:line: what`` lines (an empty list: the page is right)."""

from __future__ import annotations

import argparse
import functools
import re
from pathlib import Path

from tests.docs.commands import (
    REPO,
    Invocation,
    ParseFailure,
    check,
    console_scripts,
    invocations,
    is_placeholder,
    option_strings,
    parse,
    parser_for,
    subparsers,
)
from tests.docs.markdown import Page, read_page

SECTIONS = ("data", "model", "loss", "optim", "train", "val")
_KEY = re.compile(rf"^((?:{'|'.join(SECTIONS)})(?:\.[A-Za-z_*][\w*]*)+)(=.*)?$")
_FILE_SUFFIX = re.compile(r"\.(py|ya?ml|jsonl?|md|csv|txt|png|pt|pkl|pth|glb|html|obj|ply|sh|toml|cff)$")
_PROSE_OVERRIDE = re.compile(rf"(?<![\w./-])((?:{'|'.join(SECTIONS)})(?:\.\w+)+)=")
_MENTION = re.compile(r"(?<![\w/-])(usl-[a-z-]+(?:\s+[a-z][a-z-]*)?|python3? -m [\w.]+|torchrun|scripts/[\w/.-]+)")
_OPTION_SPAN = re.compile(r"^--[\w-]+(?:[ =][\w.,:/*-]+)?$")  # "--flag" or "--flag VALUE", not "--stride > 1"
# A page may name a key the code no longer has where it says so: in the table row, paragraph or page
# title that names it, by saying "removed" or linking the page that records the removed options.
_SAYS_REMOVED = re.compile(r"\bremoved\b|removed-options\.md", re.I)


class ConfigKeys:
    """The config keys ``usl-train --list-keys`` lists, with their section prefixes; below a mapping
    (``optim.lr_mult``) any name goes."""

    def __init__(self) -> None:
        from usl.config import Config
        from usl.config_docs import iter_keys

        leaves = list(iter_keys(Config()))
        self.keys = {k.key for k in leaves}
        self.prefixes = {k.rsplit(".", i)[0] for k in self.keys for i in range(1, k.count(".") + 1)}
        self.mappings = {k.key for k in leaves if k.type.startswith("dict")}

    def problem(self, key: str) -> str | None:
        name = key.split("*")[0].rstrip(".")
        if name in self.keys or name in self.prefixes or any(name.startswith(f"{m}.") for m in self.mappings):
            return None
        return f"no config key {key}"


def where(page: Page, line: int) -> str:
    try:
        return f"{page.path.relative_to(REPO)}:{line}"
    except ValueError:
        return f"{page.path}:{line}"


def title(page: Page) -> str:
    return next((text for _, text in page.prose if text.startswith("# ")), "")


def _project_commands(page: Page) -> list[tuple[int, Invocation | None, bool, str, list[str]]]:
    """(line, command, partial, context, problems): the fenced shell commands, then the inline spans
    that are one; the context is what may say that a key it names was removed."""
    found = []
    for line, text in page.commands:
        commands, problems = invocations(text)
        found += [(line, c, False, title(page), []) for c in commands]
        found += [(line, None, False, "", problems)] if problems else []
    for span in page.spans:
        if _MENTION.match(span.text) and " " in span.text:
            commands, problems = invocations(span.text)
            found += [(span.line, c, True, f"{title(page)}\n{span.paragraph}", []) for c in commands]
            found += [(span.line, None, True, "", problems)] if problems else []
    return found


def command_problems(page: Page, keys: ConfigKeys) -> list[str]:
    """Every project command line parses with its real parser; the keys it overrides exist and the
    recipe it names loads with them."""
    from usl.cli.train import RECIPES
    from usl.config import ConfigError, load_config

    problems = []
    for line, command, partial, context, found in _project_commands(page):
        problems += [f"{where(page, line)}: {p}" for p in found]
        if command is None:
            continue
        parsed = check(command, partial)
        if isinstance(parsed, str):
            problems.append(f"{where(page, line)}: {parsed}")
            continue
        overrides = getattr(parsed, "overrides", None) or []
        removed = bool(_SAYS_REMOVED.search(context))
        for override in overrides:
            key = override.partition("=")[0]
            problem = None if is_placeholder(key) else keys.problem(key)
            problems += [f"{where(page, line)}: {command.program}: {problem}"] if problem and not removed else []
        recipe = getattr(parsed, "config", None)
        if recipe and not is_placeholder(recipe) and not recipe.endswith((".yaml", ".yml")):
            if recipe not in RECIPES:
                problems.append(f"{where(page, line)}: no recipe {recipe!r} (built in: {RECIPES})")
            elif not removed and not any(is_placeholder(o.partition("=")[0]) for o in overrides):
                try:
                    load_config(recipe, overrides)
                except ConfigError as exc:
                    problems.append(f"{where(page, line)}: {exc}")
    return problems


def key_problems(page: Page, keys: ConfigKeys) -> list[str]:
    """In backticks (`optim.lr`, `optim.lr=0.01`) or as key=value in prose; a key the code no longer
    has only where its table row, or its paragraph, or the page's title says it was removed."""
    lines = dict(page.prose)
    heading = title(page)
    named = []  # (line, key, where it must say so)
    for span in page.spans:
        for token in span.text.split():
            match = _KEY.match(token.strip(",;:()'"))
            if match and not _FILE_SUFFIX.search(match.group(1)) and not token.endswith("("):
                row = lines[span.line]
                named.append((span.line, match.group(1), row if row.lstrip().startswith("|") else span.paragraph))
    for line, text in page.prose:
        without_code = re.sub(r"`[^`]*`", "", text)
        named += [(line, m.group(1), text) for m in _PROSE_OVERRIDE.finditer(without_code)]
    problems = []
    for line, key, context in named:
        problem = keys.problem(key)
        if problem and not _SAYS_REMOVED.search(f"{heading}\n{context}"):
            problems.append(f"{where(page, line)}: {problem} (if it was removed, say so beside it)")
    return problems


def _candidates(page: Page, section: str) -> tuple[dict[str, argparse.ArgumentParser], bool]:
    """The parsers of the project commands a section mentions, or the page anywhere, by name, and
    whether the section mentions another program (a script, torchrun), whose options are not ours
    to check."""
    on_page = _MENTION.findall("\n".join([*(t for _, t in page.prose), *(c for _, c in page.commands)]))
    other = any(m.split()[0] not in console_scripts() for m in _MENTION.findall(section))
    mentions = _MENTION.findall(section) + on_page
    parsers: dict[str, argparse.ArgumentParser] = {}
    for mention in mentions:
        words = mention.split()
        if words[0] not in console_scripts():
            continue
        parser = parser_for(console_scripts()[words[0]])
        subs = subparsers(parser)
        if len(words) > 1 and words[1] in subs:
            parsers[" ".join(words[:2])] = subs[words[1]]
        else:
            parsers[words[0]] = parser
            parsers.update({f"{words[0]} {name}": sub for name, sub in subs.items()})
    return parsers, other


@functools.cache
def every_option() -> frozenset[str]:
    """Every option of every console script (and of its subcommands)."""
    options: set[str] = set()
    for module in set(console_scripts().values()):
        parser = parser_for(module)
        options |= option_strings(parser).union(*(option_strings(s) for s in subparsers(parser).values()))
    return frozenset(options)


def option_problems(page: Page) -> list[str]:
    """``--flag`` (or ``--flag VALUE``) in prose: an option of a command its section or page names,
    with a value that command's parser accepts."""
    every = every_option()
    problems = []
    for span in page.spans:
        if not _OPTION_SPAN.match(span.text):
            continue
        flag = span.text.split()[0].split("=")[0]
        parsers, other = _candidates(page, span.section)
        owners = {name: p for name, p in parsers.items() if flag in option_strings(p)}
        if not owners:
            if not (other or (not parsers and flag in every)):
                named = ", ".join(sorted(parsers)) or "any command"
                problems.append(f"{where(page, span.line)}: {flag} is no option of {named}")
            continue
        if " " not in span.text.strip():
            continue
        failures = []
        for name, parser in owners.items():
            try:
                parse(parser, span.text.split(), partial=True)
                break
            except ParseFailure as exc:
                failures.append(f"{name} {span.text}: {exc}")
        else:
            if not any(is_placeholder(t) for t in span.text.split()[1:]):
                problems.append(f"{where(page, span.line)}: {failures[0]}")
    return problems


def link_problems(page: Page, pages: dict[Path, Page]) -> list[str]:
    """Every relative link names a file that exists, and its ``#anchor`` a heading of that page."""
    problems = []
    for line, target in page.links:
        if re.match(r"^[a-z][a-z+.-]*:", target):  # https:, mailto:
            continue
        file_part, _, anchor = target.partition("#")
        destination = (page.path.parent / file_part).resolve() if file_part else page.path
        if not destination.exists():
            problems.append(f"{where(page, line)}: {target}: no such file")
        elif anchor and destination.suffix == ".md":
            anchors = (pages.get(destination) or read_page(destination)).anchors
            if anchor not in anchors:
                problems.append(f"{where(page, line)}: {target}: no heading with anchor #{anchor}")
        elif anchor:
            problems.append(f"{where(page, line)}: {target}: an anchor into a file that is not Markdown")
    return problems
