"""The full model and its multi-view loss on geometrically exact synthetic scenes."""
from dataclasses import replace

import numpy as np
import pytest
import torch

from usl.config import LayoutRange, load_config
from usl.data import CategoryIndex, MultiViewDataset, SampleKey
from usl.geometry.cameras import project, transform_points
from usl.model.multiview_loss import multiview_silhouette_loss
from usl.model.outputs import ObjectPredictions
from usl.model.usl_model import USLModel
from usl.records import RecordsDataset


@pytest.fixture(scope="module")
def setup(synthetic_root):
    cfg = load_config("tiny", [f"data.root={synthetic_root}", "data.num_views=4", "data.max_size=0"])
    records = RecordsDataset(synthetic_root, "train")
    cfg.model.categories = tuple(c["name"] for c in records.categories)
    cfg.model.layout_range = LayoutRange(**records.manifest["layout"])
    dataset = MultiViewDataset(records, cfg.data, CategoryIndex(records.categories), seed=0)
    return cfg, records, dataset


def _true_meshes(records, dataset, sample, index):
    """The sample's true cuboids in its input camera frame, (N, 8, 3), and their shared faces."""
    scene_id, _ = dataset.items[index]
    objects = {o["instance_id"]: o for o in records.read_objects(scene_id)}
    to_input = torch.linalg.inv(sample.views[0].cam_to_world)
    ids = sample.frame.instance_ids[sample.object_rows].tolist()
    verts = torch.stack([transform_points(torch.tensor(np.asarray(objects[i]["vertices"]), dtype=torch.float64), to_input) for i in ids])
    return verts.float(), torch.tensor(np.asarray(objects[ids[0]]["faces"]), dtype=torch.int64)


def test_true_depth_beats_a_depth_error_only_other_views_can_see(setup):
    """Scaling meshes about the input camera keeps their input-view silhouette: l_dist must still
    prefer the true depth, which proves the R_{1->j} casting into the other views.

    (Total L_3D values are not comparable across the IoU gate: l_xent switches on above IoU 0.5.)
    """
    cfg, records, dataset = setup
    for index in (0, 9):
        sample = dataset[SampleKey(index, 0)]
        verts, faces = _true_meshes(records, dataset, sample, index)
        counts = [len(verts)]
        dist = {s: multiview_silhouette_loss(verts * s, faces, [sample], counts, cfg.loss)[1]["l_dist"] for s in (0.8, 1.0, 1.3)}
        assert dist[1.0] < 0.5 * dist[1.3] and dist[1.0] < 0.5 * dist[0.8]
        assert multiview_silhouette_loss(verts, faces, [sample], counts, cfg.loss)[1]["xent_gate"] > 0.6  # occlusion lowers some IoUs
        only_input = replace(sample, views=sample.views[:1])
        a = multiview_silhouette_loss(verts, faces, [only_input], counts, cfg.loss)[0]
        b = multiview_silhouette_loss(verts * 1.3, faces, [only_input], counts, cfg.loss)[0]
        assert torch.isclose(a, b, rtol=0.05)  # the input view alone cannot see depth


def test_loss_is_a_per_image_mean_and_ignores_absent_objects(setup):
    cfg, records, dataset = setup
    samples = [dataset[SampleKey(i, 0)] for i in (1, 14)]
    meshes = [_true_meshes(records, dataset, s, i) for s, i in zip(samples, (1, 14))]
    faces = meshes[0][1]
    verts = [m[0] * 1.1 for m in meshes]
    single = [multiview_silhouette_loss(v, faces, [s], [len(v)], cfg.loss)[0] for v, s in zip(verts, samples)]
    batch, _ = multiview_silhouette_loss(torch.cat(verts), faces, samples, [len(v) for v in verts], cfg.loss)
    assert torch.isclose(batch, 0.5 * (single[0] + single[1]), rtol=1e-5)
    # an object marked absent in a view contributes nothing there, whatever its mask says
    view = samples[0].views[1]
    absent = replace(view, present=torch.tensor([False, True]), masks=view.masks.clone())
    garbage = replace(absent, masks=torch.ones_like(view.masks))
    garbage.masks[1] = view.masks[1]
    losses = [
        multiview_silhouette_loss(verts[0], faces, [replace(samples[0], views=[samples[0].views[0], v])], [2], cfg.loss)[0]
        for v in (absent, garbage)
    ]
    assert torch.isclose(losses[0], losses[1])


