"""Layout head, shape head, GraphConv and vertex samplers against independent oracles."""

import numpy as np
import pytest
import torch

from usl.geometry import cube_to_frustum, ico_sphere, unique_edges
from usl.geometry.cameras import project
from usl.model.backbone import ShapeSpec
from usl.model.config import LayoutHeadConfig, LayoutRange, ShapeHeadConfig
from usl.model.heads import GraphConv, LayoutHead, ShapeHead, project_cube_to_image, roimap_features, vertalign_features
from usl.model.heads.layout import box_geometry
from usl.model.heads.vertex_features import single_level_pooler

RANGE = LayoutRange(z0=1.0, z1=5.0, rho0=0.2, rho1=2.0)


def test_graph_conv_matches_dense_adjacency():
    torch.manual_seed(0)
    verts, faces = ico_sphere(1)
    conv = GraphConv(5, 4)
    x = torch.randn(2, len(verts), 5)
    adjacency = np.zeros((len(verts), len(verts)))
    for a, b, c in faces.tolist():  # built from faces with numpy, not from unique_edges
        for i, j in ((a, b), (b, c), (c, a)):
            adjacency[i, j] = adjacency[j, i] = 1
    A = torch.tensor(adjacency, dtype=torch.float32)
    expected = conv.w0(x) + A @ conv.w1(x)
    assert torch.allclose(conv(x, unique_edges(faces)), expected, atol=1e-6)


def test_graph_conv_equals_the_advanced_indexing_form_bit_for_bit():
    """GraphConv gathers with index_select (its backward an index_add); the advanced-indexing
    gather ``message[:, b]`` (backward: an accumulating index_put), adds the same terms in the same order,
    so values and gradients are equal, not merely close."""
    torch.manual_seed(0)
    verts, faces = ico_sphere(2)
    edges = unique_edges(faces)
    conv = GraphConv(67, 64, "kaiming")

    def advanced_indexing(x: torch.Tensor) -> torch.Tensor:
        own, message = conv.w0(x), conv.w1(x)
        a, b = edges[:, 0], edges[:, 1]
        return own.index_add(1, a, message[:, b]).index_add(1, b, message[:, a])

    x = torch.randn(8, len(verts), 67, requires_grad=True)
    weight = torch.randn(8, len(verts), 64)
    results = []
    for forward in (lambda x: conv(x, edges), advanced_indexing):
        y = forward(x)
        results.append([y, *torch.autograd.grad((y * weight).sum(), [x, *conv.parameters()])])
    assert all(torch.equal(new, old) for new, old in zip(*results, strict=True))


def test_graph_conv_inits_mesh_rcnn_small_weights_or_a_scale_keeping_kaiming():
    """Three GraphConvs on a smooth vertex signal (positions and features that vary slowly over an
    ico-sphere): Mesh R-CNN's N(0, 0.01²) shrinks the signal ~5x a layer, "kaiming" keeps it."""
    torch.manual_seed(0)
    verts, faces = ico_sphere(3)
    edges = unique_edges(faces)
    smooth = torch.cat([verts, torch.sin(3 * verts), torch.cos(2 * verts)], dim=-1).repeat(4, 1, 8)[..., :64]
    scales = {}
    for init in ("normal", "kaiming"):
        x = smooth
        for _ in range(3):
            conv = GraphConv(x.shape[-1], 64, init)
            x = torch.relu(conv(x, edges))
        scales[init] = (x.pow(2).mean() / smooth.pow(2).mean()).sqrt().item()
        assert torch.count_nonzero(conv.w0.bias) == 0 and torch.count_nonzero(conv.w1.bias) == 0
    assert scales["normal"] < 0.05
    assert 0.3 < scales["kaiming"] < 3.0
    assert GraphConv(10, 4, "normal").w0.weight.std().item() == pytest.approx(0.01, rel=0.3)
    with pytest.raises(ValueError, match="init must be one of"):
        GraphConv(3, 3, "xavier")


K_SIMPLE = torch.tensor([[200.0, 0.0, 64.0], [0.0, 180.0, 48.0], [0.0, 0.0, 1.0]])


def test_layout_head_ranges_and_category_specific_outputs():
    torch.manual_seed(0)
    head = LayoutHead(8, 3, LayoutHeadConfig(fc_dim=16), RANGE)
    feats = torch.randn(5, 8, 7, 7)
    boxes, K = torch.tensor([[10.0, 12.0, 40.0, 50.0]]).expand(5, 4), K_SIMPLE.expand(5, 3, 3)
    out = head(feats, torch.tensor([0, 1, 2, 0, 1]), boxes, K)
    assert out.z.shape == out.rho.shape == (5,)
    assert torch.allclose(out.z, torch.full((5,), 3.0), atol=0.01)  # fresh head: mid-range
    with torch.no_grad():
        head.z_pred.bias.copy_(torch.tensor([-50.0, 0.0, 50.0]))
        head.rho_pred.bias.copy_(torch.tensor([50.0, -50.0, 0.0]))
    out = head(feats, torch.tensor([0, 1, 2, 0, 1]), boxes, K)
    assert torch.allclose(out.z, torch.tensor([1.0, 3.0, 5.0, 1.0, 3.0]), atol=1e-3)
    assert torch.allclose(out.rho, torch.tensor([2.0, 0.2, 1.1, 2.0, 0.2]), atol=1e-3)
    with pytest.raises(ValueError, match="layout range"):
        LayoutHead(8, 3, LayoutHeadConfig(), LayoutRange())


