"""curves.png reads: one panel per kind of quantity, legends off the curves (checked on matplotlib's
own figure and on the PNG it writes)."""

from __future__ import annotations

import csv

import cv2
import numpy as np

from usl.engine.curves import curves_figure, plot_curves

VALIDATION = {
    "val/mask_iou_input": 0.3,
    "val/mask_iou_views": 0.25,
    "val/box_giou_input": 0.6,
    "val/box_giou_views": 0.4,
    "val/depth_l1_input": 0.15,
    "val/depth_l1_views": 0.17,
    "val/chamfer": 0.04,
    "val/f1": 56.0,
}


def write_csv(path, rows):
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


def fake_run(run_dir):
    run_dir.mkdir()
    write_csv(
        run_dir / "metrics.csv",
        [{"iteration": i, "loss": 3 / i, "l3d": 1 / i, "det/loss_cls": 2 / i, "lr": 0.01} for i in range(10, 1300, 10)],
    )
    steps = list(range(150, 1300, 150)) + [1290]
    write_csv(
        run_dir / "validation.csv",
        [{"iteration": i, **{k: v * (1 + i / 2000) for k, v in VALIDATION.items()}} for i in steps],
    )
    return steps


def test_each_panel_holds_one_kind_of_quantity_and_legends_sit_outside(tmp_path):
    steps = fake_run(tmp_path / "run")
    figure = curves_figure(tmp_path / "run", "validation.csv")
    panels = {axes.get_title(): [line.get_label() for line in axes.get_lines()] for axes in figure.axes}
    validation = {title: labels for title, labels in panels.items() if title.startswith("validation")}
    assert sorted(label for labels in validation.values() for label in labels) == sorted(VALIDATION)
    for title, labels in validation.items():  # F1 (0-100) never shares an axis with IoU or metres
        kinds = {label.removeprefix("val/").split("_")[0] for label in labels}
        assert kinds <= {"mask", "box"} or len(kinds) == 1, (title, labels)
    for axes in figure.axes:
        assert all(len(line.get_xdata()) in (len(steps), 129) for line in axes.get_lines())
    figure.canvas.draw()
    renderer = figure.canvas.get_renderer()
    legends = [axes for axes in figure.axes if axes.get_legend() is not None]
    assert len(legends) >= 3  # losses, overlaps, depth
    for axes in legends:
        legend, data = axes.get_legend().get_window_extent(renderer), axes.get_window_extent(renderer)
        assert legend.x0 >= data.x1 and legend.x1 <= figure.bbox.x1, axes.get_title()  # right of the data, on the page


def test_png_is_written_with_a_panel_per_quantity(tmp_path):
    fake_run(tmp_path / "run")
    path = plot_curves(tmp_path / "run", "validation.csv")
    image = cv2.imread(str(path))
    assert image is not None and image.shape[0] > 1000 and np.std(image) > 10
