"""``loss.supervision=3d``: Mesh R-CNN's losses against the objects table's true meshes."""

import json
import shutil
from dataclasses import replace

import pytest
import torch

from tests.model.test_usl_model import _true_meshes  # an independent camera-frame cast
from usl.config import load_config
from usl.data import CategoryIndex, MultiViewDataset, SampleKey
from usl.errors import UslError
from usl.model.config import LayoutRange
from usl.model.mesh3d_loss import MESH_RCNN_SHAPENET, mesh_supervision_loss
from usl.model.usl_model import USLModel
from usl.records import RecordsDataset


@pytest.fixture(scope="module")
def setup(synthetic_root):
    cfg = load_config(
        "tiny",
        [
            f"data.root={synthetic_root}",
            "data.max_size=0",
            "loss.supervision=3d",
            "data.flip_prob=0",
        ],
    )
    records = RecordsDataset(synthetic_root, "train")
    cfg.model.categories = tuple(c["name"] for c in records.categories)
    cfg.model.layout_range = LayoutRange(**records.manifest["layout"])
    categories = CategoryIndex(records.categories)
    return cfg, records, MultiViewDataset(records, cfg.data, categories, seed=0, with_true_meshes=True), categories


def test_samples_carry_the_true_meshes_in_the_input_camera_only_when_asked(setup):
    cfg, records, dataset, categories = setup
    sample = dataset[SampleKey(3, 0)]
    verts, faces = _true_meshes(records, dataset, sample, 3)
    assert len(sample.true_meshes) == len(sample.object_rows) == len(verts)
    for mesh, expected in zip(sample.true_meshes, verts, strict=True):
        torch.testing.assert_close(mesh.verts, expected, atol=1e-5, rtol=0)
        assert torch.equal(mesh.faces, faces)
    assert MultiViewDataset(records, cfg.data, categories, seed=0)[SampleKey(3, 0)].true_meshes is None


def test_true_mesh_scores_zero_and_descent_moves_shape_and_layout_to_it(setup):
    cfg, records, dataset, _ = setup
    samples = [dataset[SampleKey(i, 0)] for i in (0, 5)]
    truth = [_true_meshes(records, dataset, s, i) for s, i in zip(samples, (0, 5), strict=True)]
    faces = truth[0][1]
    verts = torch.cat([v for v, _ in truth])
    counts = [len(v) for v, _ in truth]
    mesh3d = replace(MESH_RCNN_SHAPENET, normals=0.1, num_samples=500)
    # a wrong depth (a scale about the camera) and a squashed shape
    centre = verts.mean(dim=1, keepdim=True)
    start = 1.25 * (centre + (verts - centre) * torch.tensor([1.0, 0.5, 1.0]))
    _, wrong = mesh_supervision_loss([start], faces, samples, counts, mesh3d)
    _, exact = mesh_supervision_loss([verts, verts], faces, samples, counts, mesh3d)
    # the true mesh: only the two point samplings differ (500 points on each; near a cuboid's edges
    # a point's nearest neighbour may lie on the adjoining face, so the normal term stays above 0)
    assert exact["chamfer3d"] < 0.02 * wrong["chamfer3d"] and exact["normals3d"] < 0.25 * wrong["normals3d"]
    pred = start.clone().requires_grad_(True)
    optimizer = torch.optim.Adam([pred], lr=0.03)
    losses, chamfers = [], []
    for _ in range(25):
        optimizer.zero_grad()
        loss, stats = mesh_supervision_loss([pred], faces, samples, counts, mesh3d)
        loss.backward()
        optimizer.step()
        losses.append(loss.item())
        chamfers.append(stats["chamfer3d"].item())
    assert losses[-1] < 0.5 * losses[0] and chamfers[-1] < 0.25 * chamfers[0]
    depth_error = lambda v: (v[..., 2].mean(1) - verts[..., 2].mean(1)).abs().mean().item()  # noqa: E731
    assert depth_error(pred.detach()) < 0.5 * depth_error(start)


def test_model_trains_every_3d_head_from_the_3d_loss(setup):
    cfg, _, dataset, _ = setup
    torch.manual_seed(0)
    model = USLModel(cfg.model, cfg.loss)
    losses = model([dataset[SampleKey(i, 0)] for i in (0, 3)])
    assert {"stat/chamfer3d", "stat/normals3d", "stat/edge3d"} <= set(losses) and "stat/l_xent" not in losses
    losses["loss"].backward()
    for module in (model.layout_head, model.shape_head):
        assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in module.parameters()), type(module).__name__


def test_3d_supervision_needs_an_objects_table_and_a_mesh_per_object(setup, tmp_path, synthetic_root):
    cfg, _, _, categories = setup
    no_objects = shutil.copytree(synthetic_root, tmp_path / "no_objects")
    manifest = json.loads((no_objects / "manifest.json").read_text())
    for shard in manifest["splits"]["train"]["shards"]:
        shard["objects"] = None  # as a Hypersim or ScanNet build
    (no_objects / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(UslError, match="no objects table.*loss.supervision=3d"):
        MultiViewDataset(RecordsDataset(no_objects, "train"), cfg.data, categories, with_true_meshes=True)
    records = RecordsDataset(synthetic_root, "train")
    dataset = MultiViewDataset(records, cfg.data, categories, with_true_meshes=True)
    scene_id = dataset.items[0][0]
    records.read_objects = lambda s: [
        o for o in RecordsDataset(synthetic_root, "train").read_objects(s) if o["instance_id"] != 2
    ]
    with pytest.raises(UslError, match=f"scene '{scene_id}': instance 2 has no row in the objects table"):
        dataset[SampleKey(0, 0)]