def test_box_geometry_is_the_pinhole_rays_of_the_box_corners_and_ignores_resolution():
    boxes = torch.tensor([[10.0, 12.0, 40.0, 50.0], [60.0, 30.0, 64.0, 96.0]])
    got = box_geometry(boxes, K_SIMPLE.expand(2, 3, 3))
    fx, fy, cx, cy = 200.0, 180.0, 64.0, 48.0  # x = (u - cx) / fx for a skew-free pinhole K
    x0, y0, x1, y1 = (boxes[:, 0] - cx) / fx, (boxes[:, 1] - cy) / fy, (boxes[:, 2] - cx) / fx, (boxes[:, 3] - cy) / fy
    want = torch.stack([x0, y0, x1, y1, (x1 - x0).log(), (y1 - y0).log()], dim=1)
    torch.testing.assert_close(got, want)
    # The same boxes in the image resized by 2.5 x 0.5 (K scaled with it) describe the same rays.
    scale = torch.tensor([2.5, 0.5, 2.5, 0.5])
    K_resized = torch.diag(torch.tensor([2.5, 0.5, 1.0])) @ K_SIMPLE
    torch.testing.assert_close(box_geometry(boxes * scale, K_resized.expand(2, 3, 3)), want)


def test_layout_head_sees_the_box_only_with_box_geometry():
    torch.manual_seed(0)
    feats, labels = torch.randn(2, 8, 7, 7), torch.tensor([1, 1])
    near_box = torch.tensor([[20.0, 10.0, 100.0, 90.0]])  # the same features, a 4x larger box
    far_box = torch.tensor([[50.0, 40.0, 70.0, 60.0]])
    for enabled in (False, True):
        head = LayoutHead(8, 3, LayoutHeadConfig(fc_dim=16, box_geometry=enabled), RANGE)
        assert head.mlp[0].in_features == 8 + (6 if enabled else 0)
        torch.nn.init.normal_(head.z_pred.weight, std=1.0)
        z = [head(feats[:1], labels[:1], box, K_SIMPLE[None]).z for box in (near_box, far_box)]
        assert (z[0] != z[1]).item() is enabled


def test_cube_projection_equals_the_frustum_homography_projection():
    """RoIMap samples at box_centre + half * (x, y): the image of the cube point through the
    frustum homography, for any depth and a tilt-shift (non upper-triangular) K."""
    torch.manual_seed(1)
    K = torch.tensor([[300.0, 2.0, 160.0], [0.0, 310.0, 120.0], [0.001, 0.002, 1.0]], dtype=torch.float64)
    boxes = torch.tensor([[40.0, 30.0, 140.0, 90.0], [100.0, 100.0, 120.0, 180.0]], dtype=torch.float64)
    verts = torch.rand(2, 50, 3, dtype=torch.float64) * 2 - 1
    cam = cube_to_frustum(
        verts, boxes, K, torch.tensor([2.0, 4.0], dtype=torch.float64), torch.tensor([0.5, 1.0], dtype=torch.float64)
    )
    uv, _ = project(cam, K)
    assert torch.allclose(project_cube_to_image(verts, boxes), uv, atol=1e-8)


def _linear_field(batch, height, width, stride):
    """Feature map whose channels are u, v and 1 at each cell centre (in input pixels)."""
    v, u = torch.meshgrid((torch.arange(height) + 0.5) * stride, (torch.arange(width) + 0.5) * stride, indexing="ij")
    field = torch.stack([u, v, torch.ones_like(u)])
    return field.expand(batch, 3, height, width).contiguous()


def test_roimap_samples_the_backbone_map_at_vertex_projections():
    stride = 4
    fmap = _linear_field(2, 16, 20, stride)  # an 80 x 64 image
    boxes = torch.tensor([[10.0, 8.0, 50.0, 40.0], [30.0, 20.0, 70.0, 56.0], [12.0, 12.0, 20.0, 30.0]])
    image_index = torch.tensor([0, 1, 1])
    verts = torch.rand(3, 30, 3) * 2 - 1
    feats = roimap_features([fmap], [stride], verts, boxes, image_index)
    uv = project_cube_to_image(verts, boxes)
    # bilinear interpolation reproduces a linear field exactly between cell centres
    assert torch.allclose(feats[..., :2], uv, atol=1e-4)
    assert torch.allclose(feats[..., 2], torch.ones(3, 30))


