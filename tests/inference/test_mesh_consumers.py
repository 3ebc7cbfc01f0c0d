"""``usl-predict``'s GLB, OBJ and PLY as Open3D and the Khronos glTF-Validator read them.

Neither tool is a dependency: each test runs where its tool is installed and skips, saying how to
install it, elsewhere (as the browser test of the viewer does). Open3D runs in its own interpreter,
``USL_OPEN3D_PYTHON`` (e.g. a scratch venv: ``python3 -m venv /tmp/o3d && /tmp/o3d/bin/pip install
open3d-cpu``), or this one if it imports ``open3d``; the validator is the npm package
``gltf-validator`` under ``USL_GLTF_VALIDATOR_DIR`` (``cd DIR && npm install gltf-validator``) or
the working directory, run by ``node``.

What Open3D 0.20 reads (as docs/getting_started.md §5 says): ``read_triangle_model`` keeps the objects of
a GLB or OBJ apart as named meshes with their colours (the GLB also the textured image plane);
``read_triangle_mesh`` merges them into one mesh, where ``triangle_material_ids`` still tell them
apart; a PLY is one mesh whose vertex colours tell the objects apart. Only glTF keeps category and
score (node ``extras``), which Open3D does not read.
"""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.inference.test_predict import CATEGORIES, GLTF_FROM_OPENCV, _frame_for_fov, fake_detector
from usl.inference.gltf_scene import IMAGE_NODE
from usl.inference.predict import predict_images
from usl.vis.visualize import palette

PROBE = Path(__file__).with_name("open3d_probe.py")
OBJECTS = ["00_chair", "01_dining_table"]  # the fake detector's two detections above the threshold


def _open3d_python() -> str | None:
    if os.environ.get("USL_OPEN3D_PYTHON"):
        return os.environ["USL_OPEN3D_PYTHON"]
    return sys.executable if importlib.util.find_spec("open3d") else None


def _validator_dir() -> str | None:
    """A folder from which node resolves ``gltf-validator``, or None."""
    node = shutil.which("node")
    folder = os.environ.get("USL_GLTF_VALIDATOR_DIR", os.getcwd())
    if node is None:
        return None
    found = subprocess.run(
        [node, "-e", "require.resolve('gltf-validator', {paths: [process.argv[1]]})", folder], capture_output=True
    )
    return folder if found.returncode == 0 else None


OPEN3D_PYTHON = _open3d_python()
VALIDATOR_DIR = _validator_dir()
needs_open3d = pytest.mark.skipif(
    OPEN3D_PYTHON is None,
    reason="Open3D is not installed (pip install open3d-cpu==0.20.0, here or in a venv named by USL_OPEN3D_PYTHON)",
)
needs_validator = pytest.mark.skipif(
    VALIDATOR_DIR is None,
    reason="Khronos glTF-Validator is not installed (node, and npm install gltf-validator in USL_GLTF_VALIDATOR_DIR)",
)


@pytest.fixture(scope="module")
def written(tmp_path_factory, image_path):
    """GLB, OBJ and PLY of the fake detector's two objects, and the vertices it predicted (glTF axes)."""
    out = tmp_path_factory.mktemp("predicted")
    predict_images(fake_detector, [image_path], out, CATEGORIES, fov_deg=60.0, formats=["glb", "obj", "ply"])
    verts = fake_detector(_frame_for_fov(image_path)).verts.double().numpy()[:2] * GLTF_FROM_OPENCV
    return out, verts


def _rows(points) -> set[tuple[float, ...]]:
    return {tuple(np.round(p, 5)) for p in np.asarray(points, dtype=np.float64)}


@needs_open3d
def test_open3d_keeps_the_objects_apart_in_glb_and_obj_models_and_merges_them_as_one_mesh(written, tmp_path):
    out, verts = written
    files = [str(out / f"room.{ext}") for ext in ("glb", "obj", "ply")]
    report_path = tmp_path / "open3d.json"
    done = subprocess.run([OPEN3D_PYTHON, str(PROBE), str(report_path), *files], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    report = json.loads(report_path.read_text())
    glb, obj, ply = (report[f] for f in files)
    colours = [[c / 255 for c in rgb] + [1.0] for rgb in palette(2)]
    for read, names in ((glb, [*OBJECTS, IMAGE_NODE]), (obj, OBJECTS)):
        assert [m["name"] for m in read["model"]] == names  # one named mesh per object
        for mesh, expected, colour in zip(read["model"], verts, colours, strict=True):
            assert _rows(mesh["vertices"]) == _rows(expected) and mesh["triangles"] == 80
            np.testing.assert_allclose(mesh["base_color"], colour, atol=1e-6)
    assert glb["model"][2]["textured"] and glb["model"][2]["triangles"] == 2  # the image plane and its texture
    # read_triangle_mesh merges; each object's triangles keep their own material id
    for read, extra in ((glb, 4), (obj, 0)):
        assert _rows(read["mesh"]["vertices"]) >= _rows(np.concatenate(verts))
        assert len(read["mesh"]["vertices"]) == 2 * len(verts[0]) + extra
        ids = read["mesh"]["triangle_material_ids"]
        assert [ids.count(i) for i in sorted(set(ids))][:2] == [80, 80]
    # PLY: one mesh, no model; the objects differ only by vertex colour
    assert ply["model"] == [] and len(ply["mesh"]["vertices"]) == 2 * len(verts[0])
    by_colour: dict[tuple[float, ...], set] = {}
    for point, colour in zip(ply["mesh"]["vertices"], ply["mesh"]["vertex_colors"], strict=True):
        by_colour.setdefault(tuple(np.round(colour, 3)), set()).add(tuple(np.round(point, 5)))
    assert sorted(map(sorted, by_colour.values())) == sorted(sorted(_rows(v)) for v in verts)


VALIDATE = """
const { readFileSync } = require("fs");
const validator = require(require.resolve("gltf-validator", { paths: [process.argv[1]] }));
validator.validateBytes(new Uint8Array(readFileSync(process.argv[2])), { maxIssues: 100 })
  .then((report) => console.log(JSON.stringify(report)))
  .catch((error) => { console.error(error); process.exit(1); });
"""


@needs_validator
@pytest.mark.parametrize("axes", ["gltf", "opencv"])
def test_khronos_validator_finds_no_error_warning_or_hint_in_the_glb(axes, image_path, tmp_path):
    predict_images(fake_detector, [image_path], tmp_path, CATEGORIES, fov_deg=60.0, formats=["glb"], axes=axes)
    done = subprocess.run(
        [shutil.which("node"), "-e", VALIDATE, VALIDATOR_DIR, str(tmp_path / "room.glb")],
        capture_output=True,
        text=True,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    report = json.loads(done.stdout)
    issues = report["issues"]
    assert (issues["numErrors"], issues["numWarnings"], issues["numHints"]) == (0, 0, 0), issues["messages"]
    # the one info: the input image is 120x80, not a power of two (fine for glTF 2.0 textures)
    assert [m["code"] for m in issues["messages"]] == ["IMAGE_NPOT_DIMENSIONS"]
    info = report["info"]
    assert info["extensionsUsed"] == ["KHR_materials_unlit"] and info["hasTextures"]
    assert (info["drawCallCount"], info["totalTriangleCount"]) == (3, 2 * 80 + 2)
