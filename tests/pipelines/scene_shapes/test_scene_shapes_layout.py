"""Scene layout, planning, the camera convention of the renderer, invisible objects, EGL errors."""

import sys

import numpy as np
import pytest
import torch
import trimesh
from scipy.spatial import ConvexHull

from pipelines.scene_shapes import render
from pipelines.scene_shapes.layout import ObjectPlacement, PlacementConfig, RigConfig, SceneLayout, sample_layout
from pipelines.scene_shapes.plan import PlanConfig, plan_shards, split_counts, split_models
from pipelines.scene_shapes.primitives import BODY
from pipelines.scene_shapes.scene import SceneConfig, SceneUnit, build_scene
from pipelines.scene_shapes.shapes import ShapeModel, procedural_refs
from usl.errors import UslError
from usl.geometry.cameras import project
from usl.records import decode_depth, decode_mask

CATEGORY_IDS = (("chair", 1), ("sofa", 2), ("table", 3))
FRACTIONS = (("train", 0.8), ("val", 0.1), ("test", 0.1))


def test_layouts_follow_the_paper():
    rig, placement = RigConfig(azimuths=6, heights=2, resolution=64), PlacementConfig()
    pools = {c: [r for r in procedural_refs(60) if r.category == c] for c in ("chair", "sofa", "table")}
    rng = np.random.default_rng(0)
    yaws = []
    for _ in range(120):
        layout = sample_layout(rng, pools, rig, placement)
        assert len(layout.objects) == 2
        assert layout.objects[0].model.source_id != layout.objects[1].model.source_id
        for obj in layout.objects:
            assert -0.4 <= obj.x <= 0.4 and 1.5 <= obj.z <= 1.9 and 0 <= obj.yaw < 2 * np.pi
            yaws.append(obj.yaw)
        poses = np.stack(layout.cam_to_world)
        assert len(poses) == 12
        np.testing.assert_allclose(poses[0, [0, 2], 3], 0.0, atol=1e-12)  # camera 0 above the world origin
        np.testing.assert_allclose(poses[:, 1, 3], np.repeat([0.8, 1.8], 6))  # heights, height-major order
        np.testing.assert_allclose(np.hypot(poses[:, 0, 3], poses[:, 2, 3] - 1.7), 1.7)  # on the orbit
        # Every camera looks at the orbit centre: it projects to the image centre.
        target = torch.tensor([0.0, rig.target_height, 1.7], dtype=torch.float64)
        world_to_cam = torch.linalg.inv(torch.as_tensor(poses))
        cam = (world_to_cam[:, :3, :3] @ target + world_to_cam[:, :3, 3])[:, None, :]
        uv, w = project(cam, torch.as_tensor(layout.K))
        np.testing.assert_allclose(uv.squeeze(1).numpy(), 32.0, atol=1e-9)
        assert (w > 0).all()
    assert np.histogram(yaws, bins=4, range=(0, 2 * np.pi))[0].min() > 35  # roughly uniform (60 expected)


def test_split_counts_and_disjoint_models():
    assert split_counts(3600, [0.8, 0.1, 0.1]) == [2880, 360, 360]
    assert split_counts(10, [0.8, 0.1, 0.1]) == [8, 1, 1]
    assert split_counts(3, [0.8, 0.1, 0.1]) == [1, 1, 1]
    assert sum(split_counts(1333, [0.8, 0.1, 0.1])) == 1333
    refs = procedural_refs(300)
    splits = split_models(refs, list(FRACTIONS), seed=4)
    assert sorted(r.source_id for s in splits.values() for r in s) == sorted(r.source_id for r in refs)
    assert len(splits["train"]) == 240 and len(splits["val"]) == 30
    assert split_models(refs, list(FRACTIONS), seed=5)["val"] != splits["val"]


def test_plans_depend_on_the_seed_and_not_on_shard_size():
    config = SceneConfig(RigConfig(azimuths=2, heights=1, resolution=32), CATEGORY_IDS)
    refs = procedural_refs(60)

    def units(seed, per_shard):
        return [u for plan in plan_shards(refs, PlanConfig(20, seed, FRACTIONS, per_shard), config) for u in plan.units]

    a, b, c = units(1, 3), units(1, 7), units(2, 3)
    assert [(u.scene_id, u.appearance_seed, u.layout.objects) for u in a] == [
        (u.scene_id, u.appearance_seed, u.layout.objects) for u in b
    ]
    assert [u.layout.objects for u in a] != [u.layout.objects for u in c]
    train_models = {o.model.source_id for u in a if u.scene_id.startswith("train") for o in u.layout.objects}
    val_models = {o.model.source_id for u in a if u.scene_id.startswith("val") for o in u.layout.objects}
    assert not train_models & val_models


