"""``curves.png``: a run's training losses and validation metrics against iterations (matplotlib).

Top: the total loss and each loss term of ``metrics.csv`` (log scale when all are positive).
Then the learning rate, then one panel per kind of ``val/*`` metric of ``validation.csv`` (when
it exists): overlaps (IoU, gIoU), F1 in percent, depth L1 in metres, Chamfer-L2 in square metres,
so each quantity reads on its own axis. Legends sit right of the panels, off the curves.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

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


# Validation panels: (title, metric name prefixes after "val/"); other metrics get a panel of their own.
VALIDATION_PANELS = (
    ("overlap: IoU, gIoU (higher is better)", ("mask_iou", "box_giou")),
    ("F1 (%, higher is better)", ("f1",)),
    ("depth L1 (m, lower is better)", ("depth_l1",)),
    ("Chamfer-L2 (m², lower is better)", ("chamfer",)),
)


def validation_groups(keys: Sequence[str]) -> list[tuple[str, list[str]]]:
    """The ``val/*`` keys grouped by ``VALIDATION_PANELS`` (panels without keys left out)."""
    groups = [
        (title, [k for k in keys if k.removeprefix("val/").startswith(prefixes)])
        for title, prefixes in VALIDATION_PANELS
    ]
    known = {k for _, members in groups for k in members}
    groups += [(k.removeprefix("val/"), [k]) for k in keys if k not in known]
    return [(title, members) for title, members in groups if members]


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
            xs, ys = zip(*points, strict=True)
            axes.plot(xs, ys, marker=marker, linewidth=2.0 if key == "loss" else 1.0, label=key)
            drawn = True
    return drawn


def curves_figure(run_dir: str | Path, validation_csv: str | None = None):
    """The matplotlib Figure of ``curves.png`` (None when the run logged nothing yet)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    run_dir = Path(run_dir)
    if not (run_dir / CSV_NAME).is_file():
        return None
    rows = read_metrics(run_dir)
    val_rows = read_metrics(run_dir, validation_csv) if validation_csv and (run_dir / validation_csv).is_file() else []
    groups = validation_groups(list(dict.fromkeys(k for row in val_rows for k in row if k.startswith("val/"))))
    if not rows:
        return None
    ratios = [3, 1] + [2] * len(groups)
    height = sum(ratios) + 0.6 * len(ratios)
    figure = Figure(figsize=(11, height))
    FigureCanvasAgg(figure)
    # fixed margins, legends in the right margin: a constrained layout costs seconds on a busy CPU
    losses, lr, *rest = figure.subplots(
        len(ratios),
        1,
        sharex=True,
        gridspec_kw={
            "height_ratios": ratios,
            "hspace": 0.5,
            "top": 1 - 0.8 / height,
            "bottom": 0.5 / height,
            "left": 0.08,
            "right": 0.74,
        },
    )
    keys = loss_keys(rows)
    _plot(losses, rows, keys)
    if all(r[k] > 0 for r in rows for k in keys if k in r):
        losses.set_yscale("log")
    losses.set_title("training losses (means over each logging interval)")
    _plot(lr, rows, ["lr"])
    lr.set_title("learning rate")
    for axes, (title, members) in zip(rest, groups, strict=True):
        _plot(axes, val_rows, members, marker="o")
        axes.set_title(f"validation: {title}")
    for axes in [losses, lr, *rest]:
        axes.grid(alpha=0.3)
        if len(axes.get_lines()) > 1:
            axes.legend(fontsize="small", loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)
    figure.axes[-1].set_xlabel("iteration")
    figure.suptitle(f"{run_dir.name}", y=1 - 0.2 / height)
    return figure


def plot_curves(run_dir: str | Path, validation_csv: str | None = None) -> Path | None:
    """Write ``run_dir/curves.png``; returns its path (None when the run logged nothing yet)."""
    figure = curves_figure(run_dir, validation_csv)
    if figure is None:
        return None
    path = Path(run_dir) / CURVES_NAME
    tmp = temp_path(path, hidden=True)  # named after this process: reaped once it is gone
    try:
        figure.savefig(tmp, dpi=100, format="png")
        tmp.replace(path)
    finally:
        tmp.unlink(missing_ok=True)
    return path
