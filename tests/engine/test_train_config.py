"""Recipes, YAML loading, key=value overrides (usl.config) and usl-train's config command line."""

import copy
import dataclasses
import inspect
import itertools
import re
import typing
from pathlib import Path

import pytest
import yaml

from usl.cli.train import main as train_main
from usl.cli.train import parse_args
from usl.config import (
    CONFIG_DIR,
    Config,
    ConfigError,
    config_from_dict,
    load_config,
    parse_overrides,
    resolve_config_path,
    save_config,
    to_dict,
)
from usl.config_docs import field_docs, iter_keys
from usl.data.config import DataConfig
from usl.model.config import ModelConfig
from usl.model.detector import DetectorConfig

RECIPE_NAMES = sorted(path.stem for path in CONFIG_DIR.glob("*.yaml"))


def test_recipes_follow_the_papers_recipe_table():
    shapes, hypersim, scannet = (load_config(n) for n in ("scene_shapes", "hypersim", "scannet"))
    assert (shapes.optim.name, shapes.optim.lr, shapes.optim.max_iter) == ("adam", 1e-3, 30000)
    assert shapes.loss.weights.mu_2d == 0 and shapes.loss.weights.edge == 0.1 and shapes.loss.weights.offset_l2 == 0
    assert shapes.loss.render.resolution == 128 and shapes.model.shape.num_stages == 3
    assert (hypersim.optim.name, hypersim.optim.lr, hypersim.optim.max_iter) == ("sgd", 1e-2, 80000)
    assert hypersim.loss.weights.offset_l2 == 0.05 and hypersim.loss.weights.mu_3d == 1.0
    assert hypersim.loss.render.resolution == 72 and hypersim.model.shape.num_stages == 3
    assert hypersim.optim.steps == (66000, 74000) and scannet.optim.steps == (150000, 170000)
    assert scannet.model.shape.num_stages == 1 and scannet.optim.max_iter == 200000
    assert scannet.loss.weights.laplacian == 0.1 and scannet.loss.weights.offset_l2 == 0.05
    assert scannet.data.view_sampling == "time_distance" and scannet.optim.name == "sgd"  # inherited
    for cfg in (shapes, hypersim, scannet):
        assert cfg.model.shape.sampler == "roimap" and cfg.model.detector.backbone.resnet.depth == 50
    for cfg in (hypersim, scannet):  # the paper's Appendix tables: R50-FPN p2, ico3, 256-d, no passing
        assert cfg.model.detector.backbone.name == "resnet_fpn" and cfg.model.shape.features == ("p2",)
        assert (
            cfg.model.shape.ico_level == 3 and cfg.model.shape.hidden_dim == 256 and not cfg.model.shape.pass_features
        )
    # Scene-Shapes: Mesh R-CNN's ShapeNet sphere-init model (meshrcnn configs/shapenet/sphereinit_R50.yaml)
    assert shapes.model.detector.backbone.name == "resnet" and shapes.model.shape.features == (
        "res2",
        "res3",
        "res4",
        "res5",
    )
    assert (shapes.model.shape.ico_level, shapes.model.shape.hidden_dim, shapes.model.shape.num_graph_convs) == (
        4,
        128,
        3,
    )
    assert shapes.model.shape.pass_features and shapes.model.shape.bottleneck_init == "normal"
    assert shapes.model.detector.backbone.resnet.norm == "BN" and shapes.model.detector.backbone.resnet.freeze_at == 0


def test_scene_shapes_fpn_is_the_same_recipe_on_the_hypersim_architecture():
    shapes, fpn, hypersim = (load_config(n) for n in ("scene_shapes", "scene_shapes_fpn", "hypersim"))
    assert to_dict(fpn.model.detector) == to_dict(DetectorConfig()) == to_dict(hypersim.model.detector)
    assert fpn.model.shape == hypersim.model.shape and fpn.model.layout == hypersim.model.layout
    for section in ("data", "loss", "optim", "train"):
        assert getattr(fpn, section) == getattr(shapes, section), section


def test_tiny_recipe_uses_the_detectors_tiny_network():
    tiny = load_config("tiny")
    assert to_dict(tiny.model.detector) == to_dict(DetectorConfig.tiny())
    assert tiny.model.shape.ico_level == 2 and tiny.optim.name == "muon"
    # the FPN shape head of the defaults, not Scene-Shapes' Mesh R-CNN head, also sampling the image itself
    assert tiny.model.shape.features == ("p2", "image") and not tiny.model.shape.pass_features
    assert tiny.model.shape.bottleneck_init == "torch" and tiny.model.layout.in_features == ("p2",)


def test_feature_names_are_distinct():
    with pytest.raises(ConfigError, match="need distinct backbone map names"):
        load_config("hypersim", ["model.shape.features=[p2, p2]"])


