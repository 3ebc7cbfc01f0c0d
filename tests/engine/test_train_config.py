"""Recipes, YAML loading and key=value overrides (usl.config)."""
import pytest

from usl.config import Config, ConfigError, config_from_dict, load_config, parse_overrides, save_config, to_dict
from usl.model.detector import DetectorConfig


def test_recipes_follow_the_papers_recipe_table():
    shapes, hypersim, scannet = (load_config(n) for n in ("scene_shapes", "hypersim", "scannet"))
    assert (shapes.optim.name, shapes.optim.lr, shapes.optim.max_iter) == ("adam", 1e-3, 30000)
    assert shapes.loss.weights.mu_2d == 0 and shapes.loss.weights.edge == 0.1 and shapes.loss.weights.offset_l2 == 0
    assert shapes.loss.render.resolution == 128 and shapes.model.shape.num_stages == 3
    assert (hypersim.optim.name, hypersim.optim.lr, hypersim.optim.max_iter) == ("sgd", 1e-2, 80000)
    assert hypersim.loss.weights.offset_l2 == 0.05 and hypersim.loss.weights.mu_3d == 1.0
    assert hypersim.loss.render.resolution == 72 and hypersim.model.shape.num_stages == 3
    assert scannet.model.shape.num_stages == 1 and scannet.optim.max_iter == 200000
    assert scannet.loss.weights.laplacian == 0.1 and scannet.loss.weights.offset_l2 == 0.05
    assert scannet.data.view_sampling == "time_distance" and scannet.optim.name == "sgd"  # inherited
    for cfg in (shapes, hypersim, scannet):
        assert cfg.model.shape.ico_level == 3 and cfg.model.shape.sampler == "roimap"
        assert cfg.model.detector.backbone.resnet.depth == 50


def test_tiny_recipe_uses_the_detectors_tiny_network():
    tiny = load_config("tiny")
    assert to_dict(tiny.model.detector) == to_dict(DetectorConfig.tiny())
    assert tiny.model.shape.ico_level == 2 and tiny.optim.name == "adam"


def test_overrides_are_typed_and_nested():
    cfg = load_config("hypersim", ["optim.lr=1e-3", "optim.steps=[10, 20]", "data.root=/data/x",
                                   "model.shape.num_stages=1", "loss.weights.laplacian=0.5"])
    assert cfg.optim.lr == 1e-3 and cfg.optim.steps == (10, 20) and cfg.data.root == "/data/x"
    assert cfg.model.shape.num_stages == 1 and cfg.loss.weights.laplacian == 0.5
    assert parse_overrides(["a.b=1", "a.c=x"]) == {"a": {"b": 1, "c": "x"}}


@pytest.mark.parametrize(
    "overrides, message",
    [
        (["optim.lrr=1"], r"config\.optim: unknown key\(s\) \['lrr'\]"),
        (["optim.lr=fast"], r"config\.optim\.lr: expected float"),
        (["optim.name=rmsprop"], r"optim\.name: 'rmsprop' is not one of"),
        (["model.shape.num_stages=2.5"], r"num_stages: expected int"),
        (["optim.steps=3"], r"optim\.steps: expected a list"),
        (["model.detector_preset=huge"], r"detector_preset: 'huge' is not one of"),
        (["lr"], r"expected key=value"),
    ],
)
def test_bad_overrides_name_the_key_and_the_file(overrides, message):
    with pytest.raises(ConfigError, match=message) as info:
        load_config("tiny", overrides)
    if "=" in overrides[0]:
        assert "tiny.yaml" in str(info.value)


def test_bad_files(tmp_path):
    with pytest.raises(ConfigError, match="no such file"):
        load_config(tmp_path / "missing.yaml")
    with pytest.raises(ConfigError, match="built-in recipes"):
        load_config("hypersimm")
    loop = tmp_path / "loop.yaml"
    loop.write_text("_base_: loop.yaml\n")
    with pytest.raises(ConfigError, match="loops"):
        load_config(loop)
    listed = tmp_path / "list.yaml"
    listed.write_text("- 1\n- 2\n")
    with pytest.raises(ConfigError, match="must hold a mapping"):
        load_config(listed)


def test_saved_config_reloads_identically(tmp_path):
    cfg = load_config("scannet", ["data.root=/somewhere", "model.categories=[chair, tv]"])
    save_config(cfg, tmp_path / "config.yaml")
    assert load_config(tmp_path / "config.yaml") == cfg
    assert config_from_dict(to_dict(cfg)) == cfg
    assert config_from_dict({}) == Config()


def test_paper_recipes_keep_the_papers_loss_and_init_while_tiny_documents_its_changes():
    """Issue F's CPU-scale findings are options: only `tiny` turns them on."""
    for name in ("scene_shapes", "hypersim", "scannet"):
        cfg = load_config(name)
        assert cfg.loss.gate_input_view and not cfg.loss.ignore_occluders, name
        assert cfg.loss.dist_schedule.iters == () and cfg.loss.dist_schedule(10**5) == 1.0, name
        assert cfg.model.shape.graph_conv_init == "normal" and cfg.loss.iou_threshold == 0.5, name
    tiny = load_config("tiny")
    assert not tiny.loss.gate_input_view and tiny.loss.ignore_occluders
    assert tiny.model.shape.graph_conv_init == "kaiming" and tiny.loss.render.resolution == 64
    assert tiny.loss.dist_schedule(0) == 1.0 and tiny.loss.dist_schedule(tiny.optim.max_iter) < 1.0
