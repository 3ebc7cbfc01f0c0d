"""RoIMap samples every object's vertices from its own image at once; the oracle is
``F.grid_sample`` object by object (a per-image reference of the sampling)."""

import torch
import torch.nn.functional as F

from usl.model.heads import project_cube_to_image, roimap_features
from usl.model.heads.vertex_features import _sample_bilinear


def grid_sample_oracle(maps, strides, verts, boxes, image_index):
    uv = project_cube_to_image(verts, boxes)
    per_object = []
    for n in range(len(verts)):
        sampled = []
        for feature_map, stride in zip(maps, strides, strict=True):
            height, width = feature_map.shape[-2:]
            extent = torch.tensor([width * stride, height * stride], dtype=uv.dtype)
            grid = (2.0 * uv[n] / extent - 1.0).reshape(1, 1, -1, 2)
            image = feature_map[image_index[n] : image_index[n] + 1]
            sampled.append(F.grid_sample(image, grid, align_corners=False)[0, :, 0].T)
        per_object.append(torch.cat(sampled, dim=1))
    return torch.stack(per_object)


def test_batched_roimap_matches_grid_sample_in_values_and_gradients():
    generator = torch.Generator().manual_seed(0)
    maps = [torch.randn(3, 5, 12, 16, generator=generator), torch.randn(3, 2, 48, 64, generator=generator)]
    strides = [4, 1]
    verts = torch.rand(7, 30, 3, generator=generator) * 2.6 - 1.3  # some vertices project outside the image
    boxes = torch.tensor([[5.0, 4.0, 30.0, 40.0], [0.0, 0.0, 64.0, 48.0], [40.0, 10.0, 70.0, 50.0]]).repeat(3, 1)[:7]
    image_index = torch.tensor([2, 0, 1, 2, 0, 0, 1])  # not grouped by image
    results = []
    for sample in (roimap_features, grid_sample_oracle):
        leaves = [m.clone().requires_grad_(True) for m in maps]
        v = verts.clone().requires_grad_(True)
        out = sample(leaves, strides, v, boxes, image_index)
        (out * torch.linspace(-1, 1, out.numel()).view_as(out)).sum().backward()
        results.append((out.detach(), v.grad, [m.grad for m in leaves]))
    (new, new_v, new_maps), (old, old_v, old_maps) = results
    torch.testing.assert_close(new, old, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(new_v, old_v, atol=1e-4, rtol=1e-4)
    for a, b in zip(new_maps, old_maps, strict=True):
        torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-5)


def four_tap_oracle(feature_map, image, xy):
    """Tap-by-tap reference of ``_sample_bilinear``: one gather and one weighted add per tap."""
    height, width = feature_map.shape[-2:]
    corner = xy.floor()
    frac = xy - corner
    out = 0.0
    for dy in (0, 1):
        for dx in (0, 1):
            x, y = corner[:, 0] + dx, corner[:, 1] + dy
            inside = (x >= 0) & (x <= width - 1) & (y >= 0) & (y <= height - 1)
            weight = (frac[:, 0] if dx else 1 - frac[:, 0]) * (frac[:, 1] if dy else 1 - frac[:, 1]) * inside
            taps = feature_map[image, :, y.clamp(0, height - 1).long(), x.clamp(0, width - 1).long()]
            out = out + taps * weight[:, None]
    return out


def test_stacked_taps_equal_the_tap_by_tap_sampler():
    """The same samples bit for bit; the map's gradient sums the four taps' scatters in another
    order, so it agrees to float rounding."""
    generator = torch.Generator().manual_seed(1)
    feature_map = torch.randn(3, 6, 10, 13, generator=generator)
    xy = torch.rand(200, 2, generator=generator) * torch.tensor([16.0, 13.0]) - 1.5  # some outside
    xy[:4] = torch.tensor([[0.0, 0.0], [12.0, 9.0], [-1.0, 3.0], [5.0, 5.0]])  # on cell centres and edges
    image = torch.randint(0, 3, (200,), generator=generator)
    results = []
    for sample in (_sample_bilinear, four_tap_oracle):
        leaf, points = feature_map.clone().requires_grad_(True), xy.clone().requires_grad_(True)
        out = sample(leaf, image, points)
        (out * torch.linspace(-1, 1, out.numel()).view_as(out)).sum().backward()
        results.append((out.detach(), points.grad, leaf.grad))
    (new, new_xy, new_map), (old, old_xy, old_map) = results
    assert torch.equal(new, old)
    torch.testing.assert_close(new_xy, old_xy, rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(new_map, old_map, rtol=1e-6, atol=1e-6)
