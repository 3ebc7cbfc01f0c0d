"""The Python API as users call it: the README's example runs as written, ``import usl`` stays cheap,
and what ``predict`` returns is what the exported files hold."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import trimesh
from PIL import Image

import usl
from tests.evaluation.eval_helpers import tiny_checkpoint
from usl.errors import UslError
from usl.inference.gltf_scene import IMAGE_NODE
from usl.inference.predict import camera_for

README = Path(__file__).resolve().parents[2] / "README.md"


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    run = tmp_path_factory.mktemp("api") / "runs" / "tiny"
    tiny_checkpoint(run)
    return run


@pytest.fixture(scope="module")
def photo():
    rng = np.random.default_rng(0)
    return rng.integers(0, 255, (96, 128, 3), dtype=np.uint8)


def readme_example() -> str:
    section = README.read_text().split("## Python API", 1)[1]
    return re.search(r"```python\n(.*?)```", section, re.S).group(1)


def test_readme_example_runs_as_written(run_dir, photo, tmp_path):
    Image.fromarray(photo).save(tmp_path / "photo.jpg")
    (tmp_path / "runs").symlink_to(run_dir.parent)
    done = subprocess.run(
        [sys.executable, "-c", readme_example()], cwd=tmp_path, capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 0, done.stderr[-3000:]
    scene = trimesh.load(tmp_path / "photo.glb")
    assert IMAGE_NODE in scene.geometry and scene.has_camera


def test_import_usl_is_cheap_and_versioned():
    code = "import sys, usl; print(usl.__version__, 'torch' in sys.modules, callable(usl.load))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out == [usl.__version__, "False", "True"] and re.fullmatch(r"\d+\.\d+\.\d+", out[0])


def test_predict_returns_what_the_files_hold(run_dir, photo, tmp_path):
    model = usl.load(run_dir, device="cpu")
    scene = model.predict(photo, fov=60, score=0.0)
    everything = len(scene.objects)
    assert everything > 0 and all(0.0 <= o.score <= 1.0 for o in scene.objects)
    high = model.predict(photo, fov=60, score=0.5)
    assert len(high.objects) == sum(o.score >= 0.5 for o in scene.objects)  # the threshold applies
    names = dict(zip(model.categories.ids, model.categories.names, strict=True))
    assert all(names[o.category_id] == o.category for o in scene.objects)  # ids are the dataset's (1-based)
    assert set(model.categories.ids) == {1, 2, 3}

    glb = trimesh.load(scene.export(tmp_path / "x.glb"))
    nodes = sorted(n for n in glb.geometry if n != IMAGE_NODE)
    assert len(nodes) == everything
    for node, obj in zip(nodes, scene.objects, strict=True):  # glTF axes in the API and in the file
        np.testing.assert_allclose(glb.geometry[node].vertices, obj.mesh.vertices, atol=1e-5)
        extras = glb.graph.transforms.edge_data[("world", node)]["metadata"]
        assert extras["category_id"] == obj.category_id and extras["category"] == obj.category
    opencv = model.predict(photo, fov=60, score=0.0, axes="opencv")
    np.testing.assert_allclose(opencv.objects[0].mesh.vertices * [1, -1, -1], scene.objects[0].mesh.vertices)
    assert (scene.objects[0].mesh.vertices[:, 2] < 0).all()  # in front of the camera, looking down -Z

    # the same image as a file, as floats, and with the equivalent K: the same objects
    Image.fromarray(photo).save(tmp_path / "photo.png")
    K = camera_for(photo, None, 60.0).double().numpy()
    for other in (
        model.predict(tmp_path / "photo.png", fov=60, score=0.0),
        model.predict(photo / 255.0, fov=60, score=0.0),
        model.predict(photo, K=K, score=0.0),
    ):
        assert [o.category_id for o in other.objects] == [o.category_id for o in scene.objects]
        np.testing.assert_allclose(other.objects[0].mesh.vertices, scene.objects[0].mesh.vertices, atol=1e-3)

    overlay = cv2.imread(str(scene.export(tmp_path / "x.png")))
    assert min(overlay.shape[:2]) >= 512  # drawn large enough for its labels


def test_obj_keeps_objects_apart_for_trimesh(run_dir, photo, tmp_path):
    scene = usl.load(run_dir, device="cpu").predict(photo, fov=60, score=0.0)
    loaded = trimesh.load_scene(scene.export(tmp_path / "x.obj"))
    assert len(loaded.geometry) == len(scene.objects) and (tmp_path / "x.mtl").is_file()
    by_name = {o.category: o for o in scene.objects}
    assert {name.split("_", 1)[1].replace("_", " ") for name in loaded.geometry} == set(by_name)
    ply = trimesh.load(scene.export(tmp_path / "x.ply"))  # one merged mesh, as PLY holds
    assert len(ply.vertices) == sum(len(o.mesh.vertices) for o in scene.objects)


def test_bad_inputs_give_one_line_errors(run_dir, tmp_path):
    model = usl.load(run_dir, device="cpu")
    with pytest.raises(UslError, match=r"\(H, W, 3\) RGB image, got an array of shape \(4, 4\)"):
        model.predict(np.zeros((4, 4), np.uint8))
    with pytest.raises(UslError, match="uint8 pixels or floats in \\[0, 1\\]"):
        model.predict(np.full((8, 8, 3), 7.0))
    with pytest.raises(UslError, match="K must be a 3x3 matrix"):
        model.predict(np.zeros((8, 8, 3), np.uint8), K=np.eye(2))
    with pytest.raises(UslError, match="nothere.png does not exist"):
        model.predict(tmp_path / "nothere.png")
    with pytest.raises(UslError, match="unknown scene format 'stl'"):
        model.predict(np.zeros((8, 8, 3), np.uint8), score=0.0).export(tmp_path / "x.stl")
