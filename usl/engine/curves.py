"""``curves.png``: a run's training losses and validation metrics against iterations (matplotlib).

Top: the total loss and each loss term of ``metrics.csv`` (log scale when all are positive).
Middle: the learning rate. Bottom: the ``val/*`` metrics of ``validation.csv`` (when it exists).
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

from usl.engine.run_log import CSV_NAME, read_metrics
from usl.records.tempfiles import temp_path

CURVES_NAME = "curves.png"
# Columns of metrics.csv that are not loss terms (statistics under "stat/" are not either).
NOT_LOSSES = {
    "iteration",
    "epoch",
    "lr",
    "grad_norm",
    "grad_norm_max",
    "clipped",
    "skipped",
    "time",
    "data_time",
    "peak_mem_mb",
}


def loss_keys(rows: Sequence[dict[str, float]]) -> list[str]:
    """``loss`` first, then the terms it sums, in column order."""
    keys = list(dict.fromkeys(k for row in rows for k in row))
    terms = [k for k in keys if k not in NOT_LOSSES and not k.startswith("stat/") and k != "loss"]
    return (["loss"] if "loss" in keys else []) + terms


def _plot(axes, rows: Sequence[dict[str, float]], keys: Sequence[str], marker: str | None = None) -> bool:
    drawn = False
    for key in keys:
        points = [(r["iteration"], r[key]) for r in rows if key in r]
        if points:
            xs, ys = zip(*points)
            axes.plot(xs, ys, marker=marker, linewidth=2.0 if key == "loss" else 1.0, label=key)
            drawn = True
    return drawn


def plot_curves(run_dir: str | Path, validation_csv: str | None = None) -> Path | None:
    """Write ``run_dir/curves.png``; returns its path (None when the run logged nothing yet)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    run_dir = Path(run_dir)
    if not (run_dir / CSV_NAME).is_file():
        return None
    rows = read_metrics(run_dir)
    val_rows = read_metrics(run_dir, validation_csv) if validation_csv and (run_dir / validation_csv).is_file() else []
    val_keys = list(dict.fromkeys(k for row in val_rows for k in row if k.startswith("val/")))
    if not rows:
        return None
    panels = 3 if val_keys else 2
    ratios = [3, 1, 3][:panels]
    height = sum(ratios) + 1.2
    figure = Figure(figsize=(9, height))
    FigureCanvasAgg(figure)
    # fixed margins: a constrained layout costs seconds on a busy CPU
    losses, lr, *rest = figure.subplots(
        panels,
        1,
        sharex=True,
        gridspec_kw={
            "height_ratios": ratios,
            "hspace": 0.45,
            "top": 1 - 0.8 / height,
            "bottom": 0.5 / height,
            "left": 0.1,
            "right": 0.97,
        },
    )
    keys = loss_keys(rows)
    _plot(losses, rows, keys)
    if all(r[k] > 0 for r in rows for k in keys if k in r):
        losses.set_yscale("log")
    losses.set_title("training losses (means over each logging interval)")
    losses.legend(fontsize="small", ncol=3)
    _plot(lr, rows, ["lr"])
    lr.set_title("learning rate")
    if rest:
        (val,) = rest
        _plot(val, val_rows, val_keys, marker="o")
        val.set_title(f"validation metrics ({validation_csv})")
        val.legend(fontsize="small", ncol=3)
    for axes in [losses, lr, *rest]:
        axes.grid(alpha=0.3)
    figure.axes[-1].set_xlabel("iteration")
    figure.suptitle(f"{run_dir.name}", y=1 - 0.2 / height)
    path = run_dir / CURVES_NAME
    tmp = temp_path(path, hidden=True)  # named after this process: reaped once it is gone
    try:
        figure.savefig(tmp, dpi=100, format="png")
        tmp.replace(path)
    finally:
        tmp.unlink(missing_ok=True)
    return path
