"""Every command line: ``--help`` answers without importing torch, shows the docstring examples and
a help text on every option; the shared options behave alike everywhere; a ``UslWarning`` prints as one line."""

from __future__ import annotations

import argparse
import importlib
import json
import subprocess
import sys
import warnings
from pathlib import Path

import pytest

from usl.cli.common import common_options, make_parser, resolution, warning_lines
from usl.errors import UslWarning

REPO = Path(__file__).parents[2]
# console script -> module of its main(), as in pyproject.toml's [project.scripts]
COMMANDS = {
    "usl-build-scene-shapes": "pipelines.scene_shapes.cli",
    "usl-records": "usl.cli.records",
    "usl-convert-hypersim": "pipelines.hypersim.cli",
    "usl-convert-scannet": "pipelines.scannet.cli",
    "usl-train": "usl.cli.train",
    "usl-eval": "usl.cli.evaluate",
    "usl-predict": "usl.cli.predict",
    "usl-segment": "usl.cli.segment",
}
# One fresh interpreter runs every --help in turn and notes after each whether torch is loaded: as
# none may load it, the first that does is the culprit (and one process keeps the test fast).
HELP_PROBE = """
import contextlib, importlib, io, json, sys
result = {}
for command, module in json.loads(sys.argv[1]).items():
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        try:
            importlib.import_module(module).main(["--help"])
        except SystemExit as exc:
            code = exc.code
    result[command] = {"code": code, "help": out.getvalue(), "torch": "torch" in sys.modules}
print(json.dumps(result))
"""


def test_the_command_table_matches_pyproject():
    text = (REPO / "pyproject.toml").read_text()
    for command, module in COMMANDS.items():
        assert f'{command} = "{module}:main"' in text


@pytest.fixture(scope="module")
def helps():
    probe = subprocess.run(
        [sys.executable, "-c", HELP_PROBE, json.dumps(COMMANDS)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=300,
        env={"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin"},
    )
    assert probe.returncode == 0, probe.stderr[-2000:]
    return json.loads(probe.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_help_runs_without_torch_and_keeps_the_examples(helps, command):
    shown = helps[command]
    assert shown["code"] == 0 and not shown["torch"], command
    doc = importlib.import_module(COMMANDS[command]).__doc__
    example = next(line for line in doc.splitlines() if line.strip().startswith(command))
    assert example.rstrip() in shown["help"]  # verbatim, indentation kept


def _parsers():
    for command, module in COMMANDS.items():
        mod = importlib.import_module(module)
        build = mod.parser
        parser = build({"tracking": {"min_track_frames": 50}}) if command == "usl-convert-scannet" else build()
        yield command, parser
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for name, sub in action.choices.items():
                    yield f"{command} {name}", sub


def test_every_option_has_help_and_shared_options_share_their_names():
    for command, parser in _parsers():
        for action in parser._actions:
            if action.help == argparse.SUPPRESS or isinstance(
                action, (argparse._HelpAction, argparse._SubParsersAction)
            ):
                continue
            assert action.help, f"{command} {action.option_strings or action.dest}: no help text"
        options = {s for a in parser._actions for s in a.option_strings}
        for old in ("--output-dir", "--size", "--image-quality", "--frame-stride"):  # spellings before 0.1
            assert old not in options, f"{command} still takes {old}"


def test_shared_parent_and_defaults_in_help(capsys):
    parser = make_parser(
        "tool",
        "tool: does things.\n\n    tool --out x   # example\n",
        parents=[common_options(out="output folder", out_default="o", workers="processes", seed="seed")],
    )
    text = parser.format_help()
    assert "    tool --out x   # example" in text and "processes (default: 1)" in text and "seed (default: 0)" in text
    assert "--quiet" in text and parser.parse_args(["--out", "a", "--out", "b"]).out == Path("b")
    with pytest.raises(SystemExit):
        parser.parse_args(["--output-dir", "a"])
    assert "unrecognized arguments: --output-dir" in capsys.readouterr().err


def test_a_usl_warning_is_one_line_naming_the_command_and_others_show_as_python_shows_them(capsys):
    with pytest.warns(UserWarning) as caught, warning_lines("tool"):
        warnings.warn("saved key x.y ignored", UslWarning, stacklevel=1)
        warnings.warn("something else", UserWarning, stacklevel=1)
    assert capsys.readouterr().err == "tool: warning: saved key x.y ignored\n"
    assert [str(w.message) for w in caught] == ["something else"]  # passed on to whoever shows warnings


@pytest.mark.parametrize("text, size", [("512", (512, 512)), ("640x480", (640, 480)), (" 32X24 ", (32, 24))])
def test_resolution_syntax(text, size):
    assert resolution(text) == size


@pytest.mark.parametrize("text", ["64by48", "0x10", "x", "12x"])
def test_bad_resolution(text):
    with pytest.raises(argparse.ArgumentTypeError, match="WIDTHxHEIGHT|>= 1"):
        resolution(text)
