"""A checkpoint saved by an older usl may hold config keys this one no longer has: ``usl-eval``,
``usl-predict``, ``usl.load`` and ``usl-train --resume`` ignore them with one line naming them,
while a recipe or a ``key=value`` override naming an unknown key stays an error naming it."""

from __future__ import annotations

import re
import warnings

import cv2
import numpy as np
import pytest
import torch
import yaml

import usl
from tests.evaluation.eval_helpers import build_dataset, tiny_checkpoint
from usl.cli.evaluate import main as eval_main
from usl.cli.predict import main as predict_main
from usl.cli.train import main as train_main
from usl.config import ConfigError, config_from_dict, load_config, resolve_config_path, saved_config, to_dict
from usl.errors import UslWarning

# what the old checkpoint holds beyond today's fields: a removed option, and a removed whole section
STALE = ("data.color_jitter", "loss.dist_vertices")
NOTICE = "ignoring saved config key(s) this usl no longer has: data.color_jitter, loss.dist_vertices"


@pytest.fixture(scope="module")
def old_run(tmp_path_factory):
    """A run folder whose checkpoint's saved config holds keys no field has any more."""
    root = tmp_path_factory.mktemp("old")
    checkpoint = tiny_checkpoint(root / "run")
    payload = torch.load(checkpoint, map_location="cpu", weights_only=True)
    payload["config"]["data"]["color_jitter"] = {"brightness": 0.4, "hue": 0.1}
    payload["config"]["loss"]["dist_vertices"] = True
    torch.save(payload, checkpoint)
    return root / "run", checkpoint, build_dataset(root / "records", num_scenes=1, num_views=2)


@pytest.fixture
def image_path(tmp_path):
    path = tmp_path / "room.png"
    cv2.imwrite(str(path), np.random.default_rng(0).integers(0, 255, (80, 120, 3), dtype=np.uint8))
    return path


def _warning_lines(err: str) -> list[str]:
    return [line for line in err.splitlines() if "warning" in line.lower()]


def test_a_saved_config_drops_the_keys_it_does_not_know_with_one_warning_naming_them():
    saved = to_dict(load_config("tiny"))
    saved["data"]["color_jitter"] = {"hue": 0.1}
    saved["loss"]["dist_vertices"] = True
    with pytest.warns(UslWarning) as caught:
        assert saved_config(saved, "old.pt") == load_config("tiny")
    assert [str(w.message) for w in caught] == [f"old.pt: {NOTICE}"]
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a config with nothing unknown loads silently
        assert saved_config(to_dict(load_config("tiny")), "new.pt") == load_config("tiny")


def test_usl_load_ignores_them_with_one_warning(old_run):
    run, checkpoint, _ = old_run
    with pytest.warns(UslWarning) as caught:
        model = usl.load(run, device="cpu")
    assert [str(w.message) for w in caught] == [f"{checkpoint}: {NOTICE}"]
    assert model.categories  # it loaded, with the checkpoint's categories


def test_usl_predict_ignores_them_with_one_line(old_run, image_path, tmp_path, capsys):
    run, checkpoint, _ = old_run
    out = tmp_path / "predictions"
    rc = predict_main([str(image_path), "--checkpoint", str(run), "--fov", "60", "--out", str(out), "--quiet"])
    err = capsys.readouterr().err
    assert rc == 0 and (out / "room.glb").is_file(), err
    assert _warning_lines(err) == [f"usl-predict: warning: {checkpoint}: {NOTICE}"]


def test_usl_eval_ignores_them_with_one_line(old_run, tmp_path, capsys):
    run, checkpoint, records = old_run
    args = [str(records), "--split", "val", "--checkpoint", str(run), "--rows", "model", "--out", str(tmp_path)]
    rc = eval_main([*args, "--input-views", "first", "--samples-3d", "100", "--pictures", "0", "--quiet"])
    err = capsys.readouterr().err
    assert rc == 0 and (tmp_path / "metrics.json").is_file(), err
    assert _warning_lines(err) == [f"usl-eval: warning: {checkpoint}: {NOTICE}"]


def test_usl_train_resume_ignores_them_with_one_line(old_run, capsys, monkeypatch):
    """A resumed run continues without them (the line says so, once for all torchrun's processes);
    its config.yaml no longer lists them."""
    run, checkpoint, _ = old_run
    monkeypatch.setenv("RANK", "1")
    assert train_main(["--resume", str(checkpoint), "--print-config"]) == 0
    assert _warning_lines(capsys.readouterr().err) == []
    monkeypatch.setenv("RANK", "0")
    assert train_main(["--resume", str(checkpoint), "--print-config"]) == 0
    out, err = capsys.readouterr()
    assert _warning_lines(err) == [f"usl-train: warning: {checkpoint}: {NOTICE}"]
    printed = yaml.safe_load(out)
    assert "color_jitter" not in printed["data"] and "dist_vertices" not in printed["loss"]
    config_from_dict(printed)  # what the resumed run saves is a valid recipe again


@pytest.mark.parametrize(
    "override, message",
    [
        ("loss.dist_vertices=false", r"config\.loss: unknown key\(s\) \['dist_vertices'\]"),
        ("data.color_jitter.hue=0.0", r"config\.data: unknown key\(s\) \['color_jitter'\]"),
    ],
)
def test_an_override_naming_an_unknown_key_is_an_error_naming_it(override, message, capsys):
    """Also at a removed option's old "off" value: only a saved config is let off."""
    with pytest.raises(ConfigError, match=rf"^command line: {message}.*\(override {override!r}\)$"):
        load_config("tiny", [override])
    assert train_main(["--config", "tiny", "--print-config", override]) == 2
    assert re.search(message, capsys.readouterr().err)


def test_a_recipe_naming_an_unknown_key_is_an_error_naming_it_and_the_file(tmp_path, capsys):
    recipe = tmp_path / "old_recipe.yaml"
    recipe.write_text(f"_base_: {resolve_config_path('tiny')}\nloss:\n  dist_vertices: false\n")
    with pytest.raises(ConfigError, match=r"old_recipe\.yaml: config\.loss: unknown key\(s\) \['dist_vertices'\]"):
        load_config(recipe)
    assert train_main(["--config", str(recipe), "--print-config"]) == 2
    assert "old_recipe.yaml" in capsys.readouterr().err
