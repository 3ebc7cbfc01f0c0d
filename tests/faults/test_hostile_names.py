"""Names from input files that would become paths outside their folders: every converter refuses them.

Each case runs a converter's CLI with one hostile name in one input file and asserts exit status 2,
one line naming that file and the name, and that nothing was written: no ``--out`` and no file
anywhere else under the test's folder but the inputs.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest

from pipelines.hypersim.cli import main as hypersim_main
from pipelines.hypersim.metadata import CAMERA_COLUMNS, SPLIT_COLUMNS
from pipelines.scannet.cli import main as scannet_main
from pipelines.scene_shapes.cli import main as scene_shapes_main
from tests.faults.outputs import one_line_error
from usl.errors import UslError
from usl.records.names import check_name, name_problem

HOSTILE = {
    "folder above": "../../x",
    "absolute path": "/tmp/x",
    "nested path": "a/b",
    "windows separator": "a\\b",
    "hidden name": ".build",
    "dot-dot": "..",
    "empty": "",
    "white space around": " train",
    "newline": "tr\nain",
    "NUL": "tr\0ain",
    "too long": "x" * 256,
}


def write_csv(path: Path, columns: tuple[str, ...], rows: list[dict[str, str]]) -> Path:
    # by hand, not csv.writer: Python 3.10's writer refuses a NUL (3.11 and later quote it)
    quote = lambda value: '"' + value.replace('"', '""') + '"'  # noqa: E731
    lines = [",".join(columns)] + [",".join(quote(row.get(c, "")) for c in columns) for row in rows]
    path.write_text("\r\n".join(lines) + "\r\n", newline="")
    return path


def hypersim(field: str, file: str) -> Callable[[Path, str], tuple[int, Path]]:
    """The Hypersim converter with ``name`` as ``field`` of the split or camera CSV."""

    def run(root: Path, name: str) -> tuple[int, Path]:
        (root / "scenes" / "ai_001_001").mkdir(parents=True)
        split = {"scene_name": "ai_001_001", "camera_name": "cam_00", "frame_id": "0"}
        split |= {"included_in_public_release": "True", "exclude_reason": "", "split_partition_name": "train"}
        camera = {c: "1" for c in CAMERA_COLUMNS} | {"scene_name": "ai_001_001"}
        (split if file == "split" else camera)[field] = name
        split_csv = write_csv(root / "split.csv", SPLIT_COLUMNS, [split])
        camera_csv = write_csv(root / "cameras.csv", CAMERA_COLUMNS, [camera])
        argv = [str(root / "scenes"), "--split-csv", str(split_csv), "--camera-csv", str(camera_csv)]
        return hypersim_main(
            [*argv, "--out", str(root / "out"), "--quiet"]
        ), split_csv if file == "split" else camera_csv

    return run


def scannet(root: Path, name: str) -> tuple[int, Path]:
    """The ScanNet converter with ``name`` as a scan id of the official split file."""
    (root / "scans" / "scene0000_00").mkdir(parents=True)
    (root / "splits").mkdir()
    split_file = root / "splits" / "scannetv2_train.txt"
    split_file.write_text(f"scene0000_00\n{name}\n")
    argv = ["--scans-root", str(root / "scans"), "--splits-dir", str(root / "splits"), "--splits", "train"]
    return scannet_main([*argv, "--masks", "scannet-labels", "--out", str(root / "out"), "--quiet"]), split_file


def mesh_root(root: Path, name: str) -> tuple[int, Path]:
    """Scene-Shapes with ``name`` as a category folder of the --mesh-root category map."""
    (root / "meshes" / "03001627").mkdir(parents=True)
    category_map = root / "map.json"  # JSON is YAML, and keeps every character of the name
    category_map.write_text(f'{{"03001627": "chair", {json.dumps(name)}: "sofa"}}')
    argv = ["--mesh-root", str(root / "meshes"), "--category-map", str(category_map)]
    return scene_shapes_main([*argv, "--out", str(root / "out"), "--quiet"]), category_map


@dataclass(frozen=True)
class Converter:
    run: Callable[[Path, str], tuple[int, Path]]
    what: str  # how the error calls the name


CONVERTERS = {
    "hypersim split": Converter(hypersim("split_partition_name", "split"), "split_partition_name"),
    "hypersim scene": Converter(hypersim("scene_name", "split"), "scene_name"),
    "hypersim camera": Converter(hypersim("camera_name", "split"), "camera_name"),
    "hypersim camera-csv scene": Converter(hypersim("scene_name", "camera"), "scene_name"),
    "scannet scan id": Converter(scannet, "scan id"),
    "scene-shapes category folder": Converter(mesh_root, "category folder"),
}
# CSV readers strip nothing but the split name, and a text file's lines are split and stripped:
# names those formats cannot carry are left out of their cases.
CANNOT_CARRY = {
    "hypersim split": {"white space around", "empty"},  # stripped, and an empty split has its own error
    "scannet scan id": {"white space around", "empty", "newline"},  # lines are stripped, blank ones skipped
}


@pytest.mark.parametrize("kind", HOSTILE)
@pytest.mark.parametrize("converter", CONVERTERS)
def test_a_hostile_name_in_an_input_file_is_refused_before_anything_is_written(
    converter, kind, tmp_path, capsys, fault_tally
):
    if kind in CANNOT_CARRY.get(converter, ()):
        pytest.skip(f"{converter}: the input format cannot hold a name that is {kind}")
    if kind == "newline" and "hypersim" in converter:
        pytest.skip("a CSV field with a newline is quoted: the name holds a control character (covered by NUL)")
    name = HOSTILE[kind]
    root = tmp_path / "deep" / "er"
    root.mkdir(parents=True)
    code, source = CONVERTERS[converter].run(root, name)
    inputs = sorted(p for p in tmp_path.rglob("*") if p.is_file())
    fault_tally.tried += 1
    assert code == 2
    message = one_line_error(capsys.readouterr().err)
    named = f"{CONVERTERS[converter].what} {name!r}" in message
    if kind == "NUL" and "hypersim" in converter and sys.version_info < (3, 11):
        named = named or "(line contains NUL)" in message  # Python 3.10's csv reader refuses the line itself
    assert f"{source}" in message and named, message
    assert not (root / "out").exists()
    assert inputs == sorted(p for p in tmp_path.rglob("*") if p.is_file()) and all(root in p.parents for p in inputs)
    fault_tally.survived += 1


@pytest.mark.parametrize("name", ["train", "ai_001_001", "cam_00", "scene0000_00", "03001627", "Étagère 2", "a.b"])
def test_plain_names_pass(name):
    assert name_problem(name) is None and check_name(name, "split", "f.csv") == name


def test_the_error_names_the_source_and_the_name():
    with pytest.raises(UslError, match=r"^split.csv:3: split '\.\./x' holds a path separator"):
        check_name("../x", "split", "split.csv:3")
