"""scripts/experiments/table1_plan.py, table1_summary.py and table1_record.py: Table 1's rows, budget,
mean ± std over seeds of each run's mean over the held-out builds, the paper's orderings judged on
it, and its scores kept in a record that the table resumes from.

The fixtures are the files table1.sh leaves: usl-eval's ``metrics.json`` of each held-out build
written by usl-eval's own writer (``write_report``) and combined by ``table1_summary.py --combine``
as table1.sh does, run folders with checkpoints written by the trainer's ``write_run_checkpoint``;
the expected numbers come from numpy and pandas, the expected verdicts from the fixture's numbers.
"""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import table1_plan
import table1_record
import table1_summary

from usl.config import CONFIG_DIR, load_config
from usl.engine.checkpoint import write_run_checkpoint
from usl.evaluation.report import write_report
from usl.evaluation.summary import METRICS, PredictorSummary

HEADER = {"dataset": "scene_shapes", "split": "train", "num_scenes": 16, "num_input_views": 128}
SEEDS = {"usl2": [0, 1, 2], "usl5": [0, 1, 2], "usl5_vertalign": [4]}  # one row with a single seed
BUILDS = (1, 2, 3)  # the held-out builds' seeds, as table1.sh scores them


def _summary(name: str, rng: np.random.Generator) -> PredictorSummary:
    metrics = {m: float(rng.uniform(0.05, 0.9)) for m in METRICS}
    metrics["f1"] = float(rng.uniform(20, 70))  # percent, as usl-eval stores it
    return PredictorSummary(name, True, True, False, num_objects=16, metrics=metrics, counts={m: 16 for m in METRICS})


def _write_eval(eval_dir: Path, builds: dict[int, list[PredictorSummary]]) -> None:
    """usl-eval's report of each held-out build in ``eval_dir/seed<k>``, then their summary.json, as table1.sh does."""
    for seed, summaries in builds.items():
        write_report(eval_dir / f"seed{seed}", HEADER, summaries, [], "scene_shapes")
    assert table1_summary.main(["--combine", str(eval_dir)]) == 0


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
    baselines = {b: [_summary("Fixed depth", rng), _summary("Random depth", rng)] for b in BUILDS}
    _write_eval(out / "baselines" / "eval", baselines)
    records = [
        {"slug": p.name, "seed": 0, "build": b, "metric": m, "value": v}
        for b, summaries in baselines.items()
        for p in summaries
        for m, v in p.metrics.items()
    ]
    for slug, seeds in SEEDS.items():
        for seed in seeds:
            run = out / "runs" / slug / f"seed{seed}"
            write_run_checkpoint(run / "train", 20, {"model": {}, "config": {}})
            builds = {b: [_summary("USL", rng)] for b in BUILDS}
            _write_eval(run / "eval", builds)
            records += [
                {"slug": slug, "seed": seed, "build": b, "metric": m, "value": v}
                for b, (summary,) in builds.items()
                for m, v in summary.metrics.items()
            ]
    write_run_checkpoint(out / "runs" / "usl5" / "seed3" / "train", 10, {"model": {}, "config": {}})  # no eval yet
    partly = out / "runs" / "usl5" / "seed5"  # stopped while scoring: one build scored, no summary yet
    write_run_checkpoint(partly / "train", 20, {"model": {}, "config": {}})
    write_report(partly / "eval" / "seed1", HEADER, [_summary("USL", rng)], [], "scene_shapes")
    return out, pd.DataFrame(records)


def _run_figures(records: pd.DataFrame) -> pd.DataFrame:
    """Each run's figure on each metric: its mean over the held-out builds."""
    return records.groupby(["slug", "seed", "metric"], as_index=False)["value"].mean()


