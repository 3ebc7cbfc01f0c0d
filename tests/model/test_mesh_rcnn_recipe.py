"""Scene-Shapes' Mesh R-CNN (ShapeNet, sphere-init) architecture: plain R50, res2..res5 per vertex,
128-d stages that pass vertex features on, ico-sphere level 4, ImageNet init from a local file."""

import pytest
import torch

from usl.config import load_config
from usl.data import CategoryIndex, MultiViewDataset, SampleKey
from usl.geometry import ico_sphere
from usl.model.backbone import ShapeSpec
from usl.model.config import LayoutRange, ShapeHeadConfig
from usl.model.heads import ShapeHead, project_cube_to_image, roimap_features
from usl.model.usl_model import USLModel
from usl.records import RecordsDataset

CATEGORIES = ("chair", "sofa", "table")
RANGE = LayoutRange(z0=1.4, z1=2.0, rho0=0.1, rho1=1.0)  # docs/design.md §4, Scene-Shapes


def _linear_field(height, width, stride, scale):
    """(1, 2, H, W): channels ``scale * u`` and ``scale * v`` at each cell centre (input pixels)."""
    v, u = torch.meshgrid((torch.arange(height) + 0.5) * stride, (torch.arange(width) + 0.5) * stride, indexing="ij")
    return (scale * torch.stack([u, v]))[None]


