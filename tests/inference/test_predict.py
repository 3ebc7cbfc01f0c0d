"""``usl-predict``: glTF files trimesh reads back upright with the input camera, image plane and extras;
OBJ/PLY/HTML, overlays, the no-detection line and one-line errors for bad paths."""

from __future__ import annotations

import json
import re

import cv2
import numpy as np
import pytest
import torch
import trimesh

from tests.evaluation.eval_helpers import tiny_checkpoint
from usl.cli.predict import main
from usl.data.frames import CategoryIndex
from usl.errors import UslError
from usl.evaluation.baselines import sphere_verts
from usl.inference.gltf_scene import CAMERA_NODE, IMAGE_NODE
from usl.inference.predict import camera_for, image_frame, model_detector, predict_images, read_image, read_intrinsics
from usl.model.outputs import ObjectPredictions

CATEGORIES = CategoryIndex([{"id": 1, "name": "chair"}, {"id": 2, "name": "sofa"}, {"id": 3, "name": "dining table"}])


def fake_detector(frame):
    """Three spheres in known boxes; the third scores below the default threshold."""
    boxes = torch.tensor([[10.0, 10.0, 40.0, 50.0], [60.0, 20.0, 100.0, 60.0], [0.0, 0.0, 20.0, 20.0]])
    z, rho = torch.tensor([2.0, 3.0, 1.0]), torch.tensor([0.5, 0.8, 0.3])
    verts, faces = sphere_verts(boxes, frame.K, z, rho, level=1)
    return ObjectPredictions(
        boxes=boxes,
        labels=torch.tensor([0, 2, 1]),
        scores=torch.tensor([0.9, 0.7, 0.2]),
        z=z,
        rho=rho,
        verts=verts,
        faces=faces,
        instance_ids=torch.full((3,), -1),
    )


GLTF_FROM_OPENCV = np.array([1.0, -1.0, -1.0])


def test_predict_writes_named_meshes_and_overlay(image_path, tmp_path):
    written = predict_images(
        fake_detector, [image_path], tmp_path, CATEGORIES, fov_deg=60.0, formats=["glb", "obj", "ply", "html"]
    )
    result = written[str(image_path)]
    assert [f.name for f in result.files] == ["room.glb", "room.obj", "room.ply", "room.html", "room_overlay.png"]
    assert result.num_objects == 2 and result.best_score == pytest.approx(0.9)
    scene = trimesh.load(tmp_path / "room.glb")
    assert sorted(scene.geometry) == ["00_chair", "01_dining_table", IMAGE_NODE]  # the 0.2 detection is dropped
    expected = fake_detector(_frame_for_fov(image_path)).verts.double().numpy()
    np.testing.assert_allclose(scene.geometry["00_chair"].vertices, expected[0] * GLTF_FROM_OPENCV, atol=1e-5)
    np.testing.assert_allclose(scene.geometry["01_dining_table"].vertices, expected[1] * GLTF_FROM_OPENCV, atol=1e-5)
    obj = trimesh.load_scene(tmp_path / "room.obj")  # objects only, each its own mesh
    assert sorted(obj.geometry) == ["00_chair", "01_dining_table"]
    np.testing.assert_allclose(obj.geometry["00_chair"].vertices, expected[0] * GLTF_FROM_OPENCV, atol=1e-5)
    assert len(trimesh.load(tmp_path / "room.ply").vertices) == 2 * expected.shape[1]
    page = (tmp_path / "room.html").read_text()
    assert "<html" in page and "$B64GLTF" not in page and 'src="http' not in page  # three.js and the GLB inline
    overlay = cv2.imread(str(tmp_path / "room_overlay.png"))
    assert overlay.shape == (512, 768, 3)  # the 120x80 input drawn at 512 on its short side
    upscaled = cv2.resize(cv2.imread(str(image_path)), (768, 512), interpolation=cv2.INTER_CUBIC)
    assert not np.array_equal(overlay, upscaled)


