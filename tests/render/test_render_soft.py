"""The soft silhouette rasterizer: pyrender masks, the dense reference, finite differences."""

import numpy as np
import pytest
import torch
import trimesh

from tests.render.host_read_oracle import iter_face_pixels_by_span, nearest_per_pixel_of_crowded
from tests.render.render_oracle import intrinsics, random_rigid, random_scene, render_pyrender
from usl.geometry.cameras import rigid_inverse, transform_points
from usl.render import SoftRasterSettings, rasterize_soft, rasterize_soft_dense
from usl.render.screen import FaceBoxes, iter_face_pixels
from usl.render.soft import nearest_per_pixel
from usl.utils.op_count import count_ops

# Near-binary: a pixel 0.01 px outside an edge shared by several faces stays below 0.5.
SHARP = SoftRasterSettings(sigma=1e-10, blur_radius=1e-8, faces_per_pixel=None)


def pack(meshes, dtype=torch.float64):
    """Packed vertices, faces and per-face window index (mesh i -> window i)."""
    verts, faces, window, offset = [], [], [], 0
    for i, (v, f) in enumerate(meshes):
        verts.append(torch.as_tensor(v, dtype=dtype))
        faces.append(torch.as_tensor(f, dtype=torch.long) + offset)
        window.append(torch.full((len(f),), i, dtype=torch.long))
        offset += len(v)
    return torch.cat(verts), torch.cat(faces), torch.cat(window)


def iou(a, b):
    return (a & b).sum() / max((a | b).sum(), 1)


@pytest.mark.parametrize(
    "height,width,tilt,seed", [(128, 128, (0.0, 0.0), 0), (80, 144, (0.0, 0.0), 1), (120, 96, (0.05, -0.04), 2)]
)
def test_sharp_soft_silhouettes_match_pyrender_masks(height, width, tilt, seed):
    rng = np.random.default_rng(seed)
    objects_cam = random_scene(rng, 5)
    cam_to_world = random_rigid(rng)
    world = [m.copy().apply_transform(cam_to_world) for m in objects_cam]
    K = intrinsics(height, width, tilt)
    _, _, amodal_ref = render_pyrender(world, cam_to_world, K, height, width)

    world_to_cam = rigid_inverse(torch.as_tensor(cam_to_world))
    verts, faces, window = pack([(transform_points(torch.as_tensor(m.vertices), world_to_cam), m.faces) for m in world])
    Ks = torch.as_tensor(K).expand(len(world), 3, 3)
    soft = rasterize_soft(verts, faces, window, Ks, height, width, SHARP)
    checked = 0
    for i, ref in enumerate(amodal_ref):
        if ref.sum() >= 150:
            assert iou(soft[i].numpy() > 0.5, ref) >= 0.99, i
            checked += 1
    assert checked >= 4


def _scene_for_dense_checks(dtype):
    """Three windows: a tilted sphere cut by the window edge, a box, and a mesh with one
    face behind the camera; non-square windows."""
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    box = trimesh.creation.box(extents=[0.6, 0.4, 0.5])
    box.apply_transform(trimesh.transformations.random_rotation_matrix(np.random.default_rng(3).random(3)))
    straddle_v = np.array([[-0.3, -0.3, 1.5], [0.3, -0.2, 1.6], [0.0, 0.35, 1.4], [0.2, 0.2, -0.3]])
    straddle_f = np.array([[0, 1, 2], [0, 1, 3]])
    meshes = [
        (sphere.vertices + [0.55, 0.1, 2.0], sphere.faces),
        (box.vertices + [-0.1, 0.05, 2.5], box.faces),
        (straddle_v, straddle_f),
    ]
    verts, faces, window = pack(meshes, dtype)
    K = torch.stack(
        [torch.as_tensor(intrinsics(40, 56, t), dtype=dtype) for t in [(0.0, 0.0), (0.04, -0.02), (0.0, 0.0)]]
    )
    return verts, faces, window, K


