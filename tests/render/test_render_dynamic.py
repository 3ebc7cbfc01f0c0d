"""Dynamic rendering: window choice, exact-area targets, and soft renders aligned with them."""

import numpy as np
import pytest
import torch
import torch.nn.functional as F
import trimesh

from tests.render.per_pair_oracle import projected_boxes_of_kept_faces, render_dynamic_per_pair
from tests.render.render_oracle import intrinsics, random_scene, render_pyrender
from usl.geometry.cameras import scale_intrinsics
from usl.render import PaddedMasks, SoftRasterSettings, render_dynamic, resample_masks_area
from usl.render.dynamic import projected_boxes
from usl.render.resample import _torch_resample_masks_area
from usl.utils import compiled
from usl.utils.op_count import count_ops

SHARP = SoftRasterSettings(sigma=1e-10, blur_radius=1e-8, faces_per_pixel=None)


def pack(meshes):
    verts, faces, window, offset = [], [], [], 0
    for i, (v, f) in enumerate(meshes):
        verts.append(torch.as_tensor(np.asarray(v), dtype=torch.float64))
        faces.append(torch.as_tensor(np.asarray(f), dtype=torch.long) + offset)
        window.append(torch.full((len(f),), i, dtype=torch.long))
        offset += len(v)
    return torch.cat(verts), torch.cat(faces), torch.cat(window)


def overlap_matrix(lo, hi, resolution, size):
    """(R, size) length of overlap between window cell i and pixel [x, x + 1)."""
    edges = np.linspace(lo, hi, resolution + 1)
    pixels = np.arange(size)
    return np.clip(np.minimum(edges[1:, None], pixels[None] + 1) - np.maximum(edges[:-1, None], pixels[None]), 0, None)


def area_oracle(mask, window, resolution):
    x0, y0, x1, y1 = window
    oy = overlap_matrix(y0, y1, resolution, mask.shape[0])
    ox = overlap_matrix(x0, x1, resolution, mask.shape[1])
    return oy @ mask.astype(np.float64) @ ox.T / ((x1 - x0) * (y1 - y0) / resolution**2)


def projected_box(verts, K):
    h = np.asarray(verts) @ np.asarray(K).T
    uv = h[:, :2] / h[:, 2:]
    return np.concatenate([uv.min(0), uv.max(0)])


def test_exact_area_resampling_matches_overlap_oracle_and_average_pooling():
    rng = np.random.default_rng(0)
    masks = rng.random((4, 37, 53)) > 0.6
    windows = [[3.3, 2.7, 30.1, 29.5], [-5.5, 10.25, 60.0, 75.75], [10.0, 12.0, 11.5, 13.5], [0.0, 0.0, 53.0, 53.0]]
    got = resample_masks_area(
        torch.as_tensor(masks), torch.tensor(windows, dtype=torch.float64), 16
    ).numpy()  # all windows at once
    for mask, window, coverage in zip(masks, windows, got, strict=True):
        np.testing.assert_allclose(coverage, area_oracle(mask, window, 16), atol=1e-9)
    # Integer-aligned windows whose side is a multiple of R are plain average pooling.
    pooled = F.avg_pool2d(torch.as_tensor(masks[0, 4:36, 8:40], dtype=torch.float64)[None], 4)
    window = torch.tensor([[8.0, 4.0, 40.0, 36.0]])
    torch.testing.assert_close(resample_masks_area(torch.as_tensor(masks[:1]), window, 8), pooled)


@pytest.mark.skipif(compiled.numba is None, reason="numba is not installed")
def test_compiled_resampling_equals_the_torch_path_bit_for_bit():
    """The CPU loop against the torch path (which CUDA runs): windows inside, past every image
    edge, smaller than a pixel, and non-contiguous masks."""
    rng = np.random.default_rng(5)
    masks = torch.as_tensor(rng.random((40, 53, 37)) > 0.6).transpose(1, 2)
    corner = torch.as_tensor(rng.uniform(-20, 50, (40, 2)))
    sides = torch.as_tensor(rng.uniform(0.3, 60, (40, 2)))
    windows = torch.cat([corner, corner + sides], dim=1)
    for resolution in (1, 7, 16):
        expected = _torch_resample_masks_area(masks, windows, resolution)
        assert torch.equal(resample_masks_area(masks, windows, resolution), expected)
    assert expected.amax() == 1.0 and (expected == 0).any() and ((expected > 0) & (expected < 1)).any()


