"""scripts/experiments/sampler_why.py's variants of a checkpoint: each loads as a usl checkpoint and
changes the shape head as its name says, on the same inputs."""

from __future__ import annotations

import sampler_why
import torch

from tests.evaluation.eval_helpers import tiny_checkpoint
from usl.engine.checkpoint import load_checkpoint


def test_each_variant_changes_the_shape_head_as_its_name_says(tmp_path):
    payload = torch.load(tiny_checkpoint(tmp_path / "run"), map_location="cpu", weights_only=True)
    generator = torch.Generator().manual_seed(0)
    for name, value in payload["model"].items():  # as if trained: every layer that moves vertices non-zero
        if name.startswith("shape_head.global_mlp.4.") or name.startswith("shape_head.stages.") and ".offset." in name:
            payload["model"][name] = 0.05 * torch.randn(value.shape, generator=generator)
    heads = {}
    for variant in sampler_why.VARIANTS:
        path = tmp_path / f"{variant}.pt"
        torch.save(sampler_why.variant_payload(payload, variant), path)
        heads[variant] = load_checkpoint(path).model.shape_head
    trained = heads["as trained"]
    assert trained.cfg.sampler == "roimap" and heads["other sampler"].cfg.sampler == "vertalign"

    p2_channels = trained.stages[0].bottleneck.in_features - 3  # tiny samples p2 and the image's 3 channels
    features = {"p2": torch.randn(1, p2_channels, 32, 32, generator=generator)}
    features["image"] = torch.randn(1, 3, 128, 128, generator=generator)
    boxes = [torch.tensor([[20.0, 30.0, 90.0, 100.0], [5.0, 60.0, 50.0, 120.0]])]
    roi = torch.randn(2, trained.global_mlp[0].in_features, generator=generator)
    with torch.no_grad():
        out = {variant: head(features, boxes, roi) for variant, head in heads.items()}
    as_trained, global_only, other = out["as trained"], out["global stage only"], out["other sampler"]
    assert not torch.allclose(as_trained.stage_verts[0], trained.sphere_verts.expand(2, -1, -1), atol=1e-3)
    assert not torch.allclose(as_trained.verts, as_trained.stage_verts[0], atol=1e-3)  # the stages move vertices
    torch.testing.assert_close(global_only.verts, as_trained.stage_verts[0], rtol=0, atol=0)
    torch.testing.assert_close(other.stage_verts[0], as_trained.stage_verts[0], rtol=0, atol=0)
    assert not torch.allclose(other.verts, as_trained.verts, atol=1e-3)  # other features, other offsets

    # without vertex features the stages see positions only: other maps, the same meshes
    blind = heads["no vertex features"]
    other_maps = {name: torch.randn(value.shape, generator=generator) for name, value in features.items()}
    with torch.no_grad():
        seen, seen_elsewhere = blind(features, boxes, roi), blind(other_maps, boxes, roi)
    torch.testing.assert_close(seen.verts, seen_elsewhere.verts, rtol=0, atol=0)
    torch.testing.assert_close(seen.stage_verts[0], as_trained.stage_verts[0], rtol=0, atol=0)
    assert not torch.allclose(seen.verts, seen.stage_verts[0], atol=1e-3)  # the stages still move vertices
    with torch.no_grad():
        assert not torch.allclose(trained(other_maps, boxes, roi).verts, as_trained.verts, atol=1e-3)