def test_overrides_are_typed_and_nested():
    cfg = load_config(
        "hypersim",
        [
            "optim.lr=1e-3",
            "optim.steps=[10, 20]",
            "data.root=/data/x",
            "model.shape.num_stages=1",
            "loss.weights.laplacian=0.5",
        ],
    )
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
        (["model.shape.global_stage=-1"], r"model\.shape\.global_stage: must be >= 0"),
        (["lr"], r"expected key=value"),
    ],
)
def test_bad_overrides_name_the_key_and_the_command_line(overrides, message):
    with pytest.raises(ConfigError, match=message) as info:
        load_config("tiny", ["data.num_views=4", *overrides])
    assert "tiny.yaml" not in str(info.value)  # the recipe is fine: the mistake is on the command line
    if "=" in overrides[0]:
        assert str(info.value).startswith("command line:") and f"(override {overrides[0]!r})" in str(info.value)


def test_a_bad_recipe_names_its_file(tmp_path):
    recipe = tmp_path / "mine.yaml"
    recipe.write_text("_base_: " + str(resolve_config_path("tiny")) + "\noptim: {lrr: 1}\n")
    with pytest.raises(ConfigError, match=r"mine\.yaml: config\.optim: unknown key"):
        load_config(recipe, ["optim.lr=0.1"])


