"""``usl-eval`` and ``usl-predict``: a full or refused disk at every write, a second writer on one
``--out``, and image names that cannot name output files. Each is one line; the report of an
earlier run in the folder stays whole, and a rerun writes it again."""

from __future__ import annotations

import socket
import subprocess
import sys

import cv2
import numpy as np
import pytest

from tests.evaluation.eval_helpers import build_dataset, tiny_checkpoint
from tests.faults.outputs import FAULTS, bytes_lost, finished_files, one_line_error
from usl.cli.evaluate import main as eval_main
from usl.cli.predict import main as predict_main

HOLD_FOLDER = """
import sys
from pathlib import Path
from usl.records.claims import sole_writer
with sole_writer(Path(sys.argv[1]), sys.argv[2]):
    print("held", flush=True)
    sys.stdin.read()
"""


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("eval")
    return build_dataset(root / "ds", num_scenes=1, num_views=2), tiny_checkpoint(root / "run")


@pytest.fixture(scope="module")
def image(tmp_path_factory):
    path = tmp_path_factory.mktemp("images") / "room.png"
    cv2.imwrite(str(path), np.random.default_rng(0).integers(0, 255, (40, 60, 3), dtype=np.uint8))
    return path


def evaluate(data, out) -> int:
    dataset, checkpoint = data
    argv = [str(dataset), "--checkpoint", str(checkpoint), "--rows", "fixed,model", "--out", str(out)]
    return eval_main([*argv, "--samples-3d", "100", "--pictures", "0", "--device", "cpu", "--quiet"])


def predict(checkpoint, images, out) -> int:
    argv = [*map(str, images), "--checkpoint", str(checkpoint), "--fov", "60", "--out", str(out)]
    return predict_main([*argv, "--score-threshold", "0.01", "--device", "cpu", "--quiet"])


@pytest.mark.parametrize(("code", "fault"), FAULTS)
def test_every_write_of_an_evaluation_fails_cleanly(
    code, fault, data, tmp_path, write_faults, fail_write, capsys, fault_tally
):
    out = tmp_path / "eval"
    assert evaluate(data, out) == 0
    earlier = finished_files(out)
    counting = write_faults()
    assert evaluate(data, out) == 0
    assert {"rename into place (metrics.json)", "rename into place (table.md)"} <= set(counting.sites)
    capsys.readouterr()
    for k, site in enumerate(counting.sites):
        fail_write(k, code, f"evaluation: {site}", lambda: evaluate(data, out))
        message = one_line_error(capsys.readouterr().err)
        assert fault in message and "rerun the same command" in message, message
        lost = bytes_lost(earlier, finished_files(out))
        fault_tally.bytes_lost += lost
        assert lost == 0, site
        fault_tally.survived += 1
    assert evaluate(data, out) == 0


@pytest.mark.parametrize("command", ["usl-eval", "usl-predict"])
def test_a_second_writer_on_one_out_is_refused_in_one_line(command, data, image, tmp_path, capsys, fault_tally):
    out = tmp_path / "out"
    out.mkdir()
    holder = subprocess.Popen(
        [sys.executable, "-c", HOLD_FOLDER, str(out), command], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    try:
        assert holder.stdout.readline() == "held\n"
        code = evaluate(data, out) if command == "usl-eval" else predict(data[1], [image], out)
        fault_tally.tried += 1
        assert code == 2
        message = one_line_error(capsys.readouterr().err)
        assert f"{out}: {command} is already writing here (pid {holder.pid} on {socket.gethostname()}" in message
        assert sorted(p.name for p in out.iterdir()) == [".lock"]
        fault_tally.survived += 1
    finally:
        holder.kill()
        holder.wait()
    code = evaluate(data, out) if command == "usl-eval" else predict(data[1], [image], out)
    assert code == 0 and not (out / ".lock").exists()


@pytest.mark.parametrize("name", [".hidden.png", "tab\there.png", "new\nline.png"])
def test_an_image_name_that_cannot_name_files_is_refused(name, data, image, tmp_path, capsys, fault_tally):
    hostile = tmp_path / name
    hostile.write_bytes(image.read_bytes())
    out = tmp_path / "out"
    assert predict(data[1], [image, hostile], out) == 2
    fault_tally.tried += 1
    message = one_line_error(capsys.readouterr().err)
    assert "image name" in message and "it would become a path" in message
    assert not [p for p in out.rglob("*") if p.is_file()] if out.exists() else True
    fault_tally.survived += 1