def test_mean_and_sample_std_match_pandas_and_numpy(table):
    out, records = table
    assert table1_summary.main([str(out)]) == 0
    rows = {r["slug"]: r for r in json.loads((out / "table1.json").read_text())["rows"]}
    runs = _run_figures(records)
    expected = runs.groupby(["slug", "metric"])["value"].agg(["mean", "std"])  # pandas' std: ddof=1
    for slug in ("usl2", "usl5"):
        assert rows[slug]["n"] == 3 and rows[slug]["status"] == "trained"
        for column in table1_summary.TABLE_COLUMNS:
            got = rows[slug]["metrics"][column.metric]
            values = records.query("slug == @slug and metric == @column.metric")["value"].to_numpy().reshape(3, 3)
            per_run = values.mean(axis=1)  # records are by seed, then build: a run's figure is its builds' mean
            assert got["values"] == pytest.approx(per_run, rel=1e-12)
            assert got["mean"] == pytest.approx(expected.loc[(slug, column.metric), "mean"], rel=1e-12)
            assert got["std"] == pytest.approx(np.std(per_run, ddof=1), rel=1e-12)
            assert got["std"] == pytest.approx(expected.loc[(slug, column.metric), "std"], rel=1e-12)
    fixed = records.query("slug == 'Fixed depth' and metric == 'f1'")["value"]
    assert rows["fixed"]["metrics"]["f1"]["values"] == pytest.approx([fixed.mean()], rel=1e-12)  # scored once
    single = rows["usl5_vertalign"]
    assert single["n"] == 1 and single["metrics"]["chamfer"]["std"] is None
    # seed3 has not been scored, seed5 not on every build
    assert [r["seed"] for r in rows["usl5"]["runs"]] == [0, 1, 2]


def test_a_runs_summary_is_the_main_jobs_over_its_builds(table):
    """Each build's usl-eval report stays; summary.json has the format of the main job's."""
    out, records = table
    eval_dir = out / "runs" / "usl2" / "seed1" / "eval"
    assert sorted(p.name for p in eval_dir.glob("seed*/metrics.json")) == ["metrics.json"] * 3
    summary = json.loads((eval_dir / "summary.json").read_text())
    assert summary["seeds"] == [1, 2, 3] and summary["num_input_views"] == {"1": 128, "2": 128, "3": 128}
    values = records.query("slug == 'usl2' and seed == 1 and metric == 'mask_iou_views'")["value"].to_numpy()
    row = summary["rows"]["USL"]["mask_iou_views"]
    assert row["values"] == pytest.approx(values) and row["mean"] == pytest.approx(values.mean(), rel=1e-12)
    assert row["std"] == pytest.approx(np.std(values, ddof=1), rel=1e-12)
    assert table1_summary.main(["--combine", str(out / "runs" / "usl5" / "seed3")]) == 2  # no build scored there


def test_markdown_cells_are_formatted_like_usl_eval(table):
    out, records = table
    table1_summary.main([str(out)])
    text = (out / "table1.md").read_text()
    assert text.startswith(
        "Scored on every input view of the train split of held-out builds with seeds 1, 2, 3 (384 input views per model)"
    )
    lines = text.split("The paper's orderings")[0].splitlines()  # the summary table, above the orderings
    cells = {
        line.split("|")[1].strip(): [c.strip() for c in line.strip("|").split("|")]
        for line in lines
        if line.startswith("| ")
    }
    assert lines[2].startswith("| Model | Ch. ↓ | F1@0.1 | Mask IoU input | Mask IoU views | Seeds | Checkpoint |")
    runs = _run_figures(records)
    chamfer = runs.query("slug == 'usl5' and metric == 'chamfer'")["value"]
    iou = runs.query("slug == 'usl5' and metric == 'mask_iou_views'")["value"] * 100  # IoU in percent
    row = cells["USL (5 views)"]
    assert row[1] == f"{chamfer.mean():.3f} ± {chamfer.std():.3f}"
    assert row[4] == f"{iou.mean():.1f} ± {iou.std():.1f}"
    assert row[5] == "n=3 (seed 0, 1, 2)" and row[6] == "model_0000020.pt (iteration 20)"
    single = cells["USL (5) w/o RoIMap"]
    assert "±" not in single[1] and single[5] == "n=1 (seed 4)"
    assert cells["USL (5) w/o ℓ_dist"][5] == "skipped: key not available (loss.weights.dist)"
    assert cells["Fixed depth"][5] == "– (not trained)" and "Mesh R-CNN (3D sup.)" not in cells  # not in this plan
    fixed = records.query("slug == 'Fixed depth' and metric == 'f1'")["value"]  # its three builds
    assert cells["Fixed depth"][2] == f"{fixed.mean():.1f}"
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
    # the main job's held-out builds: 3 x 16 train scenes of 20 x 8 views, each an input view
    assert "scoring 384 held-out input views (3 builds, every input view)" in text
    assert table1_plan.heldout_input_views(3) == 8  # --quick's: one train scene of three
    lines = [line.split("\t") for line in (tmp_path / "plan.tsv").read_text().splitlines()]
    assert [line[0] for line in lines] == [r.slug for r in table1_plan.TRAINED]
    assert "for the 10 runs not scored yet" in text
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