@pytest.mark.parametrize("faces_per_pixel", [10, 2, None])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_sparse_equals_dense_reference_in_values_and_gradients(faces_per_pixel, dtype):
    verts, faces, window, K = _scene_for_dense_checks(dtype)
    settings = SoftRasterSettings(sigma=1e-3, blur_radius=3e-3, faces_per_pixel=faces_per_pixel, chunk_size=777)
    weights = torch.rand(3, 40, 56, generator=torch.Generator().manual_seed(0), dtype=dtype)
    results = []
    for fn in (rasterize_soft, rasterize_soft_dense):
        v = verts.clone().requires_grad_(True)
        image = fn(v, faces, window, K, 40, 56, settings)
        (image * weights).sum().backward()
        results.append((image.detach(), v.grad))
    (sparse, sparse_grad), (dense, dense_grad) = results
    assert dense.amax() > 0.9 and (dense > 0.01).sum() > 300  # the scene is actually drawn
    assert torch.isfinite(sparse_grad).all()
    assert (sparse - dense).abs().max() <= 1e-5
    assert dense_grad.abs().max() > 1.0  # gradients are substantial, not trivially equal
    # float64: identical up to summation order; float32: gradients reach ~300, so compare relatively.
    scale = 1.0 if dtype == torch.float64 else dense_grad.abs().max().item()
    assert (sparse_grad - dense_grad).abs().max() <= 1e-5 * scale


def assert_gradient_matches_central_differences(loss, verts, eps=1e-6, directions=8):
    """Directional derivatives along random directions (any wrong gradient entry shows up
    in every generic direction), by central differences in float64."""
    v = verts.clone().requires_grad_(True)
    loss(v).backward()
    assert v.grad.abs().max() > 0.1
    generator = torch.Generator().manual_seed(0)
    for _ in range(directions):
        u = torch.randn(verts.shape, dtype=verts.dtype, generator=generator)
        numeric = (loss(verts + eps * u) - loss(verts - eps * u)) / (2 * eps)
        analytic = (v.grad * u).sum()
        assert abs(analytic - numeric) <= 1e-6 * max(1.0, (v.grad.norm() * u.norm()).item()), (analytic, numeric)