def test_forward_losses_and_gradients(setup):
    cfg, _, dataset = setup
    torch.manual_seed(0)
    model = USLModel(cfg.model, cfg.loss)
    samples = [dataset[SampleKey(i, 0)] for i in (0, 3)]
    losses = model(samples)
    expected = {"det/loss_rpn_cls", "det/loss_rpn_loc", "det/loss_cls", "det/loss_box_reg", "det/loss_mask", "l3d", "edge", "loss"}
    assert expected <= set(losses)
    assert all(torch.isfinite(v) for v in losses.values())
    parts = sum(v for k, v in losses.items() if not k.startswith("stat/") and k != "loss")
    assert torch.isclose(losses["loss"], parts)
    losses["loss"].backward()
    for module in (model.layout_head, model.shape_head, model.detector.backbone.bottom_up, model.detector.roi_heads):
        grads = [p.grad for p in module.parameters() if p.requires_grad]
        assert any(g is not None and g.abs().sum() > 0 for g in grads), type(module).__name__


def test_sample_without_objects_still_trains_every_head(setup):
    cfg, _, dataset = setup
    model = USLModel(cfg.model, cfg.loss)
    sample = dataset[SampleKey(2, 0)]
    empty = replace(sample, object_rows=sample.object_rows[:0],
                    views=[replace(v, masks=v.masks[:0], present=v.present[:0]) for v in sample.views])
    losses = model([empty])
    assert losses["l3d"].item() == 0.0
    losses["loss"].backward()
    assert all(p.grad is not None for p in model.layout_head.parameters())  # zero, but present for DDP


def test_predict_casts_meshes_into_the_object_frustum(setup):
    cfg, _, dataset = setup
    model = USLModel(cfg.model, cfg.loss)
    frames = [dataset[SampleKey(i, 0)].frame for i in (0, 5)]
    predictions = model.predict(frames, mode="gt_boxes")
    assert model.training  # predict restores the mode it found
    for frame, pred in zip(frames, predictions):
        assert isinstance(pred, ObjectPredictions) and len(pred) == len(frame.boxes)
        assert torch.equal(pred.instance_ids, frame.instance_ids) and torch.equal(pred.labels, frame.labels)
        assert pred.verts.shape == (len(frame.boxes), 162, 3) and pred.faces.shape == (320, 3)
        # a fresh shape head outputs the unit sphere: it projects inside its box, and nearly fills it,
        # and its depths lie between the frustum's near and far planes
        uv, depth = project(pred.verts, frame.K)
        lo, hi = uv.amin(1), uv.amax(1)
        assert torch.all(lo >= frame.boxes[:, :2] - 1e-3) and torch.all(hi <= frame.boxes[:, 2:] + 1e-3)
        assert torch.all((hi - lo) > 0.95 * (frame.boxes[:, 2:] - frame.boxes[:, :2]))
        assert torch.all(depth >= (pred.z - pred.rho / 2)[:, None] - 1e-4)
        assert torch.all(depth <= (pred.z + pred.rho / 2)[:, None] + 1e-4)
    detections = model.predict(frames, mode="detections")
    for pred in detections:
        assert pred.verts.shape[1:] == (162, 3) and torch.all(pred.instance_ids == -1)
        assert torch.all((pred.scores >= 0) & (pred.scores <= 1))
    with pytest.raises(ValueError, match="mode"):
        model.predict(frames, mode="oracle")