# Orderings: each row's runs (seeds) as (Chamfer, F1 in percent, Mask IoU input, Mask IoU views); every
# run is scored on the three builds at 0.9, 1 and 1.1 times these, so its figure (their mean) is them.
FIGURES = {
    "fixed": [(0.20, 25.0, 0.40, 0.20)],
    "random": [(0.25, 22.0, 0.38, 0.18)],
    "usl2": [(0.100, 40.0, 0.46, 0.30), (0.110, 41.0, 0.47, 0.31)],
    "usl5": [(0.090, 43.0, 0.44, 0.33), (0.092, 44.0, 0.45, 0.34)],
    "usl5_vertalign": [(0.095, 42.0, 0.46, 0.32), (0.097, 42.5, 0.47, 0.32)],
    "usl5_no_dist": [(0.088, 42.0, 0.40, 0.28), (0.096, 44.0, 0.41, 0.29)],
    "meshrcnn_3d": [(0.050, 60.0, 0.50, 0.45), (0.060, 58.0, 0.42, 0.44)],
}
BUILD_SCALES = {1: 0.9, 2: 1.0, 3: 1.1}
NAMES = {"fixed": "Fixed depth", "random": "Random depth"}


def _figures_table(out: Path, figures: dict[str, list[tuple]], plan: dict[str, str]) -> Path:
    """A table1.sh output folder whose runs score ``figures`` (mean over builds); ``plan``: slug -> status."""
    labels = {r.slug: r.label for r in table1_plan.ROWS}
    (out / "plan.tsv").parent.mkdir(parents=True)
    (out / "plan.tsv").write_text(
        "".join(f"{s}\t{labels[s]}\t{status}\toptim.max_iter=20\n" for s, status in plan.items())
    )

    def summaries(rows: dict[str, tuple], scale: float) -> list[PredictorSummary]:
        made = []
        for name, (chamfer, f1, iou_input, iou_views) in rows.items():
            metrics = dict.fromkeys(METRICS, 0.5)
            metrics.update(chamfer=chamfer * scale, f1=f1 * scale, mask_iou_input=iou_input * scale)
            metrics["mask_iou_views"] = iou_views * scale
            made.append(PredictorSummary(name, True, True, False, 16, metrics, dict.fromkeys(METRICS, 16)))
        return made

    baselines = {NAMES[s]: figures[s][0] for s in NAMES if s in figures}
    if baselines:
        _write_eval(out / "baselines" / "eval", {b: summaries(baselines, k) for b, k in BUILD_SCALES.items()})
    for slug in plan:
        for seed, run_figures in enumerate(figures.get(slug, [])):
            run = out / "runs" / slug / f"seed{seed}"
            write_run_checkpoint(run / "train", 20, {"model": {}, "config": {}})
            _write_eval(run / "eval", {b: summaries({"USL": run_figures}, k) for b, k in BUILD_SCALES.items()})
    return out


def _judged(out: Path) -> dict[str, dict]:
    assert table1_summary.main([str(out)]) == 0
    return {o["key"]: o for o in json.loads((out / "table1.json").read_text())["orderings"]}


def _shown(slug: str, metric: int, scale: float, decimals: int) -> str:
    """A row's figure as the table prints it, worked out from FIGURES: mean ± sample std over seeds."""
    values = np.array([run[metric] for run in FIGURES[slug]]) * scale
    return f"{values.mean():.{decimals}f}" + (f" ± {values.std(ddof=1):.{decimals}f}" if len(values) > 1 else "")


