"""Evaluation metrics on tiny pyrender-made datasets with known answers.

Oracles: pyrender (OpenGL) masks and depth for ground truth and for re-rendering predictions,
numpy for IoU / gIoU, pycocotools for AP. The evaluator itself renders with usl's rasterizer.
"""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from data_specs import load_dataset_spec
from tests.evaluation.eval_helpers import PerfectPredictor, build_dataset, render_truth
from usl.data.frames import CategoryIndex, decode_frame
from usl.evaluation.baselines import spec_baselines
from usl.evaluation.evaluate import run_evaluation
from usl.evaluation.report import markdown_table, write_report
from usl.evaluation.scene import EvalConfig
from usl.evaluation.types import EvalInput
from usl.records import RecordsDataset, decode_mask, frame_pose

FAST = dict(num_samples_3d=400)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return build_dataset(tmp_path_factory.mktemp("eval") / "ds", num_scenes=2, num_views=3)


def _by_name(run):
    return {s.name: s for s in run.summaries}


def test_perfect_prediction_scores_perfectly(dataset):
    run = run_evaluation(dataset, "val", [PerfectPredictor()], EvalConfig(input_views="all", **FAST), progress=False)
    m = run.summaries[0].metrics
    assert m["mask_iou_input"] > 0.98 and m["mask_iou_views"] > 0.98
    assert m["box_giou_input"] > 0.98 and m["box_giou_views"] > 0.98
    assert m["depth_l1_input"] < 0.01 and m["depth_l1_views"] < 0.01
    assert m["chamfer"] < 1e-3 and m["f1"] > 99.0
    # Every object is scored in each other view where it appears, never where it is absent.
    records = RecordsDataset(dataset, "val")
    for row in run.rows:
        frames = records.read_scene(row["scene_id"])
        seen = [f["view_id"] for f in frames if any(i["instance_id"] == row["instance_id"] for i in f["instances"])]
        assert row["num_views"] == len([v for v in seen if v != row["input_view"]])
    assert run.header["num_input_views"] == 6 and run.summaries[0].num_objects == 12


def _np_giou(a, b):
    inter = max(0, min(a[2], b[2]) - max(a[0], b[0])) * max(0, min(a[3], b[3]) - max(a[1], b[1]))
    area = lambda r: (r[2] - r[0]) * (r[3] - r[1])  # noqa: E731
    union = area(a) + area(b) - inter
    hull = (max(a[2], b[2]) - min(a[0], b[0])) * (max(a[3], b[3]) - min(a[1], b[1]))
    return inter / union - (hull - union) / hull


def _np_box(mask):
    rows, cols = np.flatnonzero(mask.any(1)), np.flatnonzero(mask.any(0))
    return [cols[0], rows[0], cols[-1] + 1, rows[-1] + 1]


def test_view_metrics_match_pyrender_reprojection(dataset):
    """Fixed-depth spheres, moved to the world with the input pose and drawn by pyrender in each view."""
    fixed = spec_baselines(load_dataset_spec("scene_shapes")["baselines"])["fixed"]
    run = run_evaluation(dataset, "val", [fixed], EvalConfig(input_views="first", **FAST), progress=False)
    records = RecordsDataset(dataset, "val")
    checked = 0
    for scene_id in records.scene_ids:
        frames = records.read_scene(scene_id)
        rows = [r for r in run.rows if r["scene_id"] == scene_id]
        frame = decode_frame(frames[0], CategoryIndex(records.categories))
        pred = fixed([EvalInput(frame, {})])[0]
        pose0 = frame_pose(frames[0])
        world = [
            (int(i), 0, v.double().numpy() @ pose0[:3, :3].T + pose0[:3, 3], pred.faces.numpy())
            for i, v in zip(pred.instance_ids, pred.verts, strict=True)
        ]
        per_object = {r["instance_id"]: ([], [], []) for r in rows}
        for f in frames[1:]:
            _, masks, depth = render_truth(world, frame_pose(f))
            for inst in f["instances"]:
                n = [w[0] for w in world].index(inst["instance_id"])
                true = decode_mask(inst["mask"])
                iou = (masks[n] & true).sum() / (masks[n] | true).sum()
                near = depth[masks[n]].min() if masks[n].any() else math.nan
                per_object[inst["instance_id"]][0].append(iou)
                per_object[inst["instance_id"]][1].append(
                    _np_giou(_np_box(masks[n]), inst["box_xyxy"]) if masks[n].any() else math.nan
                )
                per_object[inst["instance_id"]][2].append(abs(near - inst["depth_min"]))
        for r in rows:
            ious, gious, depths = per_object[r["instance_id"]]
            assert r["mask_iou_views"] == pytest.approx(np.mean(ious), abs=0.005)
            if not np.isnan(gious).any():
                assert r["box_giou_views"] == pytest.approx(np.mean(gious), abs=0.005)
                assert r["depth_l1_views"] == pytest.approx(np.mean(depths), abs=1e-3)
            checked += 1
    assert checked == 4


