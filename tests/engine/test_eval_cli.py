"""``usl-eval`` end to end: every table row with a tiny random checkpoint, files, and clear errors."""
from __future__ import annotations

import json

import pytest

from eval_helpers import build_dataset, tiny_checkpoint
from usl.engine.eval_views import FurthestFraction, view_selection
from usl.engine.evaluate import dataset_spec, main

ALL_ROWS = "random,fixed,model,detections,layout_only,sphere_true_depth,model_true_depth"


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("cli")
    return build_dataset(root / "ds", num_scenes=2, num_views=3), tiny_checkpoint(root / "run")


def test_every_row_with_a_checkpoint(data, tmp_path, capsys):
    dataset, checkpoint = data
    out = tmp_path / "eval"
    rc = main([str(dataset), "--checkpoint", str(checkpoint), "--rows", ALL_ROWS, "--out", str(out), "--samples-3d", "200",
               "--pictures", "1", "--input-views", "first", "--other-views", "furthest:0.5", "--device", "cpu", "--quiet"])
    assert rc == 0, capsys.readouterr().err
    document = json.loads((out / "metrics.json").read_text())
    names = [p["name"] for p in document["predictors"]]
    assert names == ["Random depth", "Fixed depth", "USL", "USL w/ detections", "Layout-only (USL)",
                     "Sphere-only w/ true depth", "USL w/ true depth"]
    by_name = {p["name"]: p for p in document["predictors"]}
    assert by_name["USL"]["num_objects"] == 4 and by_name["USL"]["metrics"]["chamfer"] is not None
    assert set(by_name["USL w/ detections"]["detection"]) >= {"bbox/AP", "bbox/AP50", "segm/AP", "segm/AP50", "matched"}
    assert by_name["Layout-only (USL)"]["predicts_shape"] is False
    rows = [json.loads(line) for line in (out / "objects.jsonl").read_text().splitlines()]
    assert all(r["num_views"] == 1 for r in rows)  # 2 other views each, furthest half -> 1
    assert {r["predictor"] for r in rows} >= {"USL", "USL w/ true depth"}
    assert len(list((out / "pictures").rglob("*.png"))) == len(names)
    table = (out / "table.md").read_text()
    assert table in capsys.readouterr().out and "| USL w/ true depth |" in table


def test_cli_errors_are_one_line(data, tmp_path, capsys):
    dataset, checkpoint = data
    cases = [
        ([str(tmp_path / "nowhere")], "nowhere/manifest.json"),
        ([str(dataset), "--split", "test"], "no split 'test'"),
        ([str(dataset), "--rows", "model"], "need a --checkpoint"),
        ([str(dataset), "--rows", "oracle"], "unknown row"),
        ([str(dataset), "--rows", "model", "--checkpoint", str(tmp_path / "none.pt")], "none.pt does not exist"),
        ([str(dataset), "--scenes", "sceneX"], "no scene"),
        ([str(dataset), "--input-views", "every:0"], "input views"),
    ]
    other = tiny_checkpoint(tmp_path / "other", categories=("lamp", "bed", "desk"))
    cases.append(([str(dataset), "--rows", "model", "--checkpoint", str(other)], "trained on categories"))
    for argv, message in cases:
        rc = main(argv + ["--out", str(tmp_path / "out"), "--quiet", "--device", "cpu"])
        err = capsys.readouterr().err.strip()
        assert rc == 2 and err.startswith("usl-eval: error:") and len(err.splitlines()) == 1, (argv, err)
        assert message in err, (argv, err)


def test_scannet_spec_selects_furthest_fifth_of_each_track():
    spec = dataset_spec({"name": "scannet", "categories": [], "layout": {}, "baselines": {}})
    selection = view_selection("auto", spec)
    assert isinstance(selection, FurthestFraction) and selection.fraction == 0.2
    assert spec["baselines"]["fixed_depth"] == {"z": 5.0, "rho": 0.5}
