"""Table 1's loss switches: ``loss.weights.dist`` (the "w/o l_dist" row), ``loss.iou_threshold``
(the IoU gate of Eq. 4) and ``loss.xent_gate``, and ``loss.weights.soft_iou``, on geometrically exact synthetic scenes."""

from dataclasses import replace

import pytest
import torch

from tests.model.test_usl_model import _true_meshes  # the samples' true cuboids
from usl.config import ConfigError, load_config
from usl.data import SampleKey
from usl.model.multiview_loss import multiview_silhouette_loss


@pytest.fixture(scope="module")
def setup(tiny_synthetic):
    cfg, records, dataset = tiny_synthetic
    sample = dataset[SampleKey(0, 0)]
    verts, faces = _true_meshes(records, dataset, sample, 0)
    loss = replace(cfg.loss, gate_input_view=True, ignore_occluders=False, dist_schedule=type(cfg.loss.dist_schedule)())
    loss = replace(loss, weights=replace(loss.weights, soft_iou=0.0))  # l_xent alone, as the tests below say
    return loss, sample, verts, faces


def _with(loss, **changes):
    return replace(loss, weights=replace(loss.weights, **changes.pop("weights", {})), **changes)


def _grad(cfg, verts, faces, sample, part="l3d"):
    verts = verts.clone().requires_grad_(True)
    out = multiview_silhouette_loss(verts, faces, [sample], [len(verts)], cfg)
    (grad,) = torch.autograd.grad(getattr(out, part), verts, allow_unused=True)
    return out, torch.zeros_like(verts) if grad is None else grad


def test_dist_weight_scales_l_dist_and_zero_removes_its_gradient_exactly(setup):
    loss, sample, verts, faces = setup
    verts = verts * 1.15  # a depth error: l_dist is far from 0 and has a gradient
    full, full_xent_grad = _grad(_with(loss, xent_gate="iou"), verts, faces, sample, "xent")
    half = multiview_silhouette_loss(
        verts, faces, [sample], [len(verts)], _with(loss, weights={"dist": 0.5}, xent_gate="iou")
    )
    torch.testing.assert_close(half.dist, 0.5 * full.dist)
    torch.testing.assert_close(half.xent, full.xent)
    # dist=0 with the paper's gate kept: L_3D is exactly the gated l_xent part of the full loss
    off, off_grad = _grad(_with(loss, weights={"dist": 0.0}, xent_gate="iou"), verts, faces, sample)
    assert off.dist.item() == 0.0 and "l_dist" not in off.stats
    torch.testing.assert_close(off.l3d, full.xent)
    assert torch.equal(off_grad, full_xent_grad)
    _, dist_grad = _grad(_with(loss, xent_gate="iou"), verts, faces, sample, "dist")
    assert dist_grad.abs().sum() > 0  # so the equality above is not trivial


def test_without_l_dist_the_gate_rewards_leaving_it(setup):
    """Why "w/o l_dist" collapses with the paper's gate: the input view cannot see depth, and a 15%
    depth error already takes every other-view pair below IoU 0.5, where a gated pair costs nothing
    and moves nothing: the gated L_3D is lowest far from the truth and flat there. Ungated
    (``xent_gate=all``) it pulls toward the truth only within such a small error (training then
    runs to the ends of the layout range, README)."""
    loss, sample, verts, faces = setup
    no_dist = _with(loss, weights={"dist": 0.0})
    scales = (0.85, 0.95, 1.15)  # depth errors about the input camera: -15%, -5%, +15%
    curves = {}
    for mode in ("iou", "all"):
        cfg = _with(no_dist, xent_gate=mode)
        curves[mode] = []
        for s0 in scales:
            scale = torch.tensor(s0, requires_grad=True)
            out = multiview_silhouette_loss(verts * scale, faces, [sample], [len(verts)], cfg)
            (grad,) = torch.autograd.grad(out.l3d, scale)
            curves[mode].append(
                (out.l3d.item(), grad.item(), out.stats["iou_pass_views"].item(), out.stats["xent_gate"].item())
            )
    (far_near, g_near, pass_near, _), (close, _, pass_close, _), (far_deep, g_deep, pass_deep, _) = curves["iou"]
    assert pass_near == pass_deep == 0.0 and pass_close > 0.4
    assert far_near < 0.1 * close and far_deep < 0.1 * close  # the gated objective prefers the wrong depth
    assert abs(g_near) < 1e-6 and abs(g_deep) < 1e-6  # ... and has no gradient there (rounding only)
    assert [c[2] for c in curves["all"]] == [c[2] for c in curves["iou"]]  # the IoUs, whatever the mode
    (near, g_near, _, gate_near), (close, _, _, _), (deep, g_deep, _, _) = curves["all"]
    assert gate_near == 1.0  # every pair is in l_xent
    assert close < near and close < deep and g_near < 0 < g_deep  # descent moves the depth to the truth


def _xent_along_scale(loss, sample, verts, faces, blur_radius, scales):
    """Input-view l_xent alone (ungated, no l_dist) and its derivative as each object is scaled
    about its own centre (scale < 1: the mesh lies inside its true silhouette)."""
    cfg = _with(loss, weights={"dist": 0.0}, xent_gate="all", render=replace(loss.render, blur_radius=blur_radius))
    only_input = replace(sample, views=sample.views[:1])
    centre = verts.mean(dim=1, keepdim=True)
    curve = []
    for s0 in scales:
        scale = torch.tensor(s0, requires_grad=True)
        out = multiview_silhouette_loss(centre + scale * (verts - centre), faces, [only_input], [len(verts)], cfg)
        (grad,) = torch.autograd.grad(out.l3d, scale)
        curve.append((out.l3d.item(), grad.item(), out.stats["unreached"].item()))
    return curve


