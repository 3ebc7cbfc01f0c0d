"""scripts/experiments/table1_plan.py and table1_summary.py: Table 1's rows, budget, and mean ± std over seeds.

The fixtures are the files table1.sh leaves: usl-eval's ``metrics.json`` written by usl-eval's own
writer (``write_report``), run folders with checkpoints written by the trainer's
``write_run_checkpoint``; the expected numbers come from numpy and pandas.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import table1_plan
import table1_summary

from usl.config import CONFIG_DIR, load_config
from usl.engine.checkpoint import write_run_checkpoint
from usl.evaluation.report import write_report
from usl.evaluation.summary import METRICS, PredictorSummary

HEADER = {"dataset": "scene_shapes", "split": "train", "num_scenes": 8, "num_input_views": 8}
SEEDS = {"usl2": [0, 1, 2], "usl5": [0, 1, 2], "usl5_vertalign": [4]}  # one row with a single seed


def _summary(name: str, rng: np.random.Generator) -> PredictorSummary:
    metrics = {m: float(rng.uniform(0.05, 0.9)) for m in METRICS}
    metrics["f1"] = float(rng.uniform(20, 70))  # percent, as usl-eval stores it
    return PredictorSummary(name, True, True, False, num_objects=16, metrics=metrics, counts={m: 16 for m in METRICS})


def _write_eval(out: Path, summaries: list[PredictorSummary]) -> None:
    write_report(out, HEADER, summaries, [], "scene_shapes")


@pytest.fixture
def table(tmp_path):
    """A table1.sh output folder: plan, baselines, finished runs, one unfinished run, one skipped row."""
    rng = np.random.default_rng(7)
    out = tmp_path / "table1"
    out.mkdir()
    plan = [
        ("usl2", "USL (2 views)", "train"),
        ("usl5", "USL (5 views)", "train"),
        ("usl5_vertalign", "USL (5) w/o RoIMap", "train"),
        ("usl5_no_dist", "USL (5) w/o ℓ_dist", "skipped: key not available (loss.weights.dist)"),
    ]
    (out / "plan.tsv").write_text("".join(f"{s}\t{label}\t{status}\toptim.max_iter=20\n" for s, label, status in plan))
    _write_eval(out / "baselines" / "eval", [_summary("Fixed depth", rng), _summary("Random depth", rng)])
    records = []
    for slug, seeds in SEEDS.items():
        for seed in seeds:
            run = out / "runs" / slug / f"seed{seed}"
            write_run_checkpoint(run / "train", 20, {"model": {}, "config": {}})
            summary = _summary("USL", rng)
            _write_eval(run / "eval", [summary])
            records += [{"slug": slug, "metric": m, "value": v} for m, v in summary.metrics.items()]
    write_run_checkpoint(out / "runs" / "usl5" / "seed3" / "train", 10, {"model": {}, "config": {}})  # no eval yet
    return out, pd.DataFrame(records)


def test_mean_and_sample_std_match_pandas_and_numpy(table):
    out, records = table
    assert table1_summary.main([str(out)]) == 0
    rows = {r["slug"]: r for r in json.loads((out / "table1.json").read_text())}
    expected = records.groupby(["slug", "metric"])["value"].agg(["mean", "std"])  # pandas' std: ddof=1
    for slug in ("usl2", "usl5"):
        assert rows[slug]["n"] == 3 and rows[slug]["status"] == "trained"
        for column in table1_summary.TABLE_COLUMNS:
            got = rows[slug]["metrics"][column.metric]
            values = records.query("slug == @slug and metric == @column.metric")["value"].to_numpy()
            assert got["mean"] == pytest.approx(expected.loc[(slug, column.metric), "mean"], rel=1e-12)
            assert got["std"] == pytest.approx(np.std(values, ddof=1), rel=1e-12)
            assert got["std"] == pytest.approx(expected.loc[(slug, column.metric), "std"], rel=1e-12)
    single = rows["usl5_vertalign"]
    assert single["n"] == 1 and single["metrics"]["chamfer"]["std"] is None
    assert [r["seed"] for r in rows["usl5"]["runs"]] == [0, 1, 2]  # seed3 has not been scored


def test_markdown_cells_are_formatted_like_usl_eval(table):
    out, records = table
    table1_summary.main([str(out)])
    text = (out / "table1.md").read_text()
    lines = text.split("Every run:")[0].splitlines()  # the summary table, above the per-run one
    cells = {
        line.split("|")[1].strip(): [c.strip() for c in line.strip("|").split("|")]
        for line in lines
        if line.startswith("| ")
    }
    assert lines[0].startswith("| Model | Ch. ↓ | F1@0.1 | Mask IoU input | Mask IoU views | Seeds | Checkpoint |")
    chamfer = records.query("slug == 'usl5' and metric == 'chamfer'")["value"]
    iou = records.query("slug == 'usl5' and metric == 'mask_iou_views'")["value"] * 100  # IoU in percent
    row = cells["USL (5 views)"]
    assert row[1] == f"{chamfer.mean():.3f} ± {chamfer.std():.3f}"
    assert row[4] == f"{iou.mean():.1f} ± {iou.std():.1f}"
    assert row[5] == "n=3 (seed 0, 1, 2)" and row[6] == "model_0000020.pt (iteration 20)"
    single = cells["USL (5) w/o RoIMap"]
    assert "±" not in single[1] and single[5] == "n=1 (seed 4)"
    assert cells["USL (5) w/o ℓ_dist"][5] == "skipped: key not available (loss.weights.dist)"
    assert cells["Fixed depth"][5] == "– (not trained)" and "Mesh R-CNN (3D sup.)" not in cells  # not in this plan
    baselines = json.loads((out / "baselines" / "eval" / "metrics.json").read_text())["predictors"]
    fixed = next(p for p in baselines if p["name"] == "Fixed depth")["metrics"]
    assert cells["Fixed depth"][2] == f"{fixed['f1']:.1f}"
    assert list(cells)[1:] == [
        "Fixed depth",
        "Random depth",
        "USL (2 views)",
        "USL (5 views)",
        "USL (5) w/o RoIMap",
        "USL (5) w/o ℓ_dist",
    ]  # the paper's order
    seed2 = chamfer.iloc[2]
    assert f"| USL (5 views) | 2 | {seed2:.3f} |" in text  # below: every run with the checkpoint it scored
    assert "runs/usl5/seed2/train/checkpoints/model_0000020.pt" in text


def test_run_line_and_clear_errors(table, tmp_path, capsys):
    out, _ = table
    assert table1_summary.main(["--run", str(out / "runs" / "usl2" / "seed0" / "eval")]) == 0
    assert capsys.readouterr().out.startswith("Ch. ↓ 0.")
    assert table1_summary.main(["--run", str(out / "baselines" / "eval")]) == 2  # two predictors: which one?
    assert "expected exactly one predictor, found: Fixed depth, Random depth" in capsys.readouterr().err
    assert table1_summary.main([str(tmp_path)]) == 2
    assert "plan.tsv: missing" in capsys.readouterr().err


def test_rows_are_the_papers_with_the_agreed_keys():
    assert [(r.label, r.overrides, r.baseline) for r in table1_plan.ROWS] == [
        ("Fixed depth", (), "Fixed depth"),
        ("Random depth", (), "Random depth"),
        ("USL (2 views)", ("data.num_views=2",), None),
        ("USL (5 views)", ("data.num_views=5",), None),
        ("USL (5) w/o RoIMap", ("data.num_views=5", "model.shape.sampler=vertalign"), None),
        ("USL (5) w/o ℓ_dist", ("data.num_views=5", "loss.weights.dist=0"), None),
        ("Mesh R-CNN (3D sup.)", ("loss.supervision=3d",), None),
    ]


def test_budget_scales_the_recipes_schedule():
    recipe = load_config("tiny")
    assert table1_plan.budget_overrides(recipe, recipe.optim.max_iter) == [f"optim.max_iter={recipe.optim.max_iter}"]
    scale = 300 / recipe.optim.max_iter
    scaled = load_config("tiny", table1_plan.budget_overrides(recipe, 300))
    assert scaled.optim.max_iter == 300
    assert list(scaled.optim.steps) == [round(s * scale) for s in recipe.optim.steps]
    assert list(scaled.loss.dist_schedule.iters) == [round(i * scale) for i in recipe.loss.dist_schedule.iters]
    assert scaled.loss.dist_schedule.values == recipe.loss.dist_schedule.values


def test_plan_skips_rows_whose_key_is_missing_and_keeps_its_budget(tmp_path):
    assert table1_plan.row_status("tiny", ["data.num_views=5"]) == "train"
    assert (
        table1_plan.row_status("tiny", ["data.num_views=5", "loss.no_such_key=0"])
        == "skipped: key not available (loss.no_such_key)"
    )
    with pytest.raises(table1_plan.ConfigError):  # a wrong value is a mistake, not a missing key
        table1_plan.row_status("tiny", ["model.shape.sampler=nonsense"])
    text = table1_plan.plan("tiny", 40, [0, 1], 2, tmp_path, ["val.period=0"], data="train=a heldout=b")
    assert "runs of 40 iterations" in text and "estimated time" in text
    lines = [line.split("\t") for line in (tmp_path / "plan.tsv").read_text().splitlines()]
    assert [line[0] for line in lines] == [r.slug for r in table1_plan.TRAINED]
    usl5 = next(line for line in lines if line[0] == "usl5")
    assert usl5[2] == "train" and usl5[3].split() == table1_plan.budget_overrides(load_config("tiny"), 40) + [
        "val.period=0",
        "data.num_views=5",
    ]
    with pytest.raises(ValueError, match="another budget"):
        table1_plan.plan("tiny", 80, [0, 1], 2, tmp_path, ["val.period=0"], data="train=a heldout=b")
    assert (
        table1_plan.main(
            ["--out", str(tmp_path), "--iters", "40", "--seeds", "0,1,2", "--data", "train=a heldout=b", "val.period=0"]
        )
        == 0
    )  # more seeds on the same budget are fine


def test_a_folder_is_refused_once_its_recipe_file_changes(tmp_path):
    """Same recipe name, same options, edited recipe: its runs must not land in the old table."""
    recipe = tmp_path / "mine.yaml"
    tiny = CONFIG_DIR / "tiny.yaml"
    recipe.write_text(f"_base_: {tiny}\nloss: {{render: {{blur_radius: 9.21e-3}}}}\n")
    out = tmp_path / "table"
    table1_plan.plan(str(recipe), 40, [0], 1, out)
    table1_plan.plan(str(recipe), 40, [0, 1], 1, out)  # unchanged: more seeds are fine
    recipe.write_text(f"_base_: {tiny}\nloss: {{render: {{blur_radius: 4.6e-3}}}}\n")
    with pytest.raises(ValueError, match="another budget"):
        table1_plan.plan(str(recipe), 40, [0, 1], 1, out)
