"""The multi-view loss gathers every (object, view) pair of a batch at once, absent pairs kept with
weight 0; the former per-(sample, view) gathering (multiview_oracle.py) is the oracle for its
losses, statistics and gradients."""

import functools
from dataclasses import replace

import pytest
import torch

import usl.model.multiview_loss as batched
from tests.data.synthetic_samples import synthetic_config, synthetic_sample
from tests.model import multiview_oracle
from usl.geometry.icosphere import ico_sphere
from usl.losses import sample_mask_points


def batch_with_absent_pairs():
    samples = [synthetic_sample(seed, 96, 128, objects, 3, 3) for seed, objects in ((0, 3), (1, 2))]
    # object 1 of the first sample is not annotated in its last view (the dataset zeroes its mask)
    last = samples[0].views[2]
    present = last.present.clone()
    present[1] = False
    masks = last.masks.clone()
    masks[1] = False
    samples[0].views[2] = replace(last, present=present, masks=masks)
    return samples


@pytest.mark.parametrize("overrides", [[], ["loss.ignore_occluders=false", "loss.gate_input_view=true"]])
def test_batched_pairs_match_the_per_view_oracle(monkeypatch, overrides):
    # every mask pixel drawn, at its centre: the true points no longer depend on the draw order
    deterministic = functools.partial(sample_mask_points, jitter=False)
    monkeypatch.setattr(batched, "sample_mask_points", deterministic)
    monkeypatch.setattr(multiview_oracle, "sample_mask_points", deterministic)
    cfg = synthetic_config("tiny", ["loss.mesh_points=6000", "loss.render.resolution=24", *overrides]).loss
    samples = batch_with_absent_pairs()
    sphere, faces = ico_sphere(1)
    centres = torch.tensor([[-0.4, 0.1, 3.0], [0.2, -0.2, 3.5], [0.5, 0.3, 2.8], [0.0, 0.0, 3.2], [-0.3, 0.4, 4.0]])
    verts = (0.4 * sphere[None] + centres[:, None]).float()
    results = []
    for loss in (batched.multiview_silhouette_loss, multiview_oracle.multiview_silhouette_loss_per_pair):
        leaf = verts.clone().requires_grad_(True)
        out = loss(leaf, faces, samples, [3, 2], cfg, iteration=0)
        (out.l3d + 0.5 * out.dist).backward()
        results.append((out, leaf.grad))
    (new, new_grad), (old, old_grad) = results
    for name in ("l3d", "dist", "xent"):
        torch.testing.assert_close(getattr(new, name), getattr(old, name), rtol=1e-5, atol=1e-7)
    assert new.stats.keys() == old.stats.keys()
    for key in new.stats:
        torch.testing.assert_close(new.stats[key].float(), old.stats[key].float(), rtol=1e-5, atol=1e-6, msg=key)
    torch.testing.assert_close(new_grad, old_grad, rtol=1e-4, atol=1e-7)
    assert new_grad.abs().sum() > 0
