"""PNG plots for results folders: trajectories from above, series over frames, heat maps
(lattice snapshots).

matplotlib's object API with the Agg canvas: no pyplot, so no global backend or figure
state is touched and the functions are safe in any process and thread of their own.

matplotlib is the optional extra `plots` (the services never plot, so the container image
leaves it out): it is imported on the first plot, and without it every plot function writes
nothing, returns None and the process says so once.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from services.common.errors import DataError
from services.evaluation.trajectory import Trajectory

log = logging.getLogger(__name__)

DPI = 120
REFERENCE_LABELS = ("groundtruth", "ground truth", "ground_truth", "gt", "reference")


class PlotError(DataError):
    """Data handed to a plot does not fit (the message names the series)."""


_missing_said = False


def new_figure(**options):
    """A matplotlib Figure (Agg canvas), or None without matplotlib (said once per process)."""
    global _missing_said
    try:
        from matplotlib.figure import Figure
    except ImportError:
        if not _missing_said:
            log.warning("matplotlib is not installed: no PNG plots are written (pip install 'gridslam[plots]')")
            _missing_said = True
        return None
    return Figure(**options)


def save(figure, png_path) -> Path:
    """Write `figure` as a PNG, making its folder."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    path = Path(png_path)
    path.parent.mkdir(parents=True, exist_ok=True)
    FigureCanvasAgg(figure)
    figure.savefig(path, dpi=DPI, format="png")
    log.debug("wrote %s", path)
    return path


def plot_trajectories(png_path, trajectories: dict[str, Trajectory], title: str = "") -> Path | None:
    """Trajectories seen from above (x, y in metres, equal aspect), each with a circle at
    its start and a square at its end. A trajectory labelled like ground truth
    ("groundtruth", "gt", "reference") is drawn as a black dashed line beneath the others."""
    figure = new_figure(figsize=(7.0, 6.0), layout="constrained")
    if figure is None:
        return None
    from matplotlib.lines import Line2D

    axes = figure.add_subplot()
    colours = iter(f"C{k}" for k in range(100))
    drawn = 0
    for label, traj in trajectories.items():
        if len(traj) == 0:
            log.warning("trajectory %r is empty: not plotted", label)
            continue
        is_reference = label.strip().lower() in REFERENCE_LABELS
        colour = "black" if is_reference else next(colours)
        x, y = traj.positions[:, 0], traj.positions[:, 1]
        axes.plot(
            x, y, color=colour, linestyle="--" if is_reference else "-",
            linewidth=1.2 if is_reference else 1.6, label=f"{label} ({traj.path_length():.1f} m)",
            zorder=1 if is_reference else 2,
        )
        axes.plot(x[0], y[0], marker="o", color=colour, markersize=7, linestyle="none", zorder=3)
        axes.plot(x[-1], y[-1], marker="s", color=colour, markersize=7, linestyle="none", zorder=3)
        drawn += 1
    if drawn:
        handles, _ = axes.get_legend_handles_labels()
        handles += [
            Line2D([], [], marker="o", color="grey", linestyle="none", label="start"),
            Line2D([], [], marker="s", color="grey", linestyle="none", label="end"),
        ]
        axes.legend(handles=handles, loc="best", fontsize="small")
    axes.set_aspect("equal", adjustable="datalim")
    axes.set_xlabel("x [m] (forward at start)")
    axes.set_ylabel("y [m] (left at start)")
    axes.grid(True, alpha=0.3)
    if title:
        axes.set_title(title)
    return save(figure, png_path)


def plot_series(png_path, series: dict[str, tuple], xlabel: str, ylabel: str, title: str = "") -> Path | None:
    """Line plots of {label: (x, y)} on shared axes, e.g. error over frames, or template and
    experience counts over frames (the paper's Fig. 10)."""
    figure = new_figure(figsize=(8.0, 4.5), layout="constrained")
    if figure is None:
        return None
    axes = figure.add_subplot()
    for label, (x, y) in series.items():
        x, y = np.asarray(x, dtype=float).reshape(-1), np.asarray(y, dtype=float).reshape(-1)
        if x.shape != y.shape:
            raise PlotError(f"series {label!r}: {len(x)} x values but {len(y)} y values")
        axes.plot(x, y, label=label, linewidth=1.4)
    if series:
        axes.legend(loc="best", fontsize="small")
    axes.set_xlabel(xlabel)
    axes.set_ylabel(ylabel)
    axes.grid(True, alpha=0.3)
    if title:
        axes.set_title(title)
    return save(figure, png_path)


def plot_heatmaps(png_path, images: dict[str, np.ndarray], title: str = "", cmap: str = "viridis") -> Path | None:
    """2-D arrays side by side, each with its own colour scale, e.g. snapshots of the
    grid-cell lattice at several frames (the paper's Fig. 1)."""
    if not images:
        raise PlotError("no images to plot")
    figure = new_figure(figsize=(3.2 * len(images), 3.6), layout="constrained")
    if figure is None:
        return None
    for index, (label, image) in enumerate(images.items()):
        image = np.asarray(image, dtype=float)
        if image.ndim != 2:
            raise PlotError(f"image {label!r}: expected a 2-D array, got shape {image.shape}")
        axes = figure.add_subplot(1, len(images), index + 1)
        shown = axes.imshow(image, cmap=cmap, origin="lower", interpolation="nearest")
        figure.colorbar(shown, ax=axes, shrink=0.8)
        axes.set_title(label, fontsize="small")
        axes.set_xticks([])
        axes.set_yticks([])
    if title:
        figure.suptitle(title)
    return save(figure, png_path)