def test_batched_render_matches_the_per_pair_oracle_in_values_and_gradients():
    """All pairs at once (views of two sizes, padded; occluder masks) against the former per-pair loop."""
    rng = np.random.default_rng(3)
    objects = random_scene(rng, 4)
    sizes = [(64, 80), (64, 80), (48, 72), (48, 72)]
    Ks = torch.stack([torch.as_tensor(intrinsics(h, w, (0.02, -0.01))) for h, w in sizes])
    masks = [
        torch.as_tensor(render_pyrender([m], np.eye(4), K.numpy(), h, w)[2][0])
        for m, K, (h, w) in zip(objects, Ks, sizes, strict=True)
    ]
    masks[1] = torch.roll(masks[1], shifts=(3, -5), dims=(0, 1))  # a truth that differs from the mesh
    occluders = [torch.as_tensor(rng.random((h, w)) > 0.9) for h, w in sizes]
    verts, faces, window = pack([(m.vertices, m.faces) for m in objects])
    padded = PaddedMasks.of(masks)
    assert padded.padded.shape == (4, 64, 80) and padded.sizes.tolist() == [list(s) for s in sizes]
    results = []
    for render, truth, hidden in (
        (render_dynamic, padded, PaddedMasks.of(occluders).padded),
        (render_dynamic_per_pair, masks, occluders),
    ):
        v = verts.clone().requires_grad_(True)
        out = render(v, faces, window, Ks, truth, resolution=24, ignore_masks=hidden)
        bce = F.binary_cross_entropy(out.soft.clamp(1e-6, 1 - 1e-6), out.target, reduction="none")
        (bce * out.valid).sum().backward()
        results.append((out, v.grad))
    (new, new_grad), (old, old_grad) = results
    for name in ("soft", "target", "valid", "windows", "K_window"):
        torch.testing.assert_close(getattr(new, name), getattr(old, name), atol=1e-9, rtol=1e-9)
    torch.testing.assert_close(new_grad, old_grad, atol=1e-9, rtol=1e-9)
    assert new.valid.float().mean() < 1.0  # the occluders did hide cells


def test_projected_boxes_mask_culled_faces_like_the_former_indexing_and_read_nothing():
    """Objects partly and wholly behind the near plane, one with no faces: boxes equal the former
    boolean-indexing version exactly, with no host sync."""
    objects = random_scene(np.random.default_rng(5), 3)
    verts, faces, window = pack([(m.vertices, m.faces) for m in objects])
    straddling = faces[window == 1].flatten().unique()
    verts[straddling, 2] -= verts[straddling, 2].mean()  # some faces in front of the camera, some behind
    verts[faces[window == 2].flatten(), 2] = -1.0  # wholly behind the camera
    Ks = torch.stack([torch.as_tensor(intrinsics(64, 80, (0.0, 0.0)))] * 4)  # window 3 has no faces
    with count_ops() as count:
        boxes = projected_boxes(verts, faces, window, Ks, 0.05)
    assert count.total_syncs == 0, count.syncs
    assert torch.equal(boxes, projected_boxes_of_kept_faces(verts, faces, window, Ks, 0.05))
    assert torch.isfinite(boxes[:2]).all() and torch.isinf(boxes[2:]).all()


def _predicted_and_true_objects(rng, height, width):
    """Meshes (the 'prediction') and true masks of the same objects moved a little (the 'truth')."""
    objects = random_scene(rng, 4)
    moved = []
    for m in objects:
        shift = np.eye(4)
        shift[:3, 3] = rng.uniform(-0.15, 0.15, size=3)
        moved.append(m.copy().apply_transform(shift))
    K = intrinsics(height, width, (0.03, -0.02))
    _, _, true_masks = render_pyrender(moved, np.eye(4), K, height, width)
    return objects, torch.as_tensor(true_masks), K


@pytest.mark.parametrize("height,width", [(96, 96), (72, 120)])
def test_windows_are_square_and_contain_the_true_silhouette_and_the_projected_mesh(height, width):
    rng = np.random.default_rng(height)
    objects, true_masks, K = _predicted_and_true_objects(rng, height, width)
    verts, faces, window = pack([(m.vertices, m.faces) for m in objects])
    out = render_dynamic(
        verts, faces, window, torch.as_tensor(K).expand(len(objects), 3, 3), PaddedMasks.of(true_masks), resolution=32
    )
    assert out.soft.shape == out.target.shape == out.valid.shape == (len(objects), 32, 32)
    for p, (mesh, mask) in enumerate(zip(objects, true_masks.numpy(), strict=True)):
        x0, y0, x1, y1 = out.windows[p].tolist()
        assert x1 - x0 == pytest.approx(y1 - y0)
        ys, xs = np.nonzero(mask)
        if len(xs):
            assert x0 <= xs.min() and y0 <= ys.min() and xs.max() + 1 <= x1 and ys.max() + 1 <= y1
        mx0, my0, mx1, my1 = projected_box(mesh.vertices, K)
        assert x0 <= max(mx0, 0) and y0 <= max(my0, 0) and min(mx1, width) <= x1 and min(my1, height) <= y1
        if x1 - x0 <= min(height, width):
            assert 0 <= x0 and 0 <= y0 and x1 <= width and y1 <= height and out.valid[p].all()
        np.testing.assert_allclose(out.target[p].numpy(), area_oracle(mask, (x0, y0, x1, y1), 32), atol=1e-6)


