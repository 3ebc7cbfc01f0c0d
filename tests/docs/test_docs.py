"""The docs say what the code does: every command line in README.md, docs/ and the pipelines' READMEs
parses with the real command's parser, every config key and option they name exists, and every
relative link and anchor resolves. Nothing runs; the whole module takes seconds."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from tests.docs.checks import ConfigKeys, command_problems, key_problems, link_problems, option_problems
from tests.docs.commands import REPO, console_scripts, runnable_problem
from tests.docs.markdown import Page, github_slug, read_page

PAGES = sorted([REPO / "README.md", *(REPO / "docs").rglob("*.md"), *(REPO / "pipelines").glob("*/README.md")])


def _id(path: Path) -> str:
    return str(path.relative_to(REPO))


@pytest.fixture(scope="module")
def pages() -> dict[Path, Page]:
    return {path: read_page(path) for path in PAGES}


@pytest.fixture(scope="module")
def keys() -> ConfigKeys:
    return ConfigKeys()


@pytest.mark.parametrize("path", PAGES, ids=_id)
def test_every_command_line_parses_with_the_real_parser(pages, keys, path):
    problems = command_problems(pages[path], keys)
    assert not problems, "\n".join(problems)


@pytest.mark.parametrize("path", PAGES, ids=_id)
def test_every_config_key_named_exists(pages, keys, path):
    problems = key_problems(pages[path], keys)
    assert not problems, "\n".join(problems)


@pytest.mark.parametrize("path", PAGES, ids=_id)
def test_every_option_named_in_prose_belongs_to_a_command_the_page_names(pages, path):
    problems = option_problems(pages[path])
    assert not problems, "\n".join(problems)


@pytest.mark.parametrize("path", PAGES, ids=_id)
def test_every_relative_link_and_anchor_resolves(pages, path):
    problems = link_problems(pages[path], pages)
    assert not problems, "\n".join(problems)


def test_the_readme_command_table_names_each_command_s_runnable_module(pages):
    rows = re.findall(r"^\| `(usl-[a-z-]+)` \| `python -m ([\w.]+)` \|", (REPO / "README.md").read_text(), re.M)
    assert dict(rows) == console_scripts()
    assert [runnable_problem(module) for _, module in rows] == [None] * len(rows)


def test_the_checks_find_what_they_look_for(tmp_path, keys):
    """Each check on a page holding one mistake of each kind (an oracle written by hand)."""
    (tmp_path / "other.md").write_text("# Other page\n\n## A `key` — and more\n")
    page_path = tmp_path / "page.md"
    page_path.write_text(
        "# A page\n\n"
        "```bash\n"
        "usl-train --config tiny optim.lr=0.1 optim.lrr=1\n"
        "usl-train --config tinyy\n"
        "usl-eval data --rows model --no-such-option\n"
        "usl-records migrate  # a comment\n"
        "torchrun --nproc_per_node 2 -m usl.engine.train --config tiny\n"
        "usl-convert-scannet ... --masks scannet-labels [--tracker source-ids]\n"
        "bash scripts/no_such_script.sh\n"
        "```\n\n"
        "`usl-predict --fov` and `usl-eval --pictures-by worst` and `optim.lr` and `optim.nope`.\n"
        "\n`model.shape.gone=1` was removed.\n\n"
        "| `loss.weights.dropped=1` | 0.1 |\n| `loss.weights.dropped=2` (since removed) | 0.2 |\n\n"
        "With usl-predict, `--fov 60`, `--no-such-flag`.\n\n"
        "[ok](other.md#a-key--and-more) [bad anchor](other.md#a-key) [gone](missing.md) [self](#a-page)\n"
    )
    page = read_page(page_path)
    found = {
        "commands": command_problems(page, keys),
        "keys": key_problems(page, keys),
        "options": option_problems(page),
        "links": link_problems(page, {}),
    }
    expected = {
        "commands": [
            ":4: usl-train: no config key optim.lrr",
            ":4: command line: config.optim: unknown key(s) ['lrr']",
            ":5: no recipe 'tinyy'",
            ":6: usl-eval: unrecognized arguments: --no-such-option",
            ":7: usl-records: the following arguments are required: root",
            ":8: usl.engine.train does not run as a program",
            ":10: scripts/no_such_script.sh does not exist",
            ":13: usl-eval: argument --pictures-by: invalid choice: 'worst'",
        ],
        "keys": [":13: no config key optim.nope", ":17: no config key loss.weights.dropped"],
        "options": [":20: --no-such-flag is no option of usl-convert-scannet, usl-eval, usl-predict,"],
        "links": [":22: other.md#a-key: no heading", ":22: missing.md: no such file"],
    }
    for kind, lines in expected.items():
        assert len(found[kind]) == len(lines), (kind, found[kind])
        for problem, line in zip(sorted(found[kind], key=_line_number), lines, strict=True):
            assert line in problem, (kind, problem)


def _line_number(problem: str) -> int:
    return int(re.search(r"\.md:(\d+):", problem).group(1))


@pytest.mark.parametrize(
    "heading, slug",
    [
        ("6. Metrics and evaluation rules", "6-metrics-and-evaluation-rules"),
        ("`model.shape.global_basis`", "modelshapeglobal_basis"),
        ("Install (without root) — step by step", "install-without-root--step-by-step"),
        ("Faults and hostile input", "faults-and-hostile-input"),
        ("Ünïcode § 3 → ok", "ünïcode--3--ok"),
    ],
)
def test_anchors_follow_github_s_slugs(heading, slug):
    assert github_slug(heading) == slug