def test_vertalign_agrees_with_roimap_inside_the_roi():
    stride, resolution = 4, 14
    fmap = _linear_field(1, 16, 16, stride)
    boxes = torch.tensor([[12.0, 8.0, 52.0, 40.0]])
    pooled = single_level_pooler("p2", stride, resolution)({"p2": fmap}, [boxes])
    inner = 1 - 1 / resolution  # beyond the outer bin centres grid_sample blends with zero padding
    verts = (torch.rand(1, 40, 3) * 2 - 1) * inner
    via_roi = vertalign_features(pooled, verts)
    direct = roimap_features([fmap], [stride], verts, boxes, torch.tensor([0]))
    assert torch.allclose(via_roi, direct, atol=1e-3)


@pytest.mark.parametrize("sampler", ["roimap", "vertalign"])
def test_shape_head_shapes_init_and_gradients(sampler):
    torch.manual_seed(0)
    cfg = ShapeHeadConfig(ico_level=1, num_stages=2, hidden_dim=16, sampler=sampler)
    head = ShapeHead({"p2": ShapeSpec(8, 4)}, cfg)
    fmap = torch.randn(2, 8, 16, 16, requires_grad=True)
    boxes = [torch.tensor([[4.0, 4.0, 40.0, 30.0]]), torch.tensor([[10.0, 10.0, 60.0, 60.0], [0.0, 0.0, 20.0, 20.0]])]
    out = head({"p2": fmap}, boxes)
    sphere, faces = ico_sphere(1)
    assert out.verts.shape == (3, len(sphere), 3) and head.faces.shape == faces.shape
    assert len(out.stage_verts) == len(out.offsets) == 2
    assert torch.allclose(out.verts, sphere.expand(3, -1, -1))  # zero-initialised offsets
    with torch.no_grad():
        head.stages[0].offset.bias.fill_(10.0)  # pre-tanh offsets: dV = tanh(.) stays within (-1, 1)
    out = head({"p2": fmap}, boxes)
    assert torch.allclose(out.stage_verts[0] - sphere, torch.ones(1), atol=1e-6)
    assert torch.allclose(out.offsets[0], torch.full_like(out.offsets[0], 10.0))
    # features reach the second stage's offsets, and gradients reach the feature map
    torch.nn.init.normal_(head.stages[1].offset.weight, std=0.1)
    head({"p2": fmap}, boxes).verts.square().sum().backward()
    assert fmap.grad is not None and fmap.grad.abs().sum() > 0
    assert head.stages[1].bottleneck.weight.grad.abs().sum() > 0


def test_global_stage_starts_as_the_sphere_and_deforms_each_vertex_from_the_roi_features():
    torch.manual_seed(0)
    cfg = ShapeHeadConfig(ico_level=1, num_stages=1, hidden_dim=16, global_stage=32)
    roi_dim = 8 * 3 * 3
    head = ShapeHead({"p2": ShapeSpec(8, 4)}, cfg, roi_dim=roi_dim)
    fmap = torch.randn(1, 8, 16, 16)
    boxes = [torch.tensor([[4.0, 4.0, 40.0, 30.0], [10.0, 10.0, 60.0, 60.0]])]
    roi = torch.randn(2, 8, 3, 3, requires_grad=True)
    out = head({"p2": fmap}, boxes, roi=roi)
    sphere, _ = ico_sphere(1)
    assert len(out.stage_verts) == len(out.offsets) == 2  # the global stage, then the refinement stage
    torch.testing.assert_close(out.verts, sphere.expand(2, -1, -1))  # zero-initialised last layer
    # one offset per vertex and coordinate, from the flattened RoI features: V_g = sphere + tanh(MLP(roi))
    last = head.global_mlp[-1]
    with torch.no_grad():
        last.bias.copy_(torch.linspace(-2, 2, last.bias.numel()))
    out = head({"p2": fmap}, boxes, roi=roi)
    expected = sphere + torch.tanh(torch.linspace(-2, 2, last.bias.numel())).view(-1, 3)
    torch.testing.assert_close(out.stage_verts[0], expected.expand(2, -1, -1))
    torch.nn.init.normal_(last.weight, std=0.1)
    out = head({"p2": fmap}, boxes, roi=roi)
    assert not torch.allclose(out.stage_verts[0][0], out.stage_verts[0][1])  # each object its own shape
    out.verts.square().sum().backward()
    assert roi.grad is not None and roi.grad.abs().sum() > 0
    with pytest.raises(ValueError, match="roi"):
        head({"p2": fmap}, boxes)
    with pytest.raises(ValueError, match="roi_dim"):
        ShapeHead({"p2": ShapeSpec(8, 4)}, cfg)
