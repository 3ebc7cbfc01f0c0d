"""The full model and its multi-view loss on geometrically exact synthetic scenes."""

from dataclasses import replace

import numpy as np
import pytest
import torch

from usl.data import SampleKey
from usl.geometry.cameras import project, transform_points
from usl.losses import PiecewiseLinear
from usl.model.heads import roimap_features
from usl.model.multiview_loss import multiview_silhouette_loss
from usl.model.outputs import ObjectPredictions
from usl.model.usl_model import USLModel


@pytest.fixture(scope="module")
def setup(tiny_synthetic):
    return tiny_synthetic


def _true_meshes(records, dataset, sample, index):
    """The sample's true cuboids in its input camera frame, (N, 8, 3), and their shared faces."""
    scene_id, _ = dataset.items[index]
    objects = {o["instance_id"]: o for o in records.read_objects(scene_id)}
    to_input = torch.linalg.inv(sample.views[0].cam_to_world)
    ids = sample.frame.instance_ids[sample.object_rows].tolist()
    verts = torch.stack(
        [transform_points(torch.tensor(np.asarray(objects[i]["vertices"]), dtype=torch.float64), to_input) for i in ids]
    )
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
        dist = {
            s: multiview_silhouette_loss(verts * s, faces, [sample], counts, cfg.loss).stats["l_dist"]
            for s in (0.8, 1.0, 1.3)
        }
        assert dist[1.0] < 0.5 * dist[1.3] and dist[1.0] < 0.5 * dist[0.8]
        assert (
            multiview_silhouette_loss(verts, faces, [sample], counts, cfg.loss).stats["xent_gate"] > 0.6
        )  # occlusion lowers some IoUs
        only_input = replace(sample, views=sample.views[:1])
        a = multiview_silhouette_loss(verts, faces, [only_input], counts, cfg.loss).l3d
        b = multiview_silhouette_loss(verts * 1.3, faces, [only_input], counts, cfg.loss).l3d
        assert torch.isclose(a, b, rtol=0.05)  # the input view alone cannot see depth


def test_loss_is_a_per_image_mean_and_ignores_absent_objects(setup):
    cfg, records, dataset = setup
    samples = [dataset[SampleKey(i, 0)] for i in (1, 14)]
    meshes = [_true_meshes(records, dataset, s, i) for s, i in zip(samples, (1, 14), strict=True)]
    faces = meshes[0][1]
    verts = [m[0] * 1.1 for m in meshes]
    single = [
        multiview_silhouette_loss(v, faces, [s], [len(v)], cfg.loss).l3d for v, s in zip(verts, samples, strict=True)
    ]
    batch = multiview_silhouette_loss(torch.cat(verts), faces, samples, [len(v) for v in verts], cfg.loss).l3d
    assert torch.isclose(batch, 0.5 * (single[0] + single[1]), rtol=1e-5)
    # an object marked absent in a view contributes nothing there, whatever its mask says
    view = samples[0].views[1]
    absent = replace(view, present=torch.tensor([False, True]), masks=view.masks.clone())
    garbage = replace(absent, masks=torch.ones_like(view.masks))
    garbage.masks[1] = view.masks[1]
    losses = [
        multiview_silhouette_loss(
            verts[0], faces, [replace(samples[0], views=[samples[0].views[0], v])], [2], cfg.loss
        ).l3d
        for v in (absent, garbage)
    ]
    assert torch.isclose(losses[0], losses[1])


def test_forward_losses_and_gradients(setup):
    cfg, _, dataset = setup
    torch.manual_seed(0)
    model = USLModel(cfg.model, cfg.loss)
    samples = [dataset[SampleKey(i, 0)] for i in (0, 3)]
    losses = model(samples)
    expected = {
        "det/loss_rpn_cls",
        "det/loss_rpn_loc",
        "det/loss_cls",
        "det/loss_box_reg",
        "det/loss_mask",
        "l3d",
        "edge",
        "loss",
    }
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
    empty = replace(
        sample,
        object_rows=sample.object_rows[:0],
        views=[replace(v, masks=v.masks[:0], present=v.present[:0]) for v in sample.views],
    )
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
    for frame, pred in zip(frames, predictions, strict=True):
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


def test_dist_schedule_scales_exactly_the_l_dist_part(setup):
    cfg, records, dataset = setup
    sample = dataset[SampleKey(0, 0)]
    verts, faces = _true_meshes(records, dataset, sample, 0)
    verts = verts * 1.2  # a depth error, so l_dist is not ~0
    plain = multiview_silhouette_loss(verts, faces, [sample], [len(verts)], cfg.loss)
    scheduled_cfg = replace(cfg.loss, dist_schedule=PiecewiseLinear(iters=(0, 100), values=(1.0, 0.25)))
    for iteration, factor in ((0, 1.0), (50, 0.625), (400, 0.25)):
        out = multiview_silhouette_loss(verts, faces, [sample], [len(verts)], scheduled_cfg, iteration)
        torch.testing.assert_close(out.dist, factor * plain.dist)
        torch.testing.assert_close(out.xent, plain.xent)
        torch.testing.assert_close(out.l3d, out.dist + out.xent)
        assert out.stats["dist_factor"].item() == pytest.approx(factor * cfg.loss.dist_scale)