ALL_TRAINED = dict.fromkeys(["usl2", "usl5", "usl5_vertalign", "usl5_no_dist", "meshrcnn_3d"], "train")


def test_the_papers_orderings_are_judged_on_the_means(tmp_path):
    out = _figures_table(tmp_path / "t", FIGURES, ALL_TRAINED)
    judged = _judged(out)
    # By hand, on the means over seeds (Chamfer, F1, IoU input, IoU views):
    # fixed 0.200 25.0 0.400 0.200, random 0.250 22.0 0.380 0.180, usl2 0.105 40.5 0.465 0.305,
    # usl5 0.091 43.5 0.445 0.335, vertalign 0.096 42.25 0.465 0.320, no_dist 0.092 43.0 0.405 0.285,
    # meshrcnn 0.055 59.0 0.460 0.445.
    # (a) every USL row is below 0.200 Chamfer, above 25.0 F1, 0.400 IoU input and 0.200 IoU views.
    # (b) usl5 beats usl2 on Chamfer, F1 and IoU views (IoU input, 0.445 < 0.465, is not asked).
    # (c) vertalign's IoU input 0.465 beats usl5's 0.445: the one failing comparison.
    # (d) no_dist is 0.001 behind on Chamfer (tolerance: its std 0.0057) and 0.5 on F1 (its std 1.41).
    # (e) no_dist is below usl5 on both IoUs. (f) meshrcnn's IoU input 0.460 is below usl2's and
    # vertalign's 0.465.
    assert {k: o["verdict"] for k, o in judged.items()} == {
        "a": "holds",
        "b": "holds",
        "c": "does not hold",
        "d": "holds",
        "e": "holds",
        "f": "does not hold",
    }
    c_fails = [c["text"] for c in judged["c"]["comparisons"] if not c["holds"]]
    assert c_fails == [
        f"Mask IoU input: USL (5 views) {_shown('usl5', 2, 100, 1)} vs USL (5) w/o RoIMap {_shown('usl5_vertalign', 2, 100, 1)}"
    ]
    f_fails = [c["text"] for c in judged["f"]["comparisons"] if not c["holds"]]
    assert f_fails == [
        f"Mask IoU input: Mesh R-CNN (3D sup.) {_shown('meshrcnn_3d', 2, 100, 1)} vs {label} {_shown(slug, 2, 100, 1)}"
        for slug, label in (("usl2", "USL (2 views)"), ("usl5_vertalign", "USL (5) w/o RoIMap"))
    ]
    assert len(judged["a"]["comparisons"]) == 4 * 2 * 4 and len(judged["b"]["comparisons"]) == 3
    tolerance = np.std([0.088, 0.096], ddof=1)  # no_dist's Chamfer std, the larger of the two rows'
    assert judged["d"]["comparisons"][0]["text"] == (
        f"Ch. ↓: USL (5) w/o ℓ_dist {_shown('usl5_no_dist', 0, 1, 3)} vs USL (5 views) {_shown('usl5', 0, 1, 3)}, "
        f"tolerance {tolerance:.3f}"
    )
    text = (out / "table1.md").read_text()
    assert (
        "- (c) RoIMap (USL (5 views)) beats VertAlign (USL (5) w/o RoIMap) on every metric: **does not hold** (fails on Mask IoU input:"
        in text
    )
    assert "- (a) every USL row beats both baselines on all four metrics: **holds** (all 32 comparisons" in text


