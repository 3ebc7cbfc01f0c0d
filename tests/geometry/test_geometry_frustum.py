"""Frustum homography: corners, inverse-depth spacing, round trips, projectivity, gradients.

Oracles: ``cameras.project`` (the camera convention owned elsewhere) for where points must
land, and float64 finite differences for gradients.
"""

import itertools

import pytest
import torch

from usl.geometry.cameras import project
from usl.geometry.frustum import MIN_NEAR_DEPTH, cube_to_frustum, frustum_homography, frustum_to_cube

DT = torch.float64
K_PINHOLE = torch.tensor([[500.0, 0.0, 320.0], [0.0, 480.0, 240.0], [0.0, 0.0, 1.0]], dtype=DT)
# Tilt-shift-like camera: last row is not [0, 0, 1], as in some Hypersim scenes.
K_TILT = torch.tensor([[520.0, 12.0, 300.0], [-8.0, 500.0, 250.0], [0.03, -0.05, 1.0]], dtype=DT)
CAMERAS = pytest.mark.parametrize("K", [K_PINHOLE, K_TILT], ids=["pinhole", "tilt_shift"])

BOX = torch.tensor([100.0, 80.0, 260.0, 300.0], dtype=DT)
Z, RHO = torch.tensor(2.5, dtype=DT), torch.tensor(1.2, dtype=DT)
CORNERS = torch.tensor(list(itertools.product([-1.0, 1.0], repeat=3)), dtype=DT)


@CAMERAS
def test_cube_corners_land_on_box_corners_at_near_and_far_depth(K):
    points = cube_to_frustum(CORNERS, BOX, K, Z, RHO)
    uv, depth = project(points, K)
    expected_u = torch.where(CORNERS[:, 0] < 0, BOX[0], BOX[2])
    expected_v = torch.where(CORNERS[:, 1] < 0, BOX[1], BOX[3])
    expected_d = torch.where(CORNERS[:, 2] < 0, Z - RHO / 2, Z + RHO / 2)
    torch.testing.assert_close(uv, torch.stack([expected_u, expected_v], dim=1))
    torch.testing.assert_close(depth, expected_d)
    torch.testing.assert_close(frustum_to_cube(points, BOX, K, Z, RHO), CORNERS)


def test_pinhole_depth_is_planar_z_and_w_is_linear_in_inverse_depth():
    w = torch.linspace(-1, 1, 9, dtype=DT)
    cube = torch.stack([torch.zeros_like(w), torch.zeros_like(w), w], dim=1)
    points = cube_to_frustum(cube, BOX, K_PINHOLE, Z, RHO)
    near, far = Z - RHO / 2, Z + RHO / 2
    expected_inv = 1 / near + (w + 1) / 2 * (1 / far - 1 / near)
    torch.testing.assert_close(1 / points[:, 2], expected_inv)


@CAMERAS
def test_round_trips(K):
    gen = torch.Generator().manual_seed(0)
    cube = torch.rand(4, 50, 3, generator=gen, dtype=DT) * 2 - 1
    boxes = torch.tensor([[10.0, 20, 90, 60], [200, 100, 210, 400], [0, 0, 640, 480], [300, 300, 301, 302]], dtype=DT)
    z = torch.tensor([1.0, 3.0, 8.0, 0.7], dtype=DT)
    rho = torch.tensor([0.5, 2.0, 1.0, 0.3], dtype=DT)
    points = cube_to_frustum(cube, boxes, K, z, rho)
    torch.testing.assert_close(frustum_to_cube(points, boxes, K, z, rho), cube)
    # and the other way: camera points in front of the camera
    cam = torch.rand(4, 50, 3, generator=gen, dtype=DT) * torch.tensor([2.0, 2.0, 4.0], dtype=DT) + torch.tensor(
        [-1.0, -1.0, 0.5], dtype=DT
    )
    torch.testing.assert_close(cube_to_frustum(frustum_to_cube(cam, boxes, K, z, rho), boxes, K, z, rho), cam)