def test_glb_is_y_up_with_the_input_camera_image_plane_and_extras(image_path, tmp_path):
    predict_images(fake_detector, [image_path], tmp_path, CATEGORIES, fov_deg=60.0)
    scene = trimesh.load(tmp_path / "room.glb")
    K = _frame_for_fov(image_path).K.double().numpy()
    # up axis: the chair's box lies in the image's upper half, so it is above the camera (+Y) and
    # in front of it (-Z), as glTF viewers expect
    centre = scene.geometry["00_chair"].vertices.mean(0)
    assert centre[1] > 0.1 and centre[2] < -1.0
    # camera node: at the origin looking down -Z, with K's vertical field of view and the image's aspect
    assert scene.has_camera and CAMERA_NODE in scene.graph.nodes
    np.testing.assert_allclose(scene.camera_transform, np.eye(4), atol=1e-9)
    yfov = np.radians(scene.camera.fov[1])
    assert 40.0 / np.tan(yfov / 2) == pytest.approx(K[1, 1], rel=1e-6)  # (H / 2) / tan(yfov / 2) = fy
    assert scene.camera.fov[0] / scene.camera.fov[1] == pytest.approx(120 / 80)  # glTF aspectRatio
    # the image plane fills the view: its corners project to the image corners through K
    plane = scene.geometry[IMAGE_NODE]
    corners = plane.vertices * GLTF_FROM_OPENCV  # back to OpenCV axes
    projected = (corners @ K.T)[:, :2] / (corners @ K.T)[:, 2:]
    np.testing.assert_allclose(
        sorted(map(tuple, projected.round(6))), [(0, 0), (0, 80), (120, 0), (120, 80)], atol=1e-4
    )  # float32
    assert corners[:, 2].min() > centre[2] * -1.0  # behind the objects
    assert plane.visual.material.baseColorTexture.size == (120, 80)
    # per-object extras on the nodes
    extras = {
        node: scene.graph.transforms.edge_data[("world", node)].get("metadata")
        for node in ("00_chair", "01_dining_table")
    }
    assert extras["00_chair"]["category"] == "chair" and extras["00_chair"]["score"] == pytest.approx(0.9)
    assert extras["01_dining_table"]["category"] == "dining table" and extras["01_dining_table"]["category_id"] == 3


def _frame_for_fov(image_path):
    image = read_image(image_path)
    return image_frame(image, camera_for(image, None, 60.0, False), "x")


def test_opencv_axes_keep_the_points_and_turn_the_camera(image_path, tmp_path):
    predict_images(fake_detector, [image_path], tmp_path / "gl", CATEGORIES, fov_deg=60.0)
    predict_images(fake_detector, [image_path], tmp_path / "cv", CATEGORIES, fov_deg=60.0, axes="opencv")
    gl, cv = (trimesh.load(tmp_path / d / "room.glb") for d in ("gl", "cv"))
    np.testing.assert_allclose(
        gl.geometry["00_chair"].vertices, cv.geometry["00_chair"].vertices * GLTF_FROM_OPENCV, atol=1e-6
    )
    np.testing.assert_allclose(cv.camera_transform[:3, :3], np.diag(GLTF_FROM_OPENCV), atol=1e-9)


def test_read_intrinsics_formats_and_errors(tmp_path):
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    np.savetxt(tmp_path / "k.txt", K)
    (tmp_path / "k.json").write_text(json.dumps({"K": K.tolist()}))
    (tmp_path / "flat.json").write_text(json.dumps(K.reshape(-1).tolist()))
    for name in ("k.txt", "k.json", "flat.json"):
        np.testing.assert_array_equal(read_intrinsics(tmp_path / name), K)
    (tmp_path / "short.txt").write_text("1 2 3 4")
    with pytest.raises(UslError, match=r"short\.txt: expected 9 numbers"):
        read_intrinsics(tmp_path / "short.txt")
    (tmp_path / "singular.txt").write_text("1 0 0 0 1 0 0 0 0")
    with pytest.raises(UslError, match="singular.txt.*invertible"):
        read_intrinsics(tmp_path / "singular.txt")
    with pytest.raises(UslError, match="nope.txt does not exist"):
        read_intrinsics(tmp_path / "nope.txt")


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    return tiny_checkpoint(tmp_path_factory.mktemp("run"))


def test_cli_with_tiny_checkpoint(image_path, checkpoint, tmp_path, capsys):
    K = np.array([[100.0, 0, 60], [0, 100.0, 40], [0, 0, 1]])
    np.savetxt(tmp_path / "k.txt", K)
    out = tmp_path / "out"
    rc = main(
        [
            str(image_path),
            "--checkpoint",
            str(checkpoint.parent.parent),
            "--K",
            str(tmp_path / "k.txt"),
            "--out",
            str(out),
            "--score-threshold",
            "0.01",
            "--device",
            "cpu",
        ]
    )
    assert rc == 0, capsys.readouterr().err
    assert "room_overlay.png" in capsys.readouterr().out
    rc = main(
        [
            str(image_path),
            "--checkpoint",
            str(checkpoint),
            "--fov",
            "60",
            "--out",
            str(tmp_path / "none"),
            "--score-threshold",
            "1.01",
            "--device",
            "cpu",
        ]
    )
    line = capsys.readouterr().out.strip()
    assert rc == 0 and "no detection scores >= 1.01 (best score 0." in line and "room_overlay.png" in line
    detect, categories = model_detector(checkpoint, "cpu")
    image = read_image(image_path)
    pred = detect(image_frame(image, torch.tensor(K, dtype=torch.float32), "room"))
    kept = int((pred.scores >= 0.01).sum())
    assert kept > 0  # the seeded random model does detect boxes on this image
    scene = trimesh.load(out / "room.glb")
    objects = [name for name in scene.geometry if name != IMAGE_NODE]
    assert len(objects) == kept
    assert all(name.split("_", 1)[1] in {c.replace(" ", "_") for c in categories.names} for name in objects)


