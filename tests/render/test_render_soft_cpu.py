"""The soft rasterizer's compiled CPU path against its torch path (the oracle, which CUDA runs) and
the dense reference: the same pairs, and the same silhouettes and gradients."""

import contextlib
from dataclasses import replace

import numpy as np
import pytest
import torch
import trimesh

from tests.render.render_oracle import intrinsics
from tests.render.test_render_soft import pack
from usl.render import SoftRasterSettings, rasterize_soft, rasterize_soft_dense, soft_cpu
from usl.render.screen import ndc_scale, project_faces
from usl.render.soft import _select_pairs
from usl.utils import compiled
from usl.utils.compiled import torch_paths_only

pytestmark = pytest.mark.skipif(compiled.numba is None, reason="numba is not installed")

HEIGHT, WIDTH = 40, 56


def crowded_scene(dtype):
    """Four windows: overlapping spheres (many faces per pixel), a sphere drawn twice over itself
    (equal depths: ties by face index), a mesh with faces behind the near plane and one straddling
    it, and an empty window; faces shuffled so windows interleave in the packed order."""
    rng = np.random.default_rng(7)
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.45)
    box = trimesh.creation.box(extents=[0.6, 0.4, 0.5])
    straddle = np.array([[-0.3, -0.3, 1.5], [0.3, -0.2, 1.6], [0.0, 0.35, 1.4], [0.2, 0.2, -0.3], [0.1, 0.0, 0.0005]])
    meshes = [
        (sphere.vertices * rng.uniform(0.6, 1.2) + [*rng.uniform(-0.3, 0.3, 2), 2.2], sphere.faces) for _ in range(3)
    ]
    meshes += [(sphere.vertices + [0.1, 0.0, 2.0], sphere.faces)] * 2
    meshes += [(box.vertices + [0.0, 0.1, 2.5], box.faces), (straddle, np.array([[0, 1, 2], [0, 1, 3], [2, 1, 4]]))]
    verts, faces, mesh = pack(meshes, dtype)
    window = torch.tensor([0, 0, 0, 1, 1, 2, 2])[mesh]
    order = torch.from_numpy(rng.permutation(len(faces)))
    K = torch.stack(
        [torch.as_tensor(intrinsics(HEIGHT, WIDTH, t), dtype=dtype) for t in [(0, 0), (0.04, -0.02), (0, 0), (0, 0)]]
    )
    return verts, faces[order], window[order], K


