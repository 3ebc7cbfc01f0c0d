"""The z-buffer rasterizer against pyrender: visible instance masks, depth maps, nearest depth."""

import numpy as np
import pytest
import torch

from tests.render.render_oracle import intrinsics, random_rigid, random_scene, render_pyrender
from usl.geometry.cameras import rigid_inverse, transform_points
from usl.render import rasterize_hard
from usl.utils import compiled

MIN_AREA = 150  # pixels; IoU >= 0.99 is only meaningful for objects this large


def pack(meshes, transforms):
    """Packed camera-frame vertices, faces and per-face mesh index for meshes given in the world."""
    verts, faces, mesh_idx, offset = [], [], [], 0
    for i, (mesh, world_to_cam) in enumerate(zip(meshes, transforms, strict=True)):
        v = transform_points(torch.as_tensor(mesh.vertices, dtype=torch.float64), world_to_cam)
        verts.append(v)
        faces.append(torch.as_tensor(mesh.faces, dtype=torch.long) + offset)
        mesh_idx.append(torch.full((len(mesh.faces),), i, dtype=torch.long))
        offset += len(v)
    return torch.cat(verts), torch.cat(faces), torch.cat(mesh_idx)


def iou(a, b):
    return (a & b).sum() / max((a | b).sum(), 1)


@pytest.mark.parametrize("height,width,seed", [(128, 128, 0), (96, 160, 1), (150, 100, 2)])
def test_hard_rasterizer_matches_pyrender_in_two_views_one_tilt_shift(height, width, seed):
    rng = np.random.default_rng(seed)
    objects_cam = random_scene(rng, 5)
    first_to_world = random_rigid(rng)
    world = [m.copy().apply_transform(first_to_world) for m in objects_cam]
    # View 2 looks at the same objects from a slightly moved camera with a tilt-shift K.
    nudge = np.eye(4)
    nudge[:3, 3] = [0.15, -0.1, 0.05]
    views = [
        (first_to_world, intrinsics(height, width)),
        (first_to_world @ nudge, intrinsics(height, width, (0.04, -0.03))),
    ]

    meshes, transforms, mesh_view = [], [], []
    for j, (cam_to_world, _) in enumerate(views):
        world_to_cam = rigid_inverse(torch.as_tensor(cam_to_world))
        meshes += world
        transforms += [world_to_cam] * len(world)
        mesh_view += [j] * len(world)
    verts, faces, mesh_idx = pack(meshes, transforms)
    K = torch.as_tensor(np.stack([k for _, k in views]))
    out = rasterize_hard(verts, faces, mesh_idx, K, height, width, mesh_view=torch.tensor(mesh_view))

    checked = 0
    for j, (cam_to_world, K_j) in enumerate(views):
        instance_ref, depth_ref, _ = render_pyrender(world, cam_to_world, K_j, height, width)
        instance = out.instance_map[j].numpy() - j * len(world)
        instance[out.instance_map[j].numpy() < 0] = -1
        foreground = (instance >= 0) | (instance_ref >= 0)
        assert (instance == instance_ref)[foreground].mean() > 0.99
        for i in range(len(world)):
            m = j * len(world) + i
            ref = instance_ref == i
            assert np.array_equal(out.masks[m].numpy(), instance == i)
            if ref.sum() >= MIN_AREA:
                assert iou(out.masks[m].numpy(), ref) >= 0.99, (j, i)
                assert abs(out.nearest_depth[m].item() - depth_ref[ref].min()) < 1e-3
                checked += 1
            elif ref.sum() == 0 and out.masks[m].sum() == 0:
                assert torch.isnan(out.nearest_depth[m])
        agree = (instance == instance_ref) & (instance >= 0)
        depth = out.depth_map[j].numpy()
        assert np.abs(depth[agree] - depth_ref[agree]).max() < 1e-3
        assert np.isinf(depth[instance < 0]).all()
    assert checked >= 4


def test_single_view_k_gives_unbatched_maps_and_faces_behind_the_camera_are_culled():
    # Triangle 0 in front; triangle 1 has a vertex behind the camera and must vanish.
    verts = torch.tensor(
        [[-1.0, -1.0, 2.0], [1.0, -1.0, 2.0], [0.0, 1.0, 2.0], [-1.0, 0.0, 1.0], [1.0, 0.0, 1.0], [0.0, 0.5, -0.5]]
    )
    faces = torch.tensor([[0, 1, 2], [3, 4, 5]])
    K = torch.tensor([[20.0, 0.0, 16.0], [0.0, 20.0, 16.0], [0.0, 0.0, 1.0]])
    out = rasterize_hard(verts, faces, torch.tensor([0, 1]), K, 32, 32)
    assert out.instance_map.shape == (32, 32) and out.depth_map.shape == (32, 32)
    assert out.masks.shape == (2, 32, 32)
    assert out.masks[0].sum() > 50 and out.masks[1].sum() == 0
    assert torch.allclose(out.depth_map[out.masks[0]], torch.tensor(2.0))
    assert out.nearest_depth[0] == pytest.approx(2.0) and torch.isnan(out.nearest_depth[1])


def test_chunking_does_not_change_the_result():
    rng = np.random.default_rng(5)
    meshes = random_scene(rng, 4)
    verts, faces, mesh_idx = pack(meshes, [torch.eye(4, dtype=torch.float64)] * len(meshes))
    K = torch.as_tensor(intrinsics(64, 80, (0.02, 0.01)))
    with compiled.torch_paths_only():  # chunks are the torch path's
        whole = rasterize_hard(verts, faces, mesh_idx, K, 64, 80)
        chunked = rasterize_hard(verts, faces, mesh_idx, K, 64, 80, chunk_size=97)
    assert torch.equal(whole.instance_map, chunked.instance_map)
    assert torch.equal(whole.depth_map, chunked.depth_map)