def test_detections_ap_with_pycocotools(dataset):
    exact = PerfectPredictor(uses_detections=True, name="exact")
    shifted = PerfectPredictor(uses_detections=True, box_shift=4.0, name="shifted")
    run = run_evaluation(dataset, "val", [exact, shifted], EvalConfig(input_views="every:2", **FAST), progress=False)
    got = _by_name(run)
    assert got["exact"].detection["bbox/AP"] == pytest.approx(100.0)
    assert got["exact"].detection["segm/AP50"] == pytest.approx(100.0)
    assert got["exact"].detection["matched"] == got["exact"].detection["ground_truth"] == 8
    assert got["shifted"].detection["bbox/AP"] < 60.0
    # Matched detections are scored like ground-truth-box predictions.
    assert got["exact"].metrics["mask_iou_views"] > 0.98


def test_baselines_rank_below_perfect_and_report_is_strict_json(dataset, tmp_path):
    baselines = spec_baselines(load_dataset_spec("scene_shapes")["baselines"])
    predictors = [baselines["random"], baselines["fixed"], PerfectPredictor()]
    run = run_evaluation(dataset, "val", predictors, EvalConfig(input_views="first", **FAST), progress=False)
    got = _by_name(run)
    for name in ("Random depth", "Fixed depth"):
        assert got[name].metrics["mask_iou_views"] < got["Perfect"].metrics["mask_iou_views"] - 0.2
        assert got[name].metrics["chamfer"] > 10 * got["Perfect"].metrics["chamfer"]
    paths = write_report(tmp_path, run.header, run.summaries, run.rows, run.layout)
    document = json.loads(paths["metrics"].read_text(), parse_constant=lambda c: pytest.fail(f"non-JSON constant {c}"))
    assert [p["name"] for p in document["predictors"]] == ["Random depth", "Fixed depth", "Perfect"]
    assert len(paths["objects"].read_text().splitlines()) == 12
    table = paths["table"].read_text()
    assert run.layout == "scene_shapes" and "| Ch. ↓ | F1@0.1 | Mask IoU input | Mask IoU views |" in table
    assert "| Perfect | 0.000 | 100.0 |" in table
    hypersim = markdown_table(run.summaries, "hypersim")
    assert "Depth L1 ↓ views" in hypersim and "| Random depth | ✗ | ✗ |" in hypersim


def test_occlusion_setting_changes_only_occluded_objects(dataset):
    perfect = PerfectPredictor()
    together = run_evaluation(dataset, "val", [perfect], EvalConfig(input_views="all", **FAST), progress=False)
    alone = run_evaluation(
        dataset, "val", [perfect], EvalConfig(input_views="all", occlusion=False, **FAST), progress=False
    )
    a, b = together.summaries[0].metrics, alone.summaries[0].metrics
    # Full silhouettes overshoot the visible true masks wherever objects overlap.
    assert b["mask_iou_views"] < a["mask_iou_views"] - 0.005
    assert b["mask_iou_input"] < a["mask_iou_input"]