@pytest.mark.parametrize(
    "case, message",
    [
        ("checkpoint", "missing.pt does not exist"),
        ("image", "image .*nothere.png does not exist"),
        ("undecodable", "garbage.png could not be decoded"),
        ("k", r"bad_k.txt: expected 9 numbers"),
    ],
)
def test_cli_bad_paths_give_one_line_errors(case, message, image_path, checkpoint, tmp_path, capsys):
    (tmp_path / "garbage.png").write_text("not an image")
    (tmp_path / "bad_k.txt").write_text("1 2")
    checkpoint = str(tmp_path / "missing.pt") if case == "checkpoint" else str(checkpoint)
    image = {"image": str(tmp_path / "nothere.png"), "undecodable": str(tmp_path / "garbage.png")}.get(
        case, str(image_path)
    )
    camera = ["--K", str(tmp_path / "bad_k.txt")] if case == "k" else ["--fov", "60"]
    rc = main([image, "--checkpoint", checkpoint, *camera, "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1
    assert err.startswith("usl-predict: error:")
    assert re.search(message, err), err


def test_glb_camera_keeps_the_full_K_and_fov_auto_warns_without_exif(image_path, checkpoint, tmp_path, capsys):
    K = np.array([[100.0, 0.5, 50.0], [0.0, 110.0, 30.0], [0.0, 0.0, 1.0]])  # off-centre, skewed
    predict_images(fake_detector, [image_path], tmp_path, CATEGORIES, K=K)
    glb = (tmp_path / "room.glb").read_bytes()
    json_length = int.from_bytes(glb[12:16], "little")
    tree = json.loads(glb[20 : 20 + json_length])
    assert tree["cameras"][0]["extras"] == {"K": K.tolist(), "image_size": [120, 80]}
    # the image plane is unlit, in every viewer that knows the extension; the objects are shaded
    unlit = [
        n["name"]
        for n in tree["nodes"]
        for m in _node_materials(tree, n)
        if "KHR_materials_unlit" in m.get("extensions", {})
    ]
    assert unlit == [IMAGE_NODE] and "KHR_materials_unlit" in tree["extensionsUsed"]
    rc = main([str(image_path), "--checkpoint", str(checkpoint), "--fov", "auto", "--out", str(tmp_path / "a")])
    assert rc == 0 and (tmp_path / "a" / "room_overlay.png").is_file()
    assert (
        f"usl-predict: warning: {image_path} has no EXIF FocalLengthIn35mmFilm: assuming a 60 degree horizontal"
        in capsys.readouterr().err
    )


def _node_materials(tree, node):
    primitives = tree["meshes"][node["mesh"]]["primitives"] if "mesh" in node else []
    return [tree["materials"][p["material"]] for p in primitives if "material" in p]


def test_glb_buffer_views_are_marked_as_vertex_data_or_indices(image_path, tmp_path):
    """glTF 2.0's bufferView.target: 34962 (ARRAY_BUFFER) for the views vertex attributes read,
    34963 (ELEMENT_ARRAY_BUFFER) for the views indices read; trimesh writes neither (the Khronos
    validator's hint, checked where it is installed in test_mesh_consumers.py)."""
    predict_images(fake_detector, [image_path], tmp_path, CATEGORIES, fov_deg=60.0)
    glb = (tmp_path / "room.glb").read_bytes()
    tree = json.loads(glb[20 : 20 + int.from_bytes(glb[12:16], "little")])
    views = tree["bufferViews"]
    primitives = [p for mesh in tree["meshes"] for p in mesh["primitives"]]
    attribute_views = {tree["accessors"][a]["bufferView"] for p in primitives for a in p["attributes"].values()}
    index_views = {tree["accessors"][p["indices"]]["bufferView"] for p in primitives if "indices" in p}
    assert len(primitives) >= 3 and attribute_views and index_views and not attribute_views & index_views
    assert all(views[v].get("target") == 34962 for v in attribute_views)
    assert all(views[v].get("target") == 34963 for v in index_views)