def test_multi_map_roimap_samples_each_map_at_its_own_stride():
    """Linear fields at strides 4, 8, 16 (one 64 x 96 image): bilinear sampling reproduces them, so
    each map's channels must equal its scale times the vertex projection; and sampling all maps at
    once equals concatenating one call per map."""
    torch.manual_seed(0)
    strides, scales = (4, 8, 16), (1.0, -2.0, 0.5)
    maps = [
        _linear_field(64 // s, 96 // s, s, k).expand(2, -1, -1, -1).contiguous()
        for s, k in zip(strides, scales, strict=True)
    ]
    maps[1] = torch.cat([maps[1], torch.randn(2, 3, 8, 12)], dim=1)  # uneven channel counts: 2, 5, 2
    boxes = torch.tensor([[20.0, 12.0, 60.0, 44.0], [30.0, 20.0, 70.0, 50.0], [40.0, 16.0, 56.0, 40.0]])
    image_index = torch.tensor([1, 0, 1])
    verts = (torch.rand(3, 40, 3) * 2 - 1) * 0.9
    together = roimap_features(maps, strides, verts, boxes, image_index)
    assert together.shape == (3, 40, 9)
    uv = project_cube_to_image(verts, boxes)
    # inside the outermost cell centres of the coarsest map: no zero padding is blended in
    inner = ((uv > 8) & (uv < torch.tensor([88.0, 56.0]))).all(-1)
    for offset, scale in zip((0, 2, 7), scales, strict=True):
        assert torch.allclose(together[..., offset : offset + 2][inner], scale * uv[inner], atol=1e-3)
    one_by_one = torch.cat(
        [roimap_features([m], [s], verts, boxes, image_index) for m, s in zip(maps, strides, strict=True)], -1
    )
    torch.testing.assert_close(together, one_by_one)
    with pytest.raises(ValueError, match="2 feature maps for 3 strides"):
        roimap_features(maps[:2], strides, verts, boxes, image_index)


@pytest.mark.parametrize("sampler", ["roimap", "vertalign"])
def test_passed_features_widen_the_next_stage_and_carry_gradient(sampler):
    """Stage 1's offsets start at zero, so with pass_features off nothing of stage 1's GraphConvs
    reaches stage 2; with it on, stage 2's loss reaches them through the passed vertex features."""
    shapes = {"res2": ShapeSpec(4, 4), "res3": ShapeSpec(6, 8)}
    maps = {"res2": torch.randn(1, 4, 16, 16), "res3": torch.randn(1, 6, 8, 8)}
    boxes = [torch.tensor([[8.0, 8.0, 48.0, 56.0]])]
    grads = {}
    for passing in (False, True):
        torch.manual_seed(0)
        cfg = ShapeHeadConfig(
            ico_level=1,
            num_stages=2,
            num_graph_convs=2,
            hidden_dim=8,
            features=("res2", "res3"),
            pass_features=passing,
            sampler=sampler,
            graph_conv_init="kaiming",
        )
        head = ShapeHead(shapes, cfg)
        assert head.stages[0].bottleneck.in_features == 10  # 4 + 6 sampled channels
        assert [g.w0.in_features for g in head.stages[0].gconvs] == [8 + 3, 8 + 3]
        assert [g.w0.in_features for g in head.stages[1].gconvs] == [8 + 8 * passing + 3, 8 + 3]
        torch.nn.init.normal_(head.stages[1].offset.weight, std=0.1)
        head(maps, boxes).verts.square().sum().backward()
        grads[passing] = head.stages[0].gconvs[-1].w0.weight.grad.abs().sum().item()
    assert grads[False] == 0.0 and grads[True] > 0


def test_bottleneck_init_normal_is_mesh_rcnns():
    shapes = {"res2": ShapeSpec(3840, 4)}
    for init, std in (("normal", 0.01), ("torch", (3 * 3840) ** -0.5)):
        head = ShapeHead(shapes, ShapeHeadConfig(ico_level=0, num_stages=1, features=("res2",), bottleneck_init=init))
        bottleneck = head.stages[0].bottleneck
        assert bottleneck.weight.std().item() == pytest.approx(std, rel=0.05)
        assert (init == "torch") or torch.count_nonzero(bottleneck.bias) == 0


@pytest.fixture(scope="module")
def recipe_model():
    # An untrained detector keeps up to 100 detections, each a 2562 x 3840 vertex-feature array
    # per stage: 2 keep the test's detections-mode pass small.
    cfg = load_config("scene_shapes", ["model.detector.roi_heads.detections_per_image=2"])
    cfg.model.categories, cfg.model.layout_range = CATEGORIES, RANGE
    torch.manual_seed(0)
    return cfg, USLModel(cfg.model, cfg.loss)


def test_scene_shapes_recipe_builds_mesh_rcnns_shapenet_model(recipe_model):
    _, model = recipe_model
    backbone = model.detector.backbone
    assert not hasattr(backbone, "fpn")
    assert {k: (s.channels, s.stride) for k, s in backbone.output_shape().items()} == {
        "res2": (256, 4),
        "res3": (512, 8),
        "res4": (1024, 16),
        "res5": (2048, 32),
    }
    head = model.shape_head
    verts, faces = ico_sphere(4)
    assert head.sphere_verts.shape == (2562, 3) and head.faces.shape == (5120, 3) and len(verts) == 2562
    assert len(head.stages) == 3
    for index, stage in enumerate(head.stages):
        assert (stage.bottleneck.in_features, stage.bottleneck.out_features) == (3840, 128)
        widths = [(g.w0.in_features, g.w0.out_features) for g in stage.gconvs]
        first = 128 + 3 if index == 0 else 128 + 128 + 3  # stages 2 and 3 also take the previous features
        assert widths == [(first, 128), (131, 128), (131, 128)]
        assert (stage.offset.in_features, stage.offset.out_features) == (131, 3)
        assert stage.bottleneck.weight.std().item() == pytest.approx(0.01, rel=0.05)
        assert torch.count_nonzero(stage.offset.weight) == 0
    assert model.layout_head.mlp[0].in_features == 1024  # res4, as the RoI heads
    resnet = backbone.bottom_up  # trained whole, BatchNorm with batch statistics (torchvision's ResNet)
    assert all(p.requires_grad for n, p in resnet.named_parameters() if not n.startswith("fc."))
    assert isinstance(resnet.layer1[0].bn1, torch.nn.BatchNorm2d)
    assert model.detector.proposal_generator.in_features == ["res4"]
    assert model.detector.proposal_generator.anchor_generator.num_anchors_per_location == [15]


def test_scene_shapes_recipe_trains_and_detects_on_a_small_image(recipe_model, synthetic_root):
    """One 64 x 64 image, 2 views: a forward and backward pass of the whole recipe, then both
    predict modes (the detector is untrained there, but builds and runs on res4)."""
    cfg, model = recipe_model
    records = RecordsDataset(synthetic_root, "train")
    data_cfg = load_config("scene_shapes", [f"data.root={synthetic_root}", "data.num_views=2"]).data
    dataset = MultiViewDataset(records, data_cfg, CategoryIndex(records.categories), seed=0)
    sample = dataset[SampleKey(0, 0)]
    model.zero_grad()
    losses = model([sample])
    assert not any(k.startswith("det/") for k in losses)  # mu_2d = 0
    assert torch.isfinite(losses["loss"]) and losses["l3d"] > 0
    losses["loss"].backward()
    resnet = model.detector.backbone.bottom_up
    # Offsets start at zero (Mesh R-CNN's init), so at step 0 the shape loss reaches the offset
    # layers only; the layout head's loss reaches the backbone through res4.
    for param in (
        resnet.conv1.weight,
        resnet.layer3[-1].conv3.weight,
        model.layout_head.z_pred.weight,
        *(stage.offset.weight for stage in model.shape_head.stages),
    ):
        assert param.grad is not None and param.grad.abs().sum() > 0
    assert all(p.grad is None for p in model.detector.roi_heads.parameters())  # not trained without L_2D
    (pred,) = model.predict([sample.frame], mode="gt_boxes")
    assert pred.verts.shape == (len(sample.frame.boxes), 2562, 3) and torch.isfinite(pred.verts).all()
    (detected,) = model.predict([sample.frame], mode="detections")
    assert detected.verts.shape[1:] == (2562, 3)
    assert torch.all(detected.boxes[:, :2] >= 0) and torch.all(detected.boxes[:, 2:] <= 64)


def test_imagenet_init_from_a_local_torchvision_resnet50_file(tmp_path, capsys):
    """A torchvision ``resnet50`` state dict (names as torchvision writes them) fills the plain
    backbone exactly; the heads keep their initialisation. (An eighth-width R50 keeps the file
    small; its keys and the code path are the full recipe's.)"""
    generator = torch.Generator().manual_seed(0)
    reference = USLModel(_small_recipe().model, load_init_weights=False).detector.backbone.bottom_up
    state = {
        k: torch.randn(v.shape, generator=generator) if v.is_floating_point() else v
        for k, v in reference.state_dict().items()
    }
    state = {k: (v.abs() + 0.5 if k.endswith("running_var") else v) for k, v in state.items()}
    path = tmp_path / "resnet50-0676ba61.pth"
    torch.save(state, path)
    model = USLModel(_small_recipe([f"model.init_weights={path}"]).model)
    assert "resnet50-0676ba61.pth (torchvision ImageNet ResNet): loaded" in capsys.readouterr().err
    loaded = model.detector.backbone.bottom_up.state_dict()
    for key, value in state.items():
        if not key.endswith("num_batches_tracked"):
            assert torch.equal(loaded[key], value), key
    assert model.detector.backbone.bottom_up.stride_in_1x1 is False  # torchvision's ResNet v1.5
    assert torch.count_nonzero(model.shape_head.stages[0].offset.weight) == 0


def _small_recipe(overrides=()):
    cfg = load_config("scene_shapes", ["model.detector.backbone.resnet.base_channels=8", *overrides])
    cfg.model.categories, cfg.model.layout_range = CATEGORIES, RANGE
    return cfg
