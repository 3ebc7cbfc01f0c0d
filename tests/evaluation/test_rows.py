"""The table rows come from a registry of builders, read typed options, and keep the order asked."""

import ast
from pathlib import Path

import pytest

from data_specs import load_dataset_spec
from usl.errors import UslError
from usl.evaluation.choices import ROWS
from usl.evaluation.rows import ROW_BUILDERS, RowOptions, build_predictors

SPEC = {"name": "scene_shapes", "categories": [], "baselines": load_dataset_spec("scene_shapes")["baselines"]}


def test_the_registry_builds_every_row_help_lists_in_its_order():
    assert tuple(ROW_BUILDERS) == ROWS


def names(options):
    return [predictor.name for predictor in build_predictors(options, SPEC)[0]]


def test_rows_come_in_the_order_asked_each_once_and_default_to_the_sphere_baselines():
    assert names(RowOptions()) == ["Random depth", "Fixed depth"]
    rows = ("sphere_true_depth", "fixed", "random", "fixed")
    assert names(RowOptions(rows=rows)) == ["Sphere-only w/ true depth", "Fixed depth", "Random depth"]
    assert names(RowOptions(rows=())) == []
    predictors, scored = build_predictors(RowOptions(rows=("random",), seed=3, sphere_level=1), SPEC)
    assert scored is None and predictors[0].seed == 3 and predictors[0].level == 1


@pytest.mark.parametrize(
    "options,spec,message",
    [
        (RowOptions(rows=("oracle",)), SPEC, r"--rows: unknown row\(s\) \['oracle'\]"),
        (RowOptions(rows=("fixed", "layout_only", "model")), SPEC, "--rows layout_only,model need a --checkpoint"),
        (RowOptions(rows=("sphere_true_depth", "random")), {"name": "x"}, "--rows random: .* no random_depth"),
    ],
)
def test_rows_that_cannot_be_built_are_refused(options, spec, message):
    with pytest.raises(UslError, match=message):
        build_predictors(options, spec)


def test_evaluation_never_sees_the_command_line():
    """usl.cli builds the typed options; no evaluation module imports argparse."""
    for path in (Path(__file__).parents[2] / "usl" / "evaluation").glob("*.py"):
        nodes = list(ast.walk(ast.parse(path.read_text())))
        modules = [alias.name for node in nodes if isinstance(node, ast.Import) for alias in node.names]
        modules += [node.module for node in nodes if isinstance(node, ast.ImportFrom)]
        assert "argparse" not in modules, path