@CAMERAS
def test_straight_lines_stay_straight(K):
    gen = torch.Generator().manual_seed(1)
    ends = torch.rand(20, 2, 3, generator=gen, dtype=DT) * 2 - 1
    t = torch.linspace(0, 1, 7, dtype=DT)[None, :, None]
    lines = ends[:, :1] + t * (ends[:, 1:] - ends[:, :1])  # (20, 7, 3) collinear cube points
    points = cube_to_frustum(lines, BOX, K, Z, RHO)
    direction = points[:, -1:] - points[:, :1]
    offsets = points - points[:, :1]
    cross = torch.linalg.cross(offsets, direction.expand_as(offsets), dim=-1)
    # distance of every point from the line through the end points, relative to the segment length
    rel = cross.norm(dim=-1) / direction.norm(dim=-1).pow(2)
    assert rel.max() < 1e-10
    # the map is not affine in depth: midpoints do not map to midpoints
    mid = cube_to_frustum(0.5 * (ends[:, :1] + ends[:, 1:]), BOX, K, Z, RHO)
    assert (mid - 0.5 * (points[:, :1] + points[:, -1:])).norm(dim=-1).max() > 1e-3


@CAMERAS
def test_matrix_agrees_with_function(K):
    gen = torch.Generator().manual_seed(2)
    boxes = torch.tensor([[10.0, 20, 90, 60], [200, 100, 260, 400]], dtype=DT)
    z, rho = torch.tensor([1.5, 4.0], dtype=DT), torch.tensor([0.4, 3.0], dtype=DT)
    cube = torch.rand(2, 30, 3, generator=gen, dtype=DT) * 2 - 1
    H = frustum_homography(boxes, K, z, rho)
    assert H.shape == (2, 4, 4)
    h = torch.cat([cube, torch.ones_like(cube[..., :1])], -1) @ H.transpose(-1, -2)
    torch.testing.assert_close(h[..., :3] / h[..., 3:], cube_to_frustum(cube, boxes, K, z, rho))


def test_broadcasting_shared_camera_and_batched_objects():
    boxes = BOX.expand(3, 5, 4)
    z = torch.full((3, 5), 2.0, dtype=DT)
    rho = torch.full((3, 5), 1.0, dtype=DT)
    cube = torch.zeros(3, 5, 2, 3, dtype=DT)
    out = cube_to_frustum(cube, boxes, K_PINHOLE, z, rho)
    assert out.shape == (3, 5, 2, 3)
    assert frustum_homography(boxes, K_PINHOLE, z, rho).shape == (3, 5, 4, 4)


def test_near_plane_is_clamped_in_front_of_the_camera():
    near_corners = CORNERS[CORNERS[:, 2] < 0]
    points = cube_to_frustum(near_corners, BOX, K_PINHOLE, torch.tensor(0.2, dtype=DT), torch.tensor(1.0, dtype=DT))
    torch.testing.assert_close(points[:, 2], torch.full((4,), MIN_NEAR_DEPTH, dtype=DT))
    # far beyond the far plane the inverse depth is clamped instead of crossing infinity
    far = cube_to_frustum(torch.tensor([[0.0, 0.0, 50.0]], dtype=DT), BOX, K_PINHOLE, Z, RHO)
    assert torch.isfinite(far).all() and far[0, 2] > 0


@CAMERAS
def test_gradcheck_points_box_depth_extent(K):
    gen = torch.Generator().manual_seed(3)
    cube = (torch.rand(2, 4, 3, generator=gen, dtype=DT) * 2 - 1).requires_grad_()
    boxes = torch.tensor([[100.0, 80, 260, 300], [10, 20, 40, 90]], dtype=DT, requires_grad=True)
    z = torch.tensor([2.5, 1.4], dtype=DT, requires_grad=True)
    rho = torch.tensor([1.2, 0.5], dtype=DT, requires_grad=True)
    assert torch.autograd.gradcheck(lambda c, b, zz, r: cube_to_frustum(c, b, K, zz, r), (cube, boxes, z, rho))
    cam = cube_to_frustum(cube, boxes, K, z, rho).detach().requires_grad_()
    assert torch.autograd.gradcheck(lambda p, b, zz, r: frustum_to_cube(p, b, K, zz, r), (cam, boxes, z, rho))
    assert torch.autograd.gradcheck(lambda b, zz, r: frustum_homography(b, K, zz, r), (boxes, z, rho))