def test_at_blur_radius_sigma_l_xent_shrinks_a_mesh_inside_its_silhouette(setup):
    """The collapse of "w/o l_dist": with the paper's literal blur radius = sigma = 1e-3 a face
    touches cells within ~1 cell of it (soft value 0.27 at the cut-off), so a true cell farther
    out costs BCE's clamp (100) with no gradient. The loss falls as a shrunk mesh grows back, but
    its gradient points the other way: descent shrinks it further. With PyTorch3D's usual
    blur radius ln(1/1e-4 - 1) sigma (soft value 1e-4 at the cut-off) it grows back."""
    loss, sample, verts, faces = setup
    scales = (0.5, 0.7)
    literal = _xent_along_scale(loss, sample, verts, faces, 1e-3, scales)
    assert literal[0][0] > literal[1][0]  # a larger mesh is better ...
    assert literal[0][1] > 0 and literal[1][1] > 0  # ... yet the gradient says shrink
    assert literal[0][2] > 0.5  # most true cells are beyond reach
    wide = _xent_along_scale(loss, sample, verts, faces, 9.21e-3, scales)
    assert wide[0][0] > wide[1][0] and wide[0][1] < 0 and wide[1][1] < 0  # descent grows it
    assert wide[0][2] < literal[0][2]


def test_iou_threshold_decides_which_pairs_pass_the_gate(setup):
    loss, sample, verts, faces = setup
    centre = verts.mean(dim=1, keepdim=True)
    shrunk = centre + 0.8 * (verts - centre)  # IoUs spread between 0 and 1 over the pairs
    fractions = []
    for threshold in (0.0, 0.3, 0.6, 1.0):
        out = multiview_silhouette_loss(shrunk, faces, [sample], [len(verts)], _with(loss, iou_threshold=threshold))
        fractions.append(out.stats["xent_gate"].item())
        if threshold == 1.0:
            assert out.xent.item() == 0.0  # no IoU exceeds 1: l_xent is off everywhere
    assert fractions[0] == 1.0 and fractions[-1] == 0.0
    assert fractions[0] > fractions[1] or fractions[1] > fractions[2] > fractions[3]
    assert fractions == sorted(fractions, reverse=True) and len(set(fractions)) >= 3


def _soft_iou_part(loss, sample, verts, faces, weight):
    """L_3D's soft-IoU part alone: the l_xent part with the term minus the l_xent part without it."""
    with_term = multiview_silhouette_loss(
        verts, faces, [sample], [len(verts)], _with(loss, weights={"soft_iou": weight})
    )
    without = multiview_silhouette_loss(verts, faces, [sample], [len(verts)], _with(loss, weights={"soft_iou": 0.0}))
    torch.testing.assert_close(with_term.dist, without.dist)
    assert "l_soft_iou" in with_term.stats and "l_soft_iou" not in without.stats
    return with_term.xent - without.xent


def test_soft_iou_joins_l_xent_under_its_gate_and_pulls_a_shrunk_mesh_out(setup):
    """``loss.weights.soft_iou`` adds w * (1 - soft IoU) to every pair l_xent applies to: linear in w,
    nothing where the gate is shut, and, on a mesh shrunk inside its silhouettes, a descent
    direction that grows it back toward the truth."""
    loss, sample, verts, faces = setup
    centre = verts.mean(dim=1, keepdim=True)
    scale = torch.tensor(0.8, dtype=verts.dtype, requires_grad=True)
    shrunk = centre + scale * (verts - centre)
    one = _soft_iou_part(loss, sample, shrunk, faces, 1.0)
    torch.testing.assert_close(_soft_iou_part(loss, sample, shrunk, faces, 2.5), 2.5 * one)
    (slope,) = torch.autograd.grad(one, scale)
    assert one.item() > 0 and slope.item() < 0  # descent grows the mesh
    mean_over_pairs = [  # the logged statistic covers every pair, gated or not: the truth scores better
        multiview_silhouette_loss(v, faces, [sample], [len(v)], _with(loss, weights={"soft_iou": 1.0})).stats[
            "l_soft_iou"
        ]
        for v in (verts, shrunk.detach())
    ]
    assert mean_over_pairs[0] < mean_over_pairs[1]
    shut = _soft_iou_part(_with(loss, iou_threshold=1.0), sample, shrunk.detach(), faces, 1.0)
    assert shut.item() == 0.0  # the gate (input view included here) lets no pair in


def test_bad_switch_values_are_config_errors():
    with pytest.raises(ConfigError, match="loss.xent_gate"):
        load_config("tiny", ["loss.xent_gate=sometimes"])
    with pytest.raises(ConfigError, match="loss.weights.dist"):
        load_config("tiny", ["loss.weights.dist=-1"])
    with pytest.raises(ConfigError, match="loss.weights.soft_iou"):
        load_config("tiny", ["loss.weights.soft_iou=-1"])
    with pytest.raises(ConfigError, match="loss.supervision"):
        load_config("tiny", ["loss.supervision=4d"])
    for recipe in ("scene_shapes", "hypersim", "scannet", "tiny"):  # the paper's defaults
        cfg = load_config(recipe)
        assert cfg.loss.weights.dist == 1.0 and cfg.loss.supervision == "2d" and cfg.loss.iou_threshold == 0.5
        assert cfg.loss.xent_gate == "iou"