def test_gate_input_view_false_applies_l_xent_in_the_input_view_only(setup):
    cfg, records, dataset = setup
    sample = dataset[SampleKey(0, 0)]
    verts, faces = _true_meshes(records, dataset, sample, 0)
    centre = verts.mean(dim=1, keepdim=True)
    shrunk = centre + 0.4 * (verts - centre)  # input-view IoU ~0.16: the paper's gate keeps it out
    only_input = replace(sample, views=sample.views[:1])
    paper, ungated = (replace(cfg.loss, gate_input_view=g, ignore_occluders=False) for g in (True, False))
    counts = [len(verts)]
    assert multiview_silhouette_loss(shrunk, faces, [only_input], counts, paper).xent.item() == 0.0
    opened = multiview_silhouette_loss(shrunk, faces, [only_input], counts, ungated)
    assert opened.xent.item() > 0 and opened.stats["xent_gate"].item() == 1.0
    # the other views keep the gate: their pairs' gate fraction is the same either way
    full = [multiview_silhouette_loss(shrunk, faces, [sample], counts, c).stats["xent_gate"] for c in (paper, ungated)]
    input_share = counts[0] / sum(int(v.present.sum()) for v in sample.views)
    assert full[1].item() == pytest.approx(full[0].item() + input_share)


def test_ignore_occluders_scores_true_meshes_as_perfect_despite_occlusion(setup):
    """True masks show visible parts only, so a true (amodal) mesh seems wrong wherever another
    object hides it; with ``ignore_occluders`` those cells are unobserved and every pair passes the gate."""
    cfg, records, dataset = setup
    for index in (0, 9):
        sample = dataset[SampleKey(index, 0)]
        verts, faces = _true_meshes(records, dataset, sample, index)
        plain, aware = (
            multiview_silhouette_loss(verts, faces, [sample], [len(verts)], replace(cfg.loss, ignore_occluders=ignore))
            for ignore in (False, True)
        )
        assert aware.stats["xent_gate"].item() == 1.0
        assert aware.stats["l_xent"] < plain.stats["l_xent"]
        torch.testing.assert_close(aware.dist, plain.dist)  # l_dist is unchanged


def test_gradient_diagnostics_observe_without_changing_the_step(setup):
    cfg, _, dataset = setup
    samples = [dataset[SampleKey(i, 0)] for i in (0, 3)]
    grads = []
    for diagnostics in (False, True):
        torch.manual_seed(0)
        model = USLModel(cfg.model, replace(cfg.loss, gate_input_view=False))
        losses = model(samples, diagnostics=diagnostics)
        losses["loss"].backward()
        grads.append([p.grad.clone() for p in model.shape_head.parameters() if p.grad is not None])
        if diagnostics:
            assert losses["stat/grad_dist"] > 0 and losses["stat/grad_xent"] > 0
            torch.testing.assert_close(losses["stat/grad_ratio"], losses["stat/grad_dist"] / losses["stat/grad_xent"])
        else:
            assert "stat/grad_dist" not in losses
    assert all(torch.equal(a, b) for a, b in zip(*grads, strict=True))
    torch.manual_seed(0)
    no_dist = USLModel(cfg.model, replace(cfg.loss, dist_schedule=PiecewiseLinear(iters=(0,), values=(0.0,))))
    assert no_dist(samples, diagnostics=True)["stat/grad_dist"].item() == 0.0


def test_shape_head_can_sample_the_input_image_itself(setup):
    """``model.shape.features=[p2, image]`` (tiny's): the normalised input image is a 3-channel map at
    stride 1, so a vertex projecting onto a pixel centre reads exactly that pixel's colour."""
    cfg, _, dataset = setup
    shape_cfg = cfg.model.shape
    assert shape_cfg.features == ("p2", "image")  # tiny's
    frame = dataset[SampleKey(0, 0)].frame
    model = USLModel(cfg.model, cfg.loss)
    _, features = model._backbone([frame])
    height, width = frame.size
    normalised = (frame.image - model.pixel_mean) / model.pixel_std
    assert torch.allclose(features["image"][0, :, :height, :width], normalised)
    assert model.shape_head.strides == [4, 1]
    assert model.shape_head.stages[0].bottleneck.in_features == features["p2"].shape[1] + 3
    # cube points whose projections are pixel centres inside the first object's box
    box = frame.boxes[0]
    cols = torch.arange(int(box[0]) + 1, int(box[2]) - 1)
    rows = torch.full_like(cols, int((box[1] + box[3]) / 2))
    x = 2 * (cols + 0.5 - box[0]) / (box[2] - box[0]) - 1
    y = 2 * (rows + 0.5 - box[1]) / (box[3] - box[1]) - 1
    verts = torch.stack([x, y, torch.zeros_like(x)], dim=-1)[None]
    sampled = roimap_features(
        [features[name] for name in shape_cfg.features], model.shape_head.strides, verts, box[None], torch.tensor([0])
    )
    torch.testing.assert_close(sampled[0, :, -3:], normalised[:, rows, cols].T, atol=1e-5, rtol=0)
    # without it, the features the detector and the heads see are the backbone's alone
    backbone_only = replace(cfg.model, shape=replace(cfg.model.shape, features=("p2",)))
    assert "image" not in USLModel(backbone_only, cfg.loss)._backbone([frame])[1]