def test_an_ordering_needing_an_unfinished_row_is_not_measured_unless_another_comparison_fails(tmp_path):
    figures = {**FIGURES, "usl5_no_dist": [(0.120, 42.0, 0.40, 0.28), (0.130, 44.0, 0.41, 0.29)]}
    figures.pop("meshrcnn_3d")  # planned, never finished
    judged = _judged(_figures_table(tmp_path / "t1", figures, ALL_TRAINED))
    # no_dist's Chamfer 0.125 is 0.034 behind usl5's 0.091, past the larger std (0.0071): (d) fails;
    # it still beats both spheres, so (a) holds; (f) has no Mesh R-CNN run.
    assert {k: o["verdict"] for k, o in judged.items()} == {
        "a": "holds",
        "b": "holds",
        "c": "does not hold",
        "d": "does not hold",
        "e": "holds",
        "f": "not measured",
    }
    assert judged["f"]["missing"] == ["Mesh R-CNN (3D sup.)"] and judged["f"]["comparisons"] == []
    assert [c["holds"] for c in judged["d"]["comparisons"]] == [False, True]  # Chamfer fails, F1 within 1.41

    skipped = {**ALL_TRAINED, "usl5_no_dist": "skipped: key not available (loss.weights.dist)"}
    no_spheres = {k: v for k, v in FIGURES.items() if k not in NAMES}
    judged = _judged(_figures_table(tmp_path / "t2", no_spheres, skipped))
    # (a) lacks the spheres and no_dist; (d), (e) lack no_dist; (f) lacks no_dist but already fails
    # on the IoU input of usl2 and vertalign, which a missing row cannot undo.
    assert {k: o["verdict"] for k, o in judged.items()} == {
        "a": "not measured",
        "b": "holds",
        "c": "does not hold",
        "d": "not measured",
        "e": "not measured",
        "f": "does not hold",
    }
    assert judged["a"]["missing"] == ["Fixed depth", "Random depth", "USL (5) w/o ℓ_dist"]
    text = (tmp_path / "t2" / "table1.md").read_text()
    assert "**not measured** (no finished run of Fixed depth, Random depth, USL (5) w/o ℓ_dist)" in text


def test_the_estimate_counts_only_runs_not_scored_and_their_measured_cpu_time(tmp_path):
    text = table1_plan.plan("tiny", 40, [0, 1], 2, tmp_path, data="train=a heldout=b")
    before = re.search(r"estimated time: (.*) on 2 idle cores for the 10 runs", text)
    run = tmp_path / "runs" / "usl2" / "seed0"
    (run / "eval").mkdir(parents=True)
    (run / "eval" / "summary.json").write_text("{}")
    (run / "train_time.txt").write_text("100 4000\n")  # wall, CPU seconds: 100 s an iteration
    text = table1_plan.plan("tiny", 40, [0, 1], 2, tmp_path, data="train=a heldout=b")
    assert before and "for the 9 runs not scored yet" in text and "usl2 100.00" in text
    per_run = 3 * table1_plan.EVAL_START_SECONDS + 384 * table1_plan.EVAL_SECONDS_PER_VIEW
    others = sum(40 * table1_plan.MEASURED_SECONDS_PER_ITER[r.slug] + per_run for r in table1_plan.TRAINED[1:])
    expected = (40 * 100 + per_run + 2 * others) / 2  # usl2's seed 1 at its measured rate, both seeds of the rest
    assert f"estimated time: {table1_plan.duration(expected)} on 2 idle cores" in text
    # a run resumed at iteration 30 timed its last 10 iterations only: 50 s an iteration
    (tmp_path / "runs" / "usl2" / "seed1").mkdir()
    (tmp_path / "runs" / "usl2" / "seed1" / "train_time.txt").write_text("30 500 10\n")
    text = table1_plan.plan("tiny", 40, [0, 1], 2, tmp_path, data="train=a heldout=b")
    assert "usl2 75.00" in text  # the mean of the two runs' rates


def _files(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file())


def test_a_record_holds_the_scores_and_gives_the_same_table(table, tmp_path):
    out, _ = table
    record = tmp_path / "record"
    (out / "budget.txt").write_text("config=tiny\n")
    (out / "runs" / "usl2" / "seed0" / "train_time.txt").write_text("10 20\n")
    folders = table1_record.finished(out)
    assert folders == ["baselines"] + [f"runs/{slug}/seed{s}" for slug, seeds in sorted(SEEDS.items()) for s in seeds]
    assert table1_record.main(["save", str(out), str(record), *folders, "plan.tsv", "budget.txt"]) == 0
    kept = _files(record)
    assert not [f for f in kept if f.endswith(".pt") or ".partial" in f or ".previous" in f]
    assert "runs/usl2/seed0/train_time.txt" in kept and "runs/usl2/seed0/train/checkpoints/last_checkpoint" in kept
    assert {f for f in kept if f.startswith("runs/usl5/seed1/eval/")} == {
        f"runs/usl5/seed1/eval/{name}" for name in ["summary.json"] + [f"seed{b}/metrics.json" for b in BUILDS]
    }
    assert table1_summary.main([str(out)]) == 0 and table1_summary.main([str(record)]) == 0
    assert (record / "table1.md").read_text() == (out / "table1.md").read_text()  # checkpoint paths included