def test_print_config_is_the_resolved_yaml(capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert train_main(["--config", "tiny", "--print-config", "optim.lr=0.5", "data.root=records", "--seed", "7"]) == 0
    printed = config_from_dict(yaml.safe_load(capsys.readouterr().out))
    assert printed == load_config("tiny", ["optim.lr=0.5", f"data.root={tmp_path / 'records'}", "train.seed=7"])
    assert not (tmp_path / "runs").exists()  # nothing ran


def test_list_keys_shows_every_key_with_type_value_and_doc(capsys):
    assert train_main(["--config", "tiny", "--list-keys"]) == 0
    lines = capsys.readouterr().out.splitlines()
    keys = [k for k in iter_keys(load_config("tiny"))]
    assert [line.split()[0] for line in lines] == [k.key for k in keys]
    by_key = {line.split()[0]: line for line in lines}
    assert by_key["optim.lr"].split()[1:4] == ["float", "0.0014", "base"]  # tiny's value, not the default 0.01
    assert (
        by_key["model.shape.sampler"].split()[1:3] == ["str", "roimap"]
        and "Mesh R-CNN" in by_key["model.shape.sampler"]
    )
    assert "tuple[str, ...]" in by_key["model.layout.in_features"]
    undocumented = [k.key for k in keys if not k.doc]
    assert undocumented == [], "document these keys with a comment beside their field in its dataclass"


def test_every_field_doc_is_at_most_two_comment_lines():
    """A key's doc says what it does and why a user would change it, in at most two lines: longer
    stories belong in docs/ (and measurements in docs/experiments/)."""
    long = {}
    for section in _config_dataclasses(Config):
        source = inspect.getsource(section).splitlines()
        for number, line in enumerate(source):
            if re.match(r"\s+\w+: .+=", line) and not line.lstrip().startswith("#"):
                above = itertools.takewhile(lambda text: text.lstrip().startswith("#"), reversed(source[:number]))
                if len(list(above)) > 2:
                    long[f"{section.__name__}.{line.split(':')[0].strip()}"] = number
    assert long == {}


def _config_dataclasses(cls: type) -> list[type]:
    """``cls`` and every dataclass its fields nest, depth first."""
    found = [cls]
    for f in dataclasses.fields(cls):
        tp = typing.get_type_hints(cls)[f.name]
        if dataclasses.is_dataclass(tp) and tp not in found:
            found += [c for c in _config_dataclasses(tp) if c not in found]
    return found


def test_the_config_stays_small():
    """Every key is one more thing a user must read past: a new one needs a user's reason to change it."""
    keys = list(iter_keys(load_config("tiny")))
    assert len(keys) <= 110
    assert len([k for k in keys if k.key.startswith("model.detector.")]) <= 30


def test_field_docs_come_from_comments_beside_or_above_the_field():
    docs = field_docs(ModelConfig)
    assert docs["detector_preset"].startswith("Defaults the ``detector`` keys start from")  # block above
    assert docs["categories"].startswith("category names; empty: the records manifest's")
    assert field_docs(DataConfig)["num_views"].startswith("M: the input view plus M - 1 other views")  # beside


def test_resume_never_swallows_an_override(tmp_path):
    args = parse_args(["--resume", "data.root=/elsewhere", "optim.max_iter=9"])
    assert args.resume == "" and args.overrides == ["data.root=/elsewhere", "optim.max_iter=9"]
    checkpoint = tmp_path / "a=b.pt"  # an existing path stays a checkpoint even with "=" in its name
    checkpoint.write_bytes(b"")
    assert parse_args(["--resume", str(checkpoint)]).resume == str(checkpoint)
    args = parse_args(["--out", "r1", "--out", "r2", "--device", "cpu", "train.device=cuda"])
    assert args.out == Path("r2") and args.overrides == ["train.device=cpu", "train.device=cuda"]


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
    """The findings that hold at any scale are the defaults, which the paper's recipes set back to the
    paper's values; the CPU-scale ones are options that only `tiny` turns on."""
    defaults = Config()
    assert not defaults.loss.gate_input_view and defaults.loss.ignore_occluders and defaults.data.flip_prob == 0.5
    assert defaults.model.layout.box_geometry and defaults.loss.render.blur_radius == 9.21e-3
    for name in ("scene_shapes", "scene_shapes_fpn", "hypersim", "scannet"):
        cfg = load_config(name)
        assert cfg.loss.gate_input_view and not cfg.loss.ignore_occluders and cfg.data.flip_prob == 0, name
        assert not cfg.model.layout.box_geometry and cfg.loss.render.blur_radius == cfg.loss.render.sigma == 1e-3
        assert cfg.loss.dist_schedule.iters == () and cfg.loss.dist_schedule(10**5) == 1.0, name
        assert cfg.model.shape.graph_conv_init == "normal" and cfg.loss.iou_threshold == 0.5, name
        assert cfg.model.shape.global_stage == 0 and cfg.optim.clip_grad_norm != 100.0, name
        assert cfg.loss.weights.normal == 0.0, name
    tiny = load_config("tiny")
    assert not tiny.loss.gate_input_view and tiny.loss.ignore_occluders
    assert tiny.model.shape.graph_conv_init == "kaiming" and tiny.loss.render.resolution == 64
    assert tiny.model.shape.global_stage > 0 and tiny.optim.clip_grad_norm == 100.0
    assert tiny.loss.weights.normal == 0.1 and tiny.loss.weights.laplacian == 0.0
    assert tiny.loss.dist_schedule(0) == 1.0 and tiny.loss.dist_schedule(tiny.optim.max_iter) < 1.0


def _recipe_keys(name: str) -> list[str]:
    """The dotted keys a recipe file sets itself (not those of its ``_base_``)."""

    def leaves(node: dict, prefix: str) -> list[str]:
        return [
            key
            for name, value in node.items()
            for key in (leaves(value, f"{prefix}{name}.") if isinstance(value, dict) and value else [prefix + name])
        ]

    return [key for key in leaves(yaml.safe_load(resolve_config_path(name).read_text()), "") if key != "_base_"]


def test_tiny_sets_few_keys():
    """Each key tiny sets is one more departure a reader must follow: what helps every recipe is the
    default, so tiny sets only what a short CPU run needs."""
    assert len(_recipe_keys("tiny")) <= 25


@pytest.mark.parametrize("name", RECIPE_NAMES)
def test_every_key_a_recipe_sets_changes_its_config(name, tmp_path):
    """A recipe holds only what differs from the defaults and its ``_base_``: a key that repeats them
    is one more line to read, and hides which values the recipe chose."""
    path = resolve_config_path(name)
    own = yaml.safe_load(path.read_text())
    if "_base_" in own:
        own["_base_"] = str(path.parent / own["_base_"])
    for key in _recipe_keys(name):
        *parents, leaf = key.split(".")
        trimmed = copy.deepcopy(own)
        nodes = [trimmed]
        for parent in parents:
            nodes.append(nodes[-1][parent])
        del nodes[-1][leaf]
        for node, parent in reversed(
            list(zip(nodes[:-1], parents, strict=True))
        ):  # an empty mapping would clear the key
            if not node[parent]:
                del node[parent]
        (tmp_path / "trimmed.yaml").write_text(yaml.safe_dump(trimmed))
        try:
            trimmed_config = load_config(tmp_path / "trimmed.yaml", [f"name={name}"])
        except ConfigError:  # needed with another key it sets (a schedule's knots and values)
            continue
        assert trimmed_config != load_config(name), key


def test_tiny_long_is_tiny_with_its_schedule_scaled_to_the_longer_run():
    """The two recipes must not drift apart: only the run length and what is placed by it differ."""
    tiny, long = load_config("tiny"), load_config("tiny_long")
    scale = long.optim.max_iter / tiny.optim.max_iter
    assert scale > 1
    assert long.optim.steps == tuple(round(s * scale, -1) for s in tiny.optim.steps)
    assert long.loss.dist_schedule.iters == tuple(round(i * scale, -1) for i in tiny.loss.dist_schedule.iters)
    assert long.loss.dist_schedule.values == tiny.loss.dist_schedule.values
    # checkpoint_every is bookkeeping, not learning: a longer run saves less often
    rebuilt = dataclasses.replace(
        long,
        name=tiny.name,
        optim=dataclasses.replace(long.optim, steps=tiny.optim.steps, max_iter=tiny.optim.max_iter),
        loss=dataclasses.replace(long.loss, dist_schedule=tiny.loss.dist_schedule),
        train=dataclasses.replace(long.train, checkpoint_every=tiny.train.checkpoint_every),
    )
    assert rebuilt == tiny


def test_help_lists_every_built_in_recipe():
    from usl.cli.train import RECIPES, parser

    assert RECIPES == sorted(p.stem for p in CONFIG_DIR.glob("*.yaml")) and len(RECIPES) >= 6
    assert all(name in " ".join(parser().format_help().split()) for name in RECIPES)