def test_soft_render_is_aligned_with_the_target_when_the_mesh_is_the_truth():
    # Truth rendered by pyrender at 8x the image resolution, so a target cell spans > 2 mask
    # pixels; the sharp soft silhouette must agree with the >50%-covered cells (a quarter
    # window-pixel misalignment drops this IoU to ~0.96).
    height, width, resolution = 64, 80, 32
    objects = random_scene(np.random.default_rng(7), 3)
    K8 = scale_intrinsics(torch.as_tensor(intrinsics(height, width, (0.03, 0.02))), 8.0, 8.0)
    _, _, true_masks = render_pyrender(objects, np.eye(4), K8.numpy(), 8 * height, 8 * width)
    verts, faces, window = pack([(m.vertices, m.faces) for m in objects])
    out = render_dynamic(
        verts,
        faces,
        window,
        K8.expand(3, 3, 3),
        PaddedMasks.of(torch.as_tensor(true_masks)),
        resolution=resolution,
        settings=SHARP,
    )
    for p in range(3):
        a, b = out.soft[p] > 0.5, out.target[p] > 0.5
        assert (a & b).sum() / (a | b).sum() > 0.975
        # ...and with pyrender rendering the window directly through K_window.
        _, _, direct = render_pyrender([objects[p]], np.eye(4), out.K_window[p].numpy(), resolution, resolution)
        assert ((a.numpy() & direct[0]).sum() / (a.numpy() | direct[0]).sum()) > 0.99


def test_truncated_wide_objects_and_empty_pairs():
    height, width = 40, 120
    K = torch.as_tensor(intrinsics(height, width))
    # A long box crossing the right image border, and a triangle behind the camera.
    box = trimesh.creation.box(extents=[3.0, 0.3, 0.3])
    box.apply_translation([1.5, 0.0, 3.0])
    behind = (np.array([[0.0, 0.0, -1.0], [1.0, 0.0, -1.0], [0.0, 1.0, -1.0]]), np.array([[0, 1, 2]]))
    verts, faces, window = pack([(box.vertices, box.faces), behind])
    true_masks = torch.zeros(2, height, width, dtype=torch.bool)
    true_masks[0, 15:25, 40:120] = True
    out = render_dynamic(verts, faces, window, K.expand(2, 3, 3), PaddedMasks.of(true_masks), resolution=24)

    x0, y0, x1, y1 = out.windows[0].tolist()
    assert x1 == pytest.approx(width) and x0 <= 40 and x1 - x0 > height  # clipped to the image, wider than tall
    assert not out.valid[0].all() and out.valid[0].any()
    assert (out.target[0][~out.valid[0]] == 0).all()
    # The mesh reaches the window's right border, since it continues past the image.
    assert out.soft[0][:, -1].max() > 0.9
    # Nothing to see: a centred square of the image's shorter side, blank render and target.
    assert out.windows[1].tolist() == pytest.approx([40.0, 0.0, 80.0, 40.0])
    assert out.soft[1].abs().sum() == 0 and out.target[1].sum() == 0

    # the same masks padded into a larger plane: windows and targets stay inside the image
    padded = PaddedMasks(F.pad(true_masks, (0, 24, 0, 16)), PaddedMasks.of(true_masks).sizes)
    listed = render_dynamic(verts, faces, window, K.expand(2, 3, 3), padded, resolution=24)
    assert torch.equal(listed.windows, out.windows) and torch.equal(listed.valid, out.valid)
    torch.testing.assert_close(listed.target, out.target, rtol=0, atol=1e-12)
    # Boxes given by the caller (an absent object's [0, 0, 0, 0] counts as no box).
    boxed = render_dynamic(
        verts,
        faces,
        window,
        K.expand(2, 3, 3),
        PaddedMasks.of(true_masks),
        resolution=24,
        true_boxes=torch.tensor([[40.0, 15.0, 120.0, 25.0], [0.0, 0.0, 0.0, 0.0]]),
    )
    assert torch.equal(boxed.windows, out.windows) and torch.equal(boxed.soft, out.soft)


def test_gradients_flow_to_vertices_through_the_window():
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.3)
    verts, faces, window = pack([(sphere.vertices + [0.1, 0.0, 2.0], sphere.faces)])
    verts.requires_grad_(True)
    K = torch.as_tensor(intrinsics(64, 64))[None]
    true_masks = torch.zeros(1, 64, 64, dtype=torch.bool)
    true_masks[0, 20:40, 30:45] = True
    out = render_dynamic(verts, faces, window, K, PaddedMasks.of(true_masks), resolution=32)
    F.binary_cross_entropy(out.soft.clamp(1e-6, 1 - 1e-6), out.target).backward()
    assert torch.isfinite(verts.grad).all() and verts.grad.abs().max() > 0