def test_a_table_resumes_from_its_record(table, tmp_path, capsys):
    out, _ = table
    record, fresh = tmp_path / "record", tmp_path / "fresh"
    (out / "budget.txt").write_text("config=tiny\n")
    assert (
        table1_record.main(["save", str(out), str(record), *table1_record.finished(out), "plan.tsv", "budget.txt"]) == 0
    )
    # another machine: the same budget, one run already scored there, the rest only in the record
    scored_here = fresh / "runs" / "usl2" / "seed0"
    shutil.copytree(out / "runs" / "usl2" / "seed0", scored_here)
    (scored_here / "eval" / "summary.json").write_text(json.dumps({"kept": True}))
    (fresh / "budget.txt").write_text("config=tiny\n")
    assert table1_record.main(["restore", str(record), str(fresh)]) == 0
    restored = [line.split()[2] for line in capsys.readouterr().out.splitlines()]
    assert restored == [f for f in table1_record.finished(out) if f != "runs/usl2/seed0"]
    assert json.loads((scored_here / "eval" / "summary.json").read_text()) == {"kept": True}  # not overwritten
    assert table1_record.finished(fresh) == table1_record.finished(out)  # table1.sh will not redo them
    shutil.copyfile(out / "runs" / "usl2" / "seed0" / "eval" / "summary.json", scored_here / "eval" / "summary.json")
    shutil.copyfile(out / "plan.tsv", fresh / "plan.tsv")
    assert table1_summary.main([str(out)]) == 0 and table1_summary.main([str(fresh)]) == 0
    assert (fresh / "table1.md").read_text() == (out / "table1.md").read_text()
    # the unscored runs of the output folder were neither recorded nor restored
    assert not (fresh / "runs" / "usl5" / "seed3").exists() and not (fresh / "runs" / "usl5" / "seed5").exists()


def test_a_record_of_another_budget_or_an_unscored_run_is_refused(table, tmp_path, capsys):
    out, _ = table
    record = tmp_path / "record"
    (out / "budget.txt").write_text("config=tiny\noverrides=optim.max_iter=20\n")
    assert table1_record.main(["save", str(out), str(record), "budget.txt", "runs/usl2/seed0"]) == 0
    other = tmp_path / "other"
    other.mkdir()
    (other / "budget.txt").write_text("config=tiny\noverrides=optim.max_iter=40\n")
    assert table1_record.main(["restore", str(record), str(other)]) == 2
    assert "hold runs of different budgets" in capsys.readouterr().err
    assert not (other / "runs").exists()
    assert table1_record.main(["save", str(out), str(record), "runs/usl5/seed5"]) == 2  # stopped while scoring
    assert f"{out / 'runs' / 'usl5' / 'seed5'}: not scored yet" in capsys.readouterr().err
    assert table1_record.main(["save", str(out), str(record), "runs/usl5"]) == 2
    assert "not a run" in capsys.readouterr().err


def test_saving_a_run_again_replaces_its_record_whole(table, tmp_path):
    out, _ = table
    record = tmp_path / "record"
    run = "runs/usl5/seed1"
    assert table1_record.main(["save", str(out), str(record), run]) == 0
    (record / run / "eval" / "stale.txt").write_text("from an earlier save")
    (out / run / "eval" / "seed3" / "metrics.json").rename(out / run / "eval" / "seed3" / "kept.json")
    assert table1_record.main(["save", str(out), str(record), run]) == 0
    assert "eval/seed2/metrics.json" in _files(record / run) and "eval/seed3/metrics.json" not in _files(record / run)
    assert not (record / run / "eval" / "stale.txt").exists()
    assert sorted(p.name for p in (record / "runs" / "usl5").iterdir()) == ["seed1"]  # no partial or previous copy left
