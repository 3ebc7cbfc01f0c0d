"""Bad captures get one-line errors naming the file, and nothing is written for them."""

from __future__ import annotations

import json
import shutil

import cv2
import numpy as np
import pytest

from pipelines.captures.cli import main


@pytest.fixture
def broken(capture, tmp_path):
    """A writable copy of the rendered nerfstudio capture."""
    folder = tmp_path / "capture"
    shutil.copytree(capture.root / "nerfstudio", folder)
    return folder


def transforms(folder) -> dict:
    return json.loads((folder / "transforms.json").read_text())


def fails(folder, tmp_path, capsys, *extra: str) -> str:
    assert main([str(folder), "--out", str(tmp_path / "out"), "--quiet", *extra]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("usl-convert-captures: error: ") and "\n" not in err
    return err


def test_missing_image(broken, tmp_path, capsys):
    data = transforms(broken)
    data["frames"][3]["file_path"] = "images/gone.png"
    (broken / "transforms.json").write_text(json.dumps(data))
    assert f"{broken / 'images' / 'gone.png'}: no such file" in fails(broken, tmp_path, capsys)


def test_frame_without_pose(broken, tmp_path, capsys):
    data = transforms(broken)
    del data["frames"][5]["transform_matrix"]
    (broken / "transforms.json").write_text(json.dumps(data))
    err = fails(broken, tmp_path, capsys)
    assert "transforms.json: frame 5" in err and "no pose" in err


def test_inconsistent_image_size(broken, tmp_path, capsys):
    image = broken / "images" / "frame_00007.png"
    cv2.imwrite(str(image), np.zeros((60, 80, 3), np.uint8))
    err = fails(broken, tmp_path, capsys, "--resolution", "native")
    assert str(image) in err and "inconsistent image sizes" in err and "80x60" in err


@pytest.mark.parametrize("content", ['{"camera": "not a capture"}', "[1, 2]", "{not json"])
def test_json_that_is_not_a_capture(broken, tmp_path, capsys, content):
    (broken / "transforms.json").write_text(content)
    assert str(broken / "transforms.json") in fails(broken, tmp_path, capsys)


def test_detection_of_no_frame(broken, tmp_path, capsys):
    detections = json.loads((broken / "detections.json").read_text())
    detections[0]["file_name"] = "elsewhere/unknown.png"
    (broken / "detections.json").write_text(json.dumps(detections))
    err = fails(broken, tmp_path, capsys)
    assert str(broken / "detections.json") in err and "names no frame" in err


def test_images_without_poses_need_sfm(broken, tmp_path, capsys):
    (broken / "transforms.json").unlink()
    assert "--poses sfm" in fails(broken, tmp_path, capsys)
