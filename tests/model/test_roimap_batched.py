"""RoIMap samples every object's vertices from its own image at once; the oracle is
``F.grid_sample`` object by object (the former per-image implementation's sampling)."""

import torch
import torch.nn.functional as F

from usl.model.heads import project_cube_to_image, roimap_features


def grid_sample_oracle(maps, strides, verts, boxes, image_index):
    uv = project_cube_to_image(verts, boxes)
    per_object = []
    for n in range(len(verts)):
        sampled = []
        for feature_map, stride in zip(maps, strides):
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
    for a, b in zip(new_maps, old_maps):
        torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-5)
