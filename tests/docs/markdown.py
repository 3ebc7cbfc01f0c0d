"""The parts of a Markdown page the docs tests check: fenced shell commands, inline code spans (with
the paragraph around them), links, and the anchors GitHub gives the page's headings."""

from __future__ import annotations

import re
import unicodedata
from dataclasses import dataclass, field
from pathlib import Path

SHELL_LANGUAGES = ("", "bash", "sh", "shell", "console")
_FENCE = re.compile(r"^\s*(```|~~~)\s*([\w+-]*)")
_INLINE_CODE = re.compile(r"(?<!`)(`+)(?!`)(.+?)(?<!`)\1(?!`)")
_LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
_HTML_ANCHOR = re.compile(r"<a\s+(?:name|id)=\"([^\"]+)\"")


@dataclass
class Span:
    """An inline code span: its text, its line, the paragraph (or table) it sits in, and the text of
    its section (from the heading above) up to the end of that paragraph."""

    text: str
    line: int
    paragraph: str
    section: str


@dataclass
class Page:
    path: Path
    commands: list[tuple[int, str]] = field(default_factory=list)  # (line, command) from shell blocks
    spans: list[Span] = field(default_factory=list)
    prose: list[tuple[int, str]] = field(default_factory=list)  # (line, text) outside code blocks
    links: list[tuple[int, str]] = field(default_factory=list)  # (line, target) of [text](target)
    anchors: set[str] = field(default_factory=set)


def read_page(path: Path) -> Page:
    page = Page(path)
    lines = path.read_text(encoding="utf-8").splitlines()
    fence: str | None = None
    shell = False
    pending = ""  # a command continued with a trailing backslash
    slugs: dict[str, int] = {}
    paragraph: list[tuple[int, str]] = []
    section: list[str] = []

    def close_paragraph() -> None:
        text = "\n".join(t for _, t in paragraph)
        section.append(text)
        for number, line in paragraph:
            page.prose.append((number, line))
            for match in _INLINE_CODE.finditer(line):
                page.spans.append(Span(match.group(2).strip(), number, text, "\n".join(section)))
            page.links.extend((number, m.group(1)) for m in _LINK.finditer(_without_code(line)))
            page.anchors.update(_HTML_ANCHOR.findall(line))
        paragraph.clear()

    for number, line in enumerate(lines, 1):
        opening = _FENCE.match(line)
        if fence is not None:
            if line.strip().startswith(fence) and not line.strip()[len(fence) :].strip():
                fence = None
            elif shell:
                text = line.split(" #", 1)[0].rstrip() if not line.lstrip().startswith("#") else ""
                if text.endswith("\\"):
                    pending += text[:-1] + " "
                elif text or pending:
                    page.commands.append((number, (pending + text).strip()))
                    pending = ""
            continue
        if opening:
            close_paragraph()
            fence, shell = opening.group(1), opening.group(2).lower() in SHELL_LANGUAGES
            continue
        heading = re.match(r"^(#{1,6})\s+(.*?)\s*#*\s*$", line)
        if heading:
            close_paragraph()
            section.clear()
            slug = github_slug(heading.group(2))
            count = slugs.get(slug, 0)
            slugs[slug] = count + 1
            page.anchors.add(slug if count == 0 else f"{slug}-{count}")
            page.prose.append((number, line))
            continue
        if not line.strip():
            close_paragraph()
        else:
            paragraph.append((number, line))
    close_paragraph()
    return page


def _without_code(line: str) -> str:
    return _INLINE_CODE.sub(lambda m: " " * len(m.group(0)), line)


def github_slug(heading: str) -> str:
    """The anchor GitHub gives a heading: its rendered text in lower case, without any character but
    letters, marks, digits, ``_``, ``-`` and spaces, each space a ``-`` (duplicates get ``-1``, ...)."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading)  # a link's text
    text = re.sub(r"<[^>]+>", "", text).lower()
    kept = (
        ch
        for ch in text
        if ch in "-_ " or unicodedata.category(ch)[0] in "LM" or unicodedata.category(ch) in ("Nd", "Nl")
    )
    return "".join(kept).replace(" ", "-")