@pytest.mark.parametrize("faces_per_pixel", [10, 3, 1, None])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_compiled_selection_keeps_the_torch_paths_pairs_in_its_order(faces_per_pixel, dtype):
    verts, faces, window, K = crowded_scene(dtype)
    settings = SoftRasterSettings(sigma=1e-3, blur_radius=3e-3, faces_per_pixel=faces_per_pixel, chunk_size=5_000)
    screen = project_faces(verts, faces, window, K, settings.near)
    assert not screen.visible.all()  # culled faces are part of the check
    face, pixel = _select_pairs(screen, window, HEIGHT, WIDTH, settings)
    compiled = soft_cpu.select_pairs(screen, window, 4, HEIGHT, WIDTH, settings)
    assert torch.equal(torch.from_numpy(compiled.face).long(), face)
    assert torch.equal(torch.from_numpy(compiled.pixel).long(), pixel)
    uncapped = torch.bincount(
        _select_pairs(screen, window, HEIGHT, WIDTH, SoftRasterSettings(blur_radius=3e-3, faces_per_pixel=None))[1]
    )
    assert uncapped.max() > 10  # every cap binds
    assert torch.equal(
        torch.bincount(pixel, minlength=len(uncapped)), uncapped.clamp_max(faces_per_pixel or len(faces))
    )
    assert not (pixel // (HEIGHT * WIDTH) == 3).any()  # the empty window has no pair


@pytest.mark.parametrize("faces_per_pixel", [10, 2, None])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_compiled_path_equals_the_torch_path_and_the_dense_reference(faces_per_pixel, dtype):
    verts, faces, window, K = crowded_scene(dtype)
    settings = SoftRasterSettings(sigma=1e-3, blur_radius=3e-3, faces_per_pixel=faces_per_pixel)
    weights = torch.rand(4, HEIGHT, WIDTH, generator=torch.Generator().manual_seed(0), dtype=dtype)

    def image_and_gradient(fn):
        v = verts.clone().requires_grad_(True)
        image = fn(v, faces, window, K, HEIGHT, WIDTH, settings)
        (image * weights).sum().backward()
        return image.detach(), v.grad

    compiled, compiled_grad = image_and_gradient(rasterize_soft)
    dense, dense_grad = image_and_gradient(rasterize_soft_dense)
    with torch_paths_only():
        torch_path, torch_grad = image_and_gradient(rasterize_soft)
    assert dense.amax() > 0.9 and (dense > 0.01).sum() > 1000 and compiled[3].abs().max() == 0
    assert torch_grad.abs().max() > 1.0
    # float64: equal up to summation order; float32: gradients reach ~1e3, so compare relatively.
    tolerance = 1e-12 if dtype == torch.float64 else 1e-5
    scale = 1.0 if dtype == torch.float64 else torch_grad.abs().max().item()
    assert (compiled - torch_path).abs().max() <= tolerance
    assert (compiled_grad - torch_grad).abs().max() <= tolerance * scale
    assert (compiled - dense).abs().max() <= 1e-5
    assert (compiled_grad - dense_grad).abs().max() <= 1e-5 * scale


def test_log_transparency_backward_passes_gradcheck():
    """The analytic backward against finite differences of the (16, F) face table, float64."""
    verts, faces, window, K = crowded_scene(torch.float64)
    settings = SoftRasterSettings(sigma=2e-2, blur_radius=5e-2, faces_per_pixel=None)
    keep = torch.nonzero(window == 2).squeeze(1)[:6]  # the box: big faces, pairs inside and outside
    screen = project_faces(verts, faces[keep], window[keep], K, settings.near)
    assert 200 < len(soft_cpu.select_pairs(screen, window[keep], 4, HEIGHT, WIDTH, settings).face) < 5_000
    scale = ndc_scale(HEIGHT, WIDTH) ** 2 / settings.sigma

    def log_transparency(plane):  # the selection is part of the function: reselected from the perturbed plane
        pairs = soft_cpu.select_pairs(replace(screen, plane=plane), window[keep], 4, HEIGHT, WIDTH, settings)
        return soft_cpu.LogTransparency.apply(plane, pairs, 4 * HEIGHT * WIDTH, scale)

    plane = screen.plane.detach().clone().requires_grad_(True)
    assert torch.autograd.gradcheck(log_transparency, (plane,), eps=1e-7, atol=1e-6, rtol=1e-5)


def test_exact_ties_between_edge_distances_share_the_gradient_as_torch_minimum_does(monkeypatch):
    """A pixel centre exactly as far from two edges (at the shared corner's bisector) takes half of
    the gradient through each, as autograd through torch.minimum does."""
    verts = torch.tensor([[-0.5, -0.5, 2.0], [0.5, -0.5, 2.0], [0.0, 0.5, 2.0]], dtype=torch.float64)
    K = torch.tensor([[[8.0, 0.0, 8.5], [0.0, 8.0, 8.0], [0.0, 0.0, 1.0]]], dtype=torch.float64)
    faces, window = torch.tensor([[0, 1, 2]]), torch.tensor([0])
    settings = SoftRasterSettings(sigma=1e-2, blur_radius=0.2, faces_per_pixel=None)
    screen = project_faces(verts, faces, window, K, settings.near)
    shares = soft_cpu.select_pairs(screen, window, 1, 16, 16, settings).share
    edges_share = (shares[:, None] >> np.array([0, 2, 4], dtype=np.uint8)) & 3
    assert (edges_share == 2).any(), "the scene no longer has a pixel exactly as far from two edges"
    grads = []
    for use_compiled in (True, False):
        with monkeypatch.context() as patch, contextlib.nullcontext() if use_compiled else torch_paths_only():
            plane = screen.plane.detach().clone().requires_grad_(True)
            screen_copy = type(screen)(screen.xy, plane, screen.depths, screen.visible)
            patch.setattr("usl.render.soft.project_faces", lambda *args, projected=screen_copy: projected)
            rasterize_soft(verts, faces, window, K, 16, 16, settings).sum().backward()
            grads.append(plane.grad)
    # column 8 (centres at x = 8.5) is the axis of symmetry: above corner 2 (8.5, 10) both edges meeting
    # there end exactly at it
    assert torch.allclose(grads[0], grads[1], rtol=1e-12, atol=1e-12)


def test_no_faces_render_blank_with_a_zero_gradient():
    verts = torch.zeros(0, 3, dtype=torch.float64, requires_grad=True)
    K = torch.as_tensor(intrinsics(16, 16)).expand(2, 3, 3)
    image = rasterize_soft(verts, torch.zeros(0, 3, dtype=torch.long), torch.zeros(0, dtype=torch.long), K, 16, 16)
    assert image.shape == (2, 16, 16) and image.abs().sum() == 0
    image.sum().backward()
    assert verts.grad.shape == (0, 3)