def test_soft_gradients_match_finite_differences():
    sphere = trimesh.creation.icosphere(subdivisions=0, radius=0.4)
    verts, faces, window = pack(
        [
            (sphere.vertices + [0.05, -0.03, 1.8], sphere.faces),
            (sphere.vertices * [1.2, 0.8, 1.0] + [0.1, 0.0, 2.2], sphere.faces),
        ]
    )
    K = torch.stack([torch.as_tensor(intrinsics(20, 24, t)) for t in [(0.0, 0.0), (0.05, 0.03)]])
    weights = torch.rand(2, 20, 24, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    settings = SoftRasterSettings(sigma=2e-2, blur_radius=0.15, faces_per_pixel=None)
    assert_gradient_matches_central_differences(
        lambda v: (rasterize_soft(v, faces, window, K, 20, 24, settings) * weights).sum(), verts
    )


def test_soft_gradients_match_finite_differences_through_the_nearest_faces_cap():
    # Separate triangles at distinct depths: the nearest-K selection is locally constant,
    # so the capped silhouette is differentiable there.
    rng = np.random.default_rng(4)
    tris = [
        (rng.uniform(-0.25, 0.25, size=(3, 3)) * [1, 1, 0.1] + [0, 0, depth], [[0, 1, 2]])
        for depth in (1.5, 1.9, 2.3, 2.7)
    ]
    verts, faces, _ = pack(tris)
    window = torch.zeros(len(faces), dtype=torch.long)
    K = torch.as_tensor(intrinsics(16, 16))[None]
    weights = torch.rand(1, 16, 16, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    settings = SoftRasterSettings(sigma=2e-2, blur_radius=0.1, faces_per_pixel=2)
    loss = lambda v: (rasterize_soft(v, faces, window, K, 16, 16, settings) * weights).sum()  # noqa: E731
    assert_gradient_matches_central_differences(loss, verts)
    uncapped = rasterize_soft(
        verts, faces, window, K, 16, 16, SoftRasterSettings(sigma=2e-2, blur_radius=0.1, faces_per_pixel=None)
    )
    assert (uncapped - rasterize_soft(verts, faces, window, K, 16, 16, settings)).max() > 0.05  # the cap binds


def test_sigma_and_blur_radius_are_resolution_independent():
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    verts, faces, window = pack([(sphere.vertices + [0.0, 0.0, 2.0], sphere.faces)])
    settings = SoftRasterSettings(sigma=1e-3, blur_radius=1e-2)
    coverage = []
    for size in (32, 96):
        K = torch.tensor(
            [[[size * 1.0, 0.0, size / 2], [0.0, size * 1.0, size / 2], [0.0, 0.0, 1.0]]], dtype=torch.float64
        )
        coverage.append(rasterize_soft(verts, faces, window, K, size, size, settings).mean().item())
    assert coverage[0] == pytest.approx(coverage[1], rel=0.02)


def test_empty_and_fully_culled_windows_render_blank():
    verts = torch.tensor(
        [[0.0, 0.0, -1.0], [1.0, 0.0, -1.0], [0.0, 1.0, -1.0]], dtype=torch.float64, requires_grad=True
    )
    K = torch.as_tensor(intrinsics(16, 16)).expand(2, 3, 3)
    image = rasterize_soft(verts, torch.tensor([[0, 1, 2]]), torch.tensor([1]), K, 16, 16)
    assert image.shape == (2, 16, 16) and image.abs().sum() == 0
    image.sum().backward()
    assert verts.grad.abs().sum() == 0


def test_malformed_inputs_get_clear_errors():
    verts, faces, window = pack([(np.eye(3) + [0, 0, 2], [[0, 1, 2]])])
    K = torch.as_tensor(intrinsics(8, 8))[None]
    with pytest.raises(ValueError, match="verts must be a float"):
        rasterize_soft(verts[:, :2], faces, window, K, 8, 8)
    with pytest.raises(ValueError, match=r"per-face index must be \(F,\)"):
        rasterize_soft(verts, faces, window[:0], K, 8, 8)
    with pytest.raises(ValueError, match=r"K must be \(P, 3, 3\)"):
        rasterize_soft(verts, faces, window, K[0], 8, 8)
    with pytest.raises(ValueError, match="sigma must be > 0"):
        SoftRasterSettings(sigma=0.0)


@pytest.mark.parametrize("chunk_size", [1, 7, 50, 10_000])
def test_pair_chunks_equal_the_former_span_reading_ones_without_a_read_per_chunk(chunk_size):
    """Faces with no pixels (first, last, inside) and faces split across chunks."""
    g = torch.Generator().manual_seed(2)
    nx, ny = torch.randint(0, 6, (40,), generator=g), torch.randint(0, 5, (40,), generator=g)
    nx[[0, 17, 39]] = 0
    boxes = FaceBoxes(
        x0=torch.randint(0, 30, (40,), generator=g), y0=torch.randint(0, 30, (40,), generator=g), nx=nx, ny=ny
    )
    with count_ops() as count:
        chunks = list(iter_face_pixels(boxes, chunk_size))
    assert count.total_syncs == 1, count.syncs  # the number of pairs, once
    former = list(iter_face_pixels_by_span(boxes, chunk_size))
    assert len(chunks) == len(former) > 0
    for new, old in zip(chunks, former, strict=True):
        assert all(torch.equal(a, b) for a, b in zip(new, old, strict=True))


def test_nearest_faces_per_pixel_equal_the_former_crowded_only_ranking_without_a_read():
    """Pixels with fewer, exactly k and more than k pairs, equal depths (ties go to the earlier pair)."""
    g = torch.Generator().manual_seed(4)
    pixel = torch.randint(0, 300, (5_000,), generator=g)
    depth = torch.randint(1, 40, (5_000,), generator=g).float() / 8  # many ties
    for k in (1, 3, 16, 100):
        with count_ops() as count:
            keep = nearest_per_pixel(pixel, depth, k)
        assert count.total_syncs == 0, count.syncs
        assert torch.equal(keep, nearest_per_pixel_of_crowded(pixel, depth, k))
        assert torch.equal(torch.bincount(pixel[keep]), torch.bincount(pixel).clamp_max(k))