def box_model(size):
    box = trimesh.creation.box(extents=size)
    box.apply_translation([0.0, size[1] / 2, 0.0])
    return ShapeModel("box", "table", box.vertices, box.faces, np.full(len(box.vertices), BODY, np.uint8))


def test_mask_matches_the_analytic_projection_of_a_convex_box():
    """Pixel-centre coverage of a convex box must have the area and centroid of the exact projected
    polygon (usl.geometry.cameras.project + convex hull): catches half-pixel and axis-flip errors."""
    rig, placement = RigConfig(azimuths=3, heights=2, resolution=160, fov_deg=50.0), PlacementConfig()
    layout = sample_layout(np.random.default_rng(3), {"table": procedural_refs(3)[2:]}, rig, placement)
    model = box_model([0.6, 0.5, 0.3])
    transform = ObjectPlacement(1, layout.objects[0].model, 0.7, 0.1, 1.7).world_from_object()
    views = render.render_scene(
        [render.PlacedModel(model, transform)],
        layout.K,
        list(layout.cam_to_world),
        rig.resolution,
        "floor",
        np.random.default_rng(0),
    )
    world = model.vertices @ transform[:3, :3].T + transform[:3, 3]
    for view, pose in zip(views, layout.cam_to_world, strict=True):
        cam = (world - pose[:3, 3]) @ pose[:3, :3]
        uv, _ = project(torch.as_tensor(cam), torch.as_tensor(layout.K))
        polygon = uv.numpy()[ConvexHull(uv.numpy()).vertices]
        x, y = polygon[:, 0], polygon[:, 1]
        cross = x * np.roll(y, -1) - np.roll(x, -1) * y
        area = cross.sum() / 2
        centroid = np.array([((x + np.roll(x, -1)) * cross).sum(), ((y + np.roll(y, -1)) * cross).sum()]) / (6 * area)
        rows, cols = np.nonzero(view.instance_index == 1)
        assert len(rows) == pytest.approx(abs(area), rel=0.01)
        np.testing.assert_allclose([cols.mean() + 0.5, rows.mean() + 0.5], centroid, atol=0.1)


def test_hidden_objects_are_absent_from_instances_but_kept_as_objects():
    rig = RigConfig(azimuths=2, heights=1, resolution=48)
    refs = procedural_refs(3)
    layout = sample_layout(np.random.default_rng(0), {"chair": refs[:1]}, rig, PlacementConfig())
    objects = (ObjectPlacement(1, refs[0], 0.3, 0.0, 1.7), ObjectPlacement(2, refs[1], 0.0, 0.0, -40.0))  # behind
    config = SceneConfig(rig, CATEGORY_IDS, background="plain")
    record = build_scene(SceneUnit("s", SceneLayout(objects, layout.cam_to_world[:1], layout.K), 1, config))
    assert [i["instance_id"] for i in record.frames[0]["instances"]] == [1]
    mask = decode_mask(record.frames[0]["instances"][0]["mask"])
    assert [o["instance_id"] for o in record.objects] == [1, 2]
    depth = decode_depth(record.frames[0]["depth"])  # plain background: depth only on the object
    assert mask.any() and np.isfinite(depth[mask]).all() and np.isnan(depth[~mask]).all()


def test_missing_egl_gives_the_install_hint(monkeypatch):
    monkeypatch.setattr(render, "_RENDERERS", {})
    monkeypatch.setitem(sys.modules, "pyrender", None)  # what a failing libEGL import looks like
    with pytest.raises(UslError, match="install libegl1 and libgl1-mesa-dri .* PYOPENGL_PLATFORM=egl"):
        render.check_offscreen_rendering(16)


def test_failing_context_gives_the_install_hint(monkeypatch):
    import pyrender

    def no_display(*args, **kwargs):
        raise RuntimeError("eglInitialize failed")

    monkeypatch.setattr(render, "_RENDERERS", {})
    monkeypatch.setattr(pyrender, "OffscreenRenderer", no_display)
    with pytest.raises(UslError, match="eglInitialize failed.*libegl1"):
        render.check_offscreen_rendering(16)


@pytest.mark.parametrize(
    "argv,message",
    [
        (["--views", "7", "--heights", "3"], "--views 7 is not a positive multiple of --heights 3"),
        (["--category-map", "map.yaml"], "--category-map needs --mesh-root"),
        (["--z-range", "1.9", "1.5"], "need ascending ranges"),
        (["--num-models", "2"], "fewer than the 3 categories"),
    ],
)
def test_bad_arguments_are_one_line_errors(tmp_path, capsys, argv, message):
    from pipelines.scene_shapes.cli import main

    assert main(["--out", str(tmp_path / "out"), "--quiet", *argv]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1
    assert not (tmp_path / "out").exists()
