"""Sphere baselines: the spec's z / rho, spheres that fill each object frustum, oracle depth."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from data_specs import load_dataset_spec
from usl.data.frames import FrameData
from usl.evaluation.baselines import FixedDepthBaseline, LayoutOnly, RandomDepthBaseline, TrueDepth, spec_baselines
from usl.evaluation.types import EvalInput, TrueMesh

K = np.array([[300.0, 0.0, 160.0], [0.0, 280.0, 120.0], [0.0, 0.0, 1.0]])


def make_input(view_id: int = 0, num_objects: int = 3, with_meshes: bool = True) -> EvalInput:
    rng = np.random.default_rng(view_id)
    boxes = []
    for _ in range(num_objects):
        x0, y0 = rng.uniform(10, 200), rng.uniform(10, 150)
        boxes.append([x0, y0, x0 + rng.uniform(20, 100), y0 + rng.uniform(20, 80)])
    frame = FrameData(
        scene_id="s",
        view_id=view_id,
        image=torch.zeros(3, 240, 320),
        K=torch.tensor(K, dtype=torch.float32),
        cam_to_world=torch.eye(4, dtype=torch.float64),
        instance_ids=torch.arange(num_objects) + 5,
        labels=torch.zeros(num_objects, dtype=torch.int64),
        boxes=torch.tensor(boxes, dtype=torch.float32),
        masks=torch.zeros(num_objects, 240, 320, dtype=torch.bool),
        depth_min=torch.tensor(rng.uniform(1.0, 3.0, num_objects), dtype=torch.float32),
    )
    meshes = {}
    if with_meshes:
        for n in range(num_objects):
            verts = torch.tensor(rng.normal(size=(50, 3)) * 0.2 + [0.0, 0.0, 2.0 + n], dtype=torch.float32)
            meshes[int(frame.instance_ids[n])] = TrueMesh(verts, torch.tensor([[0, 1, 2]]))
    return EvalInput(frame, meshes)


def projected_box(verts: torch.Tensor) -> np.ndarray:
    h = verts.double().numpy() @ K.T
    uv = h[..., :2] / h[..., 2:]
    return np.concatenate([uv.min(-2), uv.max(-2)], -1)


def homogeneous_depth(verts: torch.Tensor) -> np.ndarray:
    return verts.double().numpy() @ K[2]


def test_fixed_depth_spheres_fill_their_frustum():
    inp = make_input()
    pred = FixedDepthBaseline(z=1.7, rho=1.0)([inp])[0]
    assert torch.equal(pred.instance_ids, inp.frame.instance_ids)
    assert torch.all(pred.z == 1.7) and torch.all(pred.rho == 1.0)
    # Silhouette inscribed in the true 2D box: touches it (within the ico-sphere's faceting).
    box, true = projected_box(pred.verts), inp.frame.boxes.numpy()
    assert np.all(box[:, :2] >= true[:, :2] - 1e-3) and np.all(box[:, 2:] <= true[:, 2:] + 1e-3)
    size, true_size = box[:, 2:] - box[:, :2], true[:, 2:] - true[:, :2]
    assert np.all(size > 0.97 * true_size)
    # Depth spans the frustum [z - rho/2, z + rho/2].
    depth = homogeneous_depth(pred.verts)
    assert np.all(depth.min(1) >= 1.2 - 1e-4) and np.all(depth.max(1) <= 2.2 + 1e-4)
    assert np.all(depth.min(1) < 1.22) and np.all(depth.max(1) > 2.17)


def test_random_depth_is_in_range_deterministic_and_varies():
    baseline = RandomDepthBaseline((1.4, 2.0), (0.1, 1.0), seed=3)
    many = [make_input(view_id=v, num_objects=20, with_meshes=False) for v in range(10)]
    preds = baseline(many)
    z = torch.cat([p.z for p in preds])
    rho = torch.cat([p.rho for p in preds])
    assert z.min() >= 1.4 and z.max() <= 2.0 and rho.min() >= 0.1 and rho.max() <= 1.0
    assert z.min() < 1.45 and z.max() > 1.95 and rho.min() < 0.2 and rho.max() > 0.9  # covers the range
    again = baseline([many[4]])[0]
    assert torch.equal(again.z, preds[4].z) and torch.equal(again.verts, preds[4].verts)
    assert not torch.equal(preds[0].z, preds[1].z[:20])
    assert not torch.equal(RandomDepthBaseline((1.4, 2.0), (0.1, 1.0), seed=4)([many[0]])[0].z, preds[0].z)


def test_spec_baselines_use_data_specs():
    hypersim = spec_baselines(load_dataset_spec("hypersim")["baselines"])
    assert (hypersim["fixed"].z, hypersim["fixed"].rho) == (5.0, 0.5)
    assert hypersim["random"].z_range == (1.0, 10.0) and hypersim["random"].rho_range == (0.1, 1.0)
    scene_shapes = spec_baselines(load_dataset_spec("scene_shapes")["baselines"])
    assert (scene_shapes["fixed"].z, scene_shapes["fixed"].rho) == (1.7, 1.0)


def test_layout_only_keeps_layout_and_drops_shape():
    inp = make_input()
    inner = RandomDepthBaseline((1.0, 3.0), (0.2, 0.8))
    inner_pred = inner([inp])[0]
    squashed = inner_pred.verts * torch.tensor([1.0, 0.5, 1.0])  # any non-sphere shape

    class Shaped:
        name, predicts_layout, predicts_shape, uses_detections = "shaped", True, True, False

        def __call__(self, inputs):
            return [type(inner_pred)(**{**inner_pred.__dict__, "verts": squashed})]

    pred = LayoutOnly(Shaped())([inp])[0]
    assert torch.equal(pred.z, inner_pred.z) and torch.equal(pred.rho, inner_pred.rho)
    assert torch.allclose(pred.verts, inner_pred.verts, atol=1e-5)
    assert LayoutOnly(Shaped()).name == "Layout-only (shaped)"


def test_true_depth_moves_objects_to_the_true_centre_or_nearest_depth():
    inp = make_input()
    sphere = FixedDepthBaseline(z=5.0, rho=0.6)
    centre = TrueDepth(sphere, "centre")([inp])[0]
    for n, iid in enumerate(inp.frame.instance_ids.tolist()):
        d = homogeneous_depth(inp.true_meshes[iid].verts)
        assert float(centre.z[n]) == pytest.approx(0.5 * (d.min() + d.max()), rel=1e-5)
        moved = homogeneous_depth(centre.verts[n])
        assert 0.5 * (moved.min() + moved.max()) == pytest.approx(0.5 * (d.min() + d.max()), rel=0.02)
    np.testing.assert_allclose(projected_box(centre.verts), projected_box(sphere([inp])[0].verts), atol=1e-3)
    nearest = TrueDepth(sphere, "nearest")([inp])[0]
    assert torch.allclose(nearest.z, inp.frame.depth_min + 0.3)
    no_meshes = make_input(with_meshes=False)
    auto = TrueDepth(sphere, "auto")([no_meshes])[0]
    assert torch.allclose(auto.z, no_meshes.frame.depth_min + 0.3)
    with pytest.raises(ValueError, match="source"):
        TrueDepth(sphere, "median")


def test_true_layout_also_gives_each_object_its_true_depth_extent():
    inp = make_input()
    sphere = FixedDepthBaseline(z=5.0, rho=0.6)
    layout = TrueDepth(sphere, "centre", extent=True)
    assert layout.name == f"{sphere.name} w/ true depth and extent"
    pred = layout([inp])[0]
    for n, iid in enumerate(inp.frame.instance_ids.tolist()):
        d = homogeneous_depth(inp.true_meshes[iid].verts)
        assert float(pred.rho[n]) == pytest.approx(d.max() - d.min(), rel=1e-5)
        moved = homogeneous_depth(pred.verts[n])  # the sphere now spans the true mesh's depth range
        assert moved.min() == pytest.approx(d.min(), rel=0.02) and moved.max() == pytest.approx(d.max(), rel=0.02)
    np.testing.assert_allclose(projected_box(pred.verts), projected_box(sphere([inp])[0].verts), atol=1e-3)
    no_meshes = make_input(with_meshes=False)  # no true mesh: the inner extent stays
    assert torch.allclose(TrueDepth(sphere, "auto", extent=True)([no_meshes])[0].rho, torch.tensor(0.6))
