"""scripts/lib/main_job_verdict.py: the main job's mean ± std over held-out builds, and its claim.

The fixtures are usl-eval reports written by usl-eval's own writer (``write_report``), one per
held-out build as ``evaluate_heldout`` lays them out (``EVAL/seed<k>/metrics.json``); the expected
means and sample stds come from numpy.
"""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

from usl.evaluation.report import write_report
from usl.evaluation.summary import METRICS, PredictorSummary

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "lib" / "main_job_verdict.py"
SPEC = importlib.util.spec_from_file_location("main_job_verdict", SCRIPT)
verdict = importlib.util.module_from_spec(SPEC)
SPEC.loader.exec_module(verdict)

HEADER = {"dataset": "scene_shapes", "split": "train", "num_scenes": 16, "num_input_views": 128}
# per build: Chamfer, F1 (percent), Mask IoU input, Mask IoU views
ROWS = {
    "Random depth": [(0.24, 29.0, 0.415, 0.193), (0.25, 25.3, 0.358, 0.163), (0.22, 26.8, 0.360, 0.171)],
    "Fixed depth": [(0.16, 32.0, 0.434, 0.216), (0.19, 27.4, 0.371, 0.183), (0.16, 29.2, 0.381, 0.189)],
    "USL": [(0.044, 65.0, 0.454, 0.334), (0.049, 61.2, 0.412, 0.296), (0.035, 68.9, 0.430, 0.332)],
}


def _write_builds(root: Path, rows: dict[str, list[tuple]], first_only: str | None = "Layout-only (USL)") -> None:
    for build, seed in enumerate((1, 2, 3)):
        summaries = []
        for name, values in rows.items():
            metrics = {m: 0.5 for m in METRICS}
            metrics.update(zip(("chamfer", "f1", "mask_iou_input", "mask_iou_views"), values[build], strict=True))
            summaries.append(PredictorSummary(name, True, True, False, 32, metrics, {m: 32 for m in METRICS}))
        if first_only and seed == 1:
            summaries.append(PredictorSummary(first_only, True, False, False, 32, dict.fromkeys(METRICS, 0.3), {}))
        write_report(root / f"seed{seed}", HEADER, summaries, [], "scene_shapes")


def test_mean_std_over_builds_every_build_and_the_claim(tmp_path, capsys):
    _write_builds(tmp_path, ROWS)
    assert verdict.main(str(tmp_path)) == 0
    table = (tmp_path / "table.md").read_text()
    ious = np.array([v[2] for v in ROWS["USL"]]) * 100
    assert f"{ious.mean():.1f} ± {ious.std(ddof=1):.1f}" in table
    assert "384 input views" in table
    assert "| Layout-only (USL) | 0.300 | 0.3 | 30.0 | 30.0 | 1 |" in table  # scored on one build: no std
    assert table.count("| USL | ") == 4  # the mean row and one row per build
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["claim_holds"] and summary["seeds"] == [1, 2, 3]
    assert summary["rows"]["USL"]["mask_iou_views"]["values"] == [v[3] for v in ROWS["USL"]]
    out = capsys.readouterr().out
    lead = 100 * (np.mean([v[2] for v in ROWS["USL"]]) - np.mean([v[2] for v in ROWS["Fixed depth"]]))
    assert f"leads Fixed depth by {lead:+.1f} points (>= +6)" in out and "target MISSED" in out
    assert "PASS: on every build (seeds 1, 2, 3)" in out


@pytest.mark.parametrize("metric", [0, 2])
def test_one_build_behind_a_sphere_fails_the_claim(tmp_path, capsys, metric):
    rows = {name: [list(v) for v in values] for name, values in ROWS.items()}
    rows["USL"][1][metric] = rows["Random depth"][1][metric] + (0.01 if metric == 0 else -0.01)  # build 2 loses
    _write_builds(tmp_path, rows, first_only=None)
    assert verdict.main(str(tmp_path)) == 1
    out = capsys.readouterr().out
    assert "FAIL: seed 2: USL" in out and "PASS" not in out
    assert not json.loads((tmp_path / "summary.json").read_text())["claim_holds"]


def test_a_folder_without_reports_names_itself(tmp_path):
    with pytest.raises(SystemExit, match=str(tmp_path)):
        verdict.main(str(tmp_path))


def test_a_build_without_the_model_row_is_named(tmp_path):
    _write_builds(tmp_path, {k: v for k, v in ROWS.items() if k != "USL"}, first_only=None)
    with pytest.raises(SystemExit, match="seed1/metrics.json has no row for USL"):
        verdict.main(str(tmp_path))
