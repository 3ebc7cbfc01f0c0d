"""The z-buffer rasterizer's compiled CPU path against its torch path (the oracle, which CUDA runs):
the same instance map, depth map, masks and nearest depths, bit for bit."""

import numpy as np
import pytest
import torch

from tests.render.render_oracle import intrinsics
from usl.render import rasterize_hard
from usl.render.screen import face_pixel_boxes, pixel_centres, project_faces, screen_barycentrics
from usl.utils import compiled

pytestmark = pytest.mark.skipif(compiled.numba is None, reason="numba is not installed")

HEIGHT, WIDTH = 24, 32
# View 0's K: a power-of-two focal length and integer centre, so vertices placed at pixel centres
# at depths 2 and 4 project there exactly and their edges run through pixel centres.
GRID_K = np.array([[8.0, 0.0, 16.0], [0.0, 8.0, 12.0], [0.0, 0.0, 1.0]])


def grid_triangles(rng, count):
    """Triangles with corners exactly at pixel centres of view 0, at depth 2 or 4 (fronto-parallel)."""
    u = rng.integers(0, WIDTH, (count, 3)) + 0.5
    v = rng.integers(0, HEIGHT, (count, 3)) + 0.5
    z = rng.choice([2.0, 4.0], (count, 1)).repeat(3, 1)
    return np.stack([(u - 16.0) * z / 8.0, (v - 12.0) * z / 8.0, z], axis=-1)


def random_triangles(rng, count, near_depth):
    """Triangles around the view axis, depths from ``near_depth`` to 4 (some straddle or cross the near plane)."""
    z = rng.uniform(near_depth, 4.0, (count, 1)) + rng.uniform(-0.3, 0.3, (count, 3))
    centre = rng.uniform(-0.6, 0.6, (count, 1, 2)) * z[..., None]
    corners = centre + rng.normal(0.0, 0.25, (count, 3, 2)) * z[..., None]
    return np.concatenate([corners, z[..., None]], axis=-1)


def crowded_scene(seed, dtype):
    """Four views with their own K (view 3 holds no mesh) and eight meshes: random and pixel-aligned
    triangles, faces behind or straddling the near plane, degenerate faces (a repeated corner, three
    collinear corners), faces off screen, and copies of faces (exact depth ties, within a mesh and
    across meshes); faces shuffled so meshes and views interleave in the packed order."""
    rng = np.random.default_rng(seed)
    mesh_view = torch.tensor([0, 0, 1, 2, 0, 1, 2, 0])
    triangles, mesh = [], []
    for m, view in enumerate(mesh_view.tolist()):
        parts = [random_triangles(rng, 40, 0.0 if m == 2 else 1.0)]
        if view == 0:
            parts.append(grid_triangles(rng, 30))
        degenerate = random_triangles(rng, 4, 1.0)
        degenerate[:2, 2] = degenerate[:2, 0]  # repeated corner
        degenerate[2:, 2] = (degenerate[2:, 0] + degenerate[2:, 1]) / 2  # collinear
        off_screen = random_triangles(rng, 3, 1.0) + np.array([30.0, 0.0, 0.0])
        parts += [degenerate, off_screen]
        if m >= 4:  # copies of an earlier mesh's faces in the same view, and of this mesh's own
            earlier = next(i for i in range(m) if mesh_view[i] == view)
            parts.append(triangles[earlier][:15])
            parts.append(parts[0][:5])
        part = np.concatenate(parts)
        triangles.append(part)
        mesh.append(np.full(len(part), m))
    triangles, mesh = np.concatenate(triangles), np.concatenate(mesh)
    order = rng.permutation(len(mesh))
    verts = torch.as_tensor(triangles[order].reshape(-1, 3), dtype=dtype)
    faces = torch.arange(len(verts)).view(-1, 3)
    K = torch.stack(
        [
            torch.as_tensor(k, dtype=dtype)
            for k in [GRID_K, intrinsics(HEIGHT, WIDTH), intrinsics(HEIGHT, WIDTH, (0.05, -0.03)), GRID_K]
        ]
    )
    return verts, faces, torch.from_numpy(mesh[order]), K, mesh_view


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_compiled_path_equals_the_torch_path_bit_for_bit(seed, dtype):
    verts, faces, mesh_idx, K, mesh_view = crowded_scene(seed, dtype)
    compiled_out = rasterize_hard(verts, faces, mesh_idx, K, HEIGHT, WIDTH, mesh_view=mesh_view)
    with compiled.torch_paths_only():
        torch_out = rasterize_hard(verts, faces, mesh_idx, K, HEIGHT, WIDTH, mesh_view=mesh_view, chunk_size=1000)
    assert torch.equal(compiled_out.instance_map, torch_out.instance_map)
    assert torch.equal(compiled_out.depth_map, torch_out.depth_map)
    assert torch.equal(compiled_out.masks, torch_out.masks)
    torch.testing.assert_close(compiled_out.nearest_depth, torch_out.nearest_depth, rtol=0, atol=0, equal_nan=True)
    assert compiled_out.depth_map.dtype == dtype

    # The scene exercises what it claims: culled faces, covered pixels on edges, ties, an empty view.
    screen = project_faces(verts, faces, mesh_view[mesh_idx], K)
    assert (~screen.visible).sum() > 8 * 2  # two faces with a repeated corner per mesh, and more
    boxes = face_pixel_boxes(screen, 0.0, HEIGHT, WIDTH)
    assert (boxes.nx * boxes.ny == 0).sum() > (~screen.visible).sum()  # off-screen faces too
    on_edge = 0
    for f in torch.nonzero(boxes.nx * boxes.ny).squeeze(1).tolist():
        col = boxes.x0[f] + torch.arange(int(boxes.nx[f])).repeat(int(boxes.ny[f]))
        row = boxes.y0[f] + torch.arange(int(boxes.ny[f])).repeat_interleave(int(boxes.nx[f]))
        bary = torch.stack(
            screen_barycentrics(*pixel_centres(col, row, dtype), screen.plane_of(torch.full_like(col, f)))
        )
        on_edge += int(((bary >= 0).all(0) & (bary == 0).any(0)).sum())
    assert on_edge > 50
    covered = compiled_out.instance_map[:3] >= 0
    assert covered[0].sum() > 100 and covered[1].sum() > 100 and covered[2].sum() > 100
    assert (compiled_out.instance_map[3] == -1).all() and torch.isinf(compiled_out.depth_map[3]).all()


def test_exact_depth_ties_go_to_the_lower_face_index_on_both_paths():
    """The same triangle three times (faces 0, 1, 2 of meshes 2, 0, 1): every covered pixel shows face 0's mesh."""
    tri = torch.tensor([[-0.5, -0.5, 2.0], [0.5, -0.4, 2.5], [0.0, 0.6, 3.0]], dtype=torch.float64)
    verts, faces = tri.repeat(3, 1), torch.arange(9).view(3, 3)
    K = torch.as_tensor(intrinsics(16, 16))
    for torch_only in (False, True):
        with compiled.torch_paths_only() if torch_only else torch.no_grad():
            out = rasterize_hard(verts, faces, torch.tensor([2, 0, 1]), K, 16, 16)
        assert (out.instance_map >= 0).sum() > 20
        assert set(out.instance_map.unique().tolist()) == {-1, 2}
