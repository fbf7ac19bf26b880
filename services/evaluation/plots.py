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


def plot_layout(png_path, walls: np.ndarray, route: np.ndarray, regions: dict[str, list] | None = None,
                labels: dict[str, tuple[float, float]] | None = None, title: str = "") -> Path | None:
    """A world from above: wall segments (N×4: x0, y0, dx, dy) in black, the route (M×2) coloured
    by distance driven with its start marked, labelled rectangles (x0, x1, y0, y1) per
    ``regions`` name (e.g. look-alike places) and text at ``labels`` points."""
    walls, route = np.asarray(walls, dtype=float), np.asarray(route, dtype=float)
    if walls.ndim != 2 or walls.shape[1] != 4 or route.ndim != 2 or route.shape[1] != 2:
        raise PlotError(f"walls must be N×4 and the route M×2, got {walls.shape} and {route.shape}")
    from matplotlib.collections import LineCollection
    from matplotlib.patches import Rectangle

    extent = np.ptp(np.r_[walls[:, :2], walls[:, :2] + walls[:, 2:]], axis=0)
    figure = new_figure(figsize=(11.0, 11.0 * extent[1] / extent[0] + 1.2), layout="constrained")
    if figure is None:
        return None
    axes = figure.add_subplot()
    axes.add_collection(LineCollection(np.stack([walls[:, :2], walls[:, :2] + walls[:, 2:]], axis=1), colors="black", linewidths=0.8))
    shown = axes.scatter(route[:, 0], route[:, 1], c=np.arange(len(route)), s=0.6, cmap="viridis", zorder=2)
    figure.colorbar(shown, ax=axes, shrink=0.6, label="frame")
    axes.plot(route[0, 0], route[0, 1], marker="o", color="red", markersize=8, linestyle="none", label="start", zorder=3)
    for index, (name, rectangles) in enumerate((regions or {}).items()):
        for x0, x1, y0, y1 in rectangles:
            axes.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, edgecolor=f"C{index + 1}", linewidth=2.0, zorder=4))
        axes.plot([], [], color=f"C{index + 1}", linewidth=2.0, label=name)
    for text, (x, y) in (labels or {}).items():
        axes.annotate(text, (x, y), fontsize="small", ha="center", va="center", color="dimgray", zorder=5)
    axes.legend(loc="upper right", fontsize="small")
    axes.set_aspect("equal", adjustable="datalim")
    axes.set_xlabel("x [m] (east)")
    axes.set_ylabel("y [m] (north)")
    axes.grid(True, alpha=0.3)
    if title:
        axes.set_title(title)
    return save(figure, png_path)
