"""``usl-eval`` end to end: every table row with a tiny random checkpoint, files, and clear errors."""

from __future__ import annotations

import json

import pytest

from tests.evaluation.eval_helpers import build_dataset, tiny_checkpoint
from usl.cli.evaluate import main
from usl.evaluation.choices import ROWS
from usl.evaluation.evaluate import dataset_spec
from usl.evaluation.views import FurthestFraction, view_selection

ALL_ROWS = ",".join(ROWS)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("cli")
    return build_dataset(root / "ds", num_scenes=2, num_views=3), tiny_checkpoint(root / "run")


def test_every_row_with_a_checkpoint(data, tmp_path, capsys):
    dataset, checkpoint = data
    out = tmp_path / "eval"
    rc = main(
        [
            str(dataset),
            "--checkpoint",
            str(checkpoint),
            "--rows",
            ALL_ROWS,
            "--out",
            str(out),
            "--samples-3d",
            "200",
            "--pictures",
            "1",
            "--input-views",
            "first",
            "--other-views",
            "furthest:0.5",
            "--device",
            "cpu",
            "--quiet",
        ]
    )
    assert rc == 0, capsys.readouterr().err
    document = json.loads((out / "metrics.json").read_text())
    names = [p["name"] for p in document["predictors"]]
    assert names == [
        "Random depth",
        "Fixed depth",
        "USL",
        "USL w/ detections",
        "Layout-only (USL)",
        "Sphere-only w/ true depth",
        "USL w/ true depth",
        "Sphere-only w/ true depth and extent",
        "USL w/ true depth and extent",
    ]
    by_name = {p["name"]: p for p in document["predictors"]}
    assert by_name["USL"]["num_objects"] == 4 and by_name["USL"]["metrics"]["chamfer"] is not None
    assert set(by_name["USL w/ detections"]["detection"]) >= {"bbox/AP", "bbox/AP50", "segm/AP", "segm/AP50", "matched"}
    assert by_name["Layout-only (USL)"]["predicts_shape"] is False
    rows = [json.loads(line) for line in (out / "objects.jsonl").read_text().splitlines()]
    assert all(r["num_views"] == 1 for r in rows)  # 2 other views each, furthest half -> 1
    # one id space with the records: each id next to its name, both for the true and the predicted class
    category = {int(c["id"]): c["name"] for c in json.loads((dataset / "manifest.json").read_text())["categories"]}
    assert all(category[r["category_id"]] == r["category"] and category[r["label"]] == r["label_name"] for r in rows)
    assert {r["predictor"] for r in rows} >= {"USL", "USL w/ true depth"}
    assert len(list((out / "pictures").rglob("*.png"))) == len(names)
    table = (out / "table.md").read_text()
    assert table in capsys.readouterr().out and "| USL w/ true depth |" in table
    assert (
        "Pictures: [pictures/index.md](pictures/index.md)" in table
        and document["links"]["pictures"] == "pictures/index.md"
    )
    assert "curves" not in table  # the random checkpoint's run folder has no curves.png


def test_model_rows_are_named_by_their_training_and_the_scored_checkpoint_is_recorded(data, tmp_path, capsys):
    dataset, usl_checkpoint = data
    meshrcnn = tiny_checkpoint(tmp_path / "meshrcnn", overrides=("loss.supervision=3d",), iteration=7)
    common = ["--rows", "fixed,model,detections", "--samples-3d", "50", "--pictures", "0", "--device", "cpu", "--quiet"]
    for checkpoint, extra, name, iteration in (
        (meshrcnn.parent.parent, [], "Mesh R-CNN (3D sup.)", 7),  # a run folder: its newest checkpoint
        (usl_checkpoint, [], "USL", 0),
        (usl_checkpoint, ["--model-name", "USL (5 views)"], "USL (5 views)", 0),
    ):
        out = tmp_path / name.replace(" ", "_")
        assert main([str(dataset), "--checkpoint", str(checkpoint), "--out", str(out), *common, *extra]) == 0, (
            capsys.readouterr().err
        )
        document = json.loads((out / "metrics.json").read_text())
        assert [p["name"] for p in document["predictors"]] == ["Fixed depth", name, f"{name} w/ detections"]
        file = meshrcnn if iteration == 7 else usl_checkpoint
        assert (
            document["checkpoint"]["path"] == str(file.resolve()) and document["checkpoint"]["iteration"] == iteration
        )
        assert f"{name}: checkpoint `{file.resolve()}`, iteration {iteration}" in (out / "table.md").read_text()
    assert main([str(dataset), "--rows", "fixed", "--out", str(tmp_path / "none"), *common[2:]]) == 0
    assert json.loads((tmp_path / "none" / "metrics.json").read_text())["checkpoint"] is None
    assert "checkpoint" not in (tmp_path / "none" / "table.md").read_text()


def _index_entries(index):
    """(picture path, scene, input view, objects.jsonl line numbers) of each row of index.md."""
    entries = []
    for line in index.splitlines():
        if line.startswith("| <a href="):
            cells = [c.strip() for c in line.strip("|").split("|")]
            path = cells[0].split('"')[1]
            entries.append((path, cells[1], int(cells[2]), [int(n) for n in cells[3].split(",") if n.strip() != "–"]))
    return entries


@pytest.mark.parametrize("pictures_by", ["spread", "extremes"])
def test_pictures_are_spread_or_extremes_and_indexed(data, tmp_path, capsys, pictures_by):
    dataset, checkpoint = data
    (checkpoint.parent.parent / "curves.png").write_bytes(b"")  # a training run's curves
    out = tmp_path / "eval"
    rc = main(
        [
            str(dataset),
            "--checkpoint",
            str(checkpoint),
            "--rows",
            "fixed,model",
            "--out",
            str(out),
            "--samples-3d",
            "50",
            "--pictures",
            "2",
            "--pictures-by",
            pictures_by,
            "--device",
            "cpu",
            "--quiet",
        ]
    )
    assert rc == 0, capsys.readouterr().err
    rows = [json.loads(line) for line in (out / "objects.jsonl").read_text().splitlines()]
    entries = _index_entries((out / "pictures" / "index.md").read_text())
    assert len(entries) == 4 and all((out / "pictures" / path).is_file() for path, *_ in entries)  # 2 views x 2 rows
    for path, scene, view, lines in entries:  # the index points at the picture's own objects
        assert lines and all(rows[n - 1]["scene_id"] == scene and rows[n - 1]["input_view"] == view for n in lines)
        assert {rows[n - 1]["predictor"] for n in lines} == {"Fixed depth" if path.startswith("Fixed") else "USL"}
    chosen = {(scene, view) for _, scene, view, _ in entries}
    if pictures_by == "spread":
        assert {scene for scene, _ in chosen} == {r["scene_id"] for r in rows}  # both scenes, not the first twice
    else:  # the worst and the best input view by the first row's mean Mask IoU (views)
        means = {}
        for r in rows:
            if r["predictor"] == "Fixed depth" and r["mask_iou_views"] is not None:
                means.setdefault((r["scene_id"], r["input_view"]), []).append(r["mask_iou_views"])
        ranked = sorted(means, key=lambda k: sum(means[k]) / len(means[k]))
        assert chosen == {ranked[0], ranked[-1]}
    table = (out / "table.md").read_text()
    assert "Training curves: [../" in table and table.rstrip().endswith("curves.png)")
    target = table.rstrip().rsplit("(", 1)[1].rstrip(")")
    assert (out / target).resolve() == (checkpoint.parent.parent / "curves.png").resolve()


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