def test_chunking_does_not_change_results(dataset):
    baselines = spec_baselines(load_dataset_spec("scene_shapes")["baselines"])
    predictors = [baselines["random"], PerfectPredictor(uses_detections=True)]
    config = dict(input_views="first", **FAST)
    big = run_evaluation(dataset, "val", predictors, EvalConfig(**config), progress=False)
    # One view per decode chunk and a render budget below one view: every group is rendered alone.
    small = run_evaluation(
        dataset,
        "val",
        predictors,
        EvalConfig(views_per_chunk=1, max_render_bytes=1, batch_size=1, **config),
        progress=False,
    )
    assert big.rows == small.rows
    assert big.summaries[1].detection == small.summaries[1].detection


class Moved(PerfectPredictor):
    """True meshes of the first object moved by ``offset`` (camera frame of the input view)."""

    def __init__(self, offset):
        super().__init__(name=f"moved {offset}")
        self.offset = torch.tensor(offset, dtype=torch.float32)

    def __call__(self, inputs):
        preds = super().__call__(inputs)
        for pred in preds:
            pred.verts[0] += self.offset
        return preds


def test_objects_out_of_sight_fall_back_to_projected_vertices(dataset):
    aside, behind = Moved([3.0, 0.0, 0.0]), Moved([0.0, 0.0, -10.0])
    run = run_evaluation(dataset, "val", [aside, behind], EvalConfig(input_views="first", **FAST), progress=False)
    first = {(r["predictor"], r["scene_id"]): r for r in run.rows if r["instance_id"] == 10}
    for scene in ("scene0", "scene1"):
        side = first[(aside.name, scene)]
        assert side["mask_iou_input"] == 0.0
        assert -1.0 < side["box_giou_input"] < -0.5  # far to the right of the true box, yet still ranked by distance
        assert 0.0 < side["depth_l1_input"] < 1.0  # nearest vertex depth, not the (empty) render
        back = first[(behind.name, scene)]
        assert back["mask_iou_input"] == 0.0 and back["box_giou_input"] == -1.0
        assert back["depth_l1_input"] is None or math.isnan(back["depth_l1_input"])
    counts = {s.name: s.counts for s in run.summaries}
    assert counts[behind.name]["depth_l1_input"] == 2 and counts[behind.name]["mask_iou_input"] == 4


class _Mislabelled(PerfectPredictor):
    """The true meshes with every label shifted to another class: per-category means must still group
    objects by their true category."""

    name = "Mislabelled"

    def __call__(self, inputs):
        return [replace(p, labels=(p.labels + 1) % 3) for p in super().__call__(inputs)]


def test_per_category_means_match_pandas_on_objects_jsonl(dataset, tmp_path):
    import pandas as pd

    fixed = spec_baselines(load_dataset_spec("scene_shapes")["baselines"])["fixed"]
    run = run_evaluation(dataset, "val", [fixed, _Mislabelled()], EvalConfig(input_views="all", **FAST), progress=False)
    paths = write_report(tmp_path, run.header, run.summaries, run.rows, run.layout)
    objects = pd.read_json(paths["objects"], lines=True)
    # the true category of each instance, read from the records themselves
    records = RecordsDataset(dataset, "val")
    names = {c["id"]: c["name"] for c in records.categories}
    truth = {
        (s, i["instance_id"]): names[i["category_id"]]
        for s in records.scene_ids
        for f in records.read_scene(s)
        for i in f["instances"]
    }
    assert [truth[(r.scene_id, r.instance_id)] for r in objects.itertuples()] == objects["category"].tolist()
    assert objects["category"].nunique() == 3
    document = json.loads(paths["metrics"].read_text())
    for predictor in document["predictors"]:
        own = objects[objects["predictor"] == predictor["name"]]
        expected = own.groupby("category")[["mask_iou_input", "mask_iou_views", "chamfer", "f1"]].mean()
        assert sorted(predictor["categories"]) == sorted(expected.index)
        for category, means in expected.iterrows():
            got = predictor["categories"][category]
            assert got["num_objects"] == int((own["category"] == category).sum())
            for metric, value in means.items():
                assert got["metrics"][metric] == pytest.approx(value, rel=1e-9)
    table = paths["table"].read_text()
    assert "Per true category:" in table and "| Model | Category | Objects | Ch. ↓ |" in table
    assert table.count("| Mislabelled |") == 1 + 3 and table.count("| Fixed depth |") == 1 + 3
