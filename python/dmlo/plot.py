"""Top-view trajectory plots (PNG), estimate against ground truth.

The view plane is chosen from the data: the two coordinate axes along which the trajectories extend the
most. For LiDAR poses (z up) that is x–y; for KITTI camera poses (y down) it is x–z. Matplotlib is used
through its Agg canvas directly, so no GUI backend is touched and nothing global is changed. Matplotlib is
optional (the ``plot`` extra): without it :func:`plot_trajectories` raises :class:`PlotUnavailable`, which the
commands turn into a one-line notice and skip the plot.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from dmlo.poses import as_poses

__all__ = ["PLOT_INSTALL_HINT", "PlotUnavailable", "plot_trajectories", "view_axes"]

PLOT_INSTALL_HINT = "pip install 'dmlo[plot]'"


class PlotUnavailable(ImportError):
    """Matplotlib (the ``plot`` extra) is not installed; the message says how to get it."""

_AXIS_NAMES = ("x", "y", "z")


def view_axes(*trajectories: NDArray[np.float64]) -> tuple[int, int]:
    """The two axes (sorted) along which the given ``(N, 4, 4)`` trajectories extend the most."""
    positions = np.concatenate([t[:, :3, 3] for t in trajectories])
    extent = positions.max(axis=0) - positions.min(axis=0)
    # Stable on ties (a perfectly flat or straight drive): prefer x, then y, then z.
    order = np.argsort(-extent, kind="stable")
    first, second = sorted(int(axis) for axis in order[:2])
    return first, second


def plot_trajectories(
    ground_truth: ArrayLike | None,
    estimate: ArrayLike,
    path: str | os.PathLike[str],
    *,
    title: str | None = None,
    estimate_label: str = "estimate",
    ground_truth_label: str = "ground truth",
    axes: tuple[int, int] | None = None,
    dpi: int = 120,
) -> Path:
    """Draw the estimated (and ground-truth) trajectory from above into a PNG file; returns its path.

    ``ground_truth`` (or None) and ``estimate`` are ``(N, 4, 4)`` poses in the same world frame (they may
    differ in length, e.g. a run stopped early); ``axes`` forces the
    view plane (e.g. ``(0, 2)`` for x–z), otherwise it is chosen by :func:`view_axes`. Raises
    :class:`PlotUnavailable` without matplotlib.
    """
    try:
        import matplotlib  # noqa: F401  (the optional dependency itself, checked first)
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError:
        raise PlotUnavailable(f"plots need matplotlib: {PLOT_INSTALL_HINT}") from None

    est = as_poses(estimate, "estimate")
    gt = None if ground_truth is None else as_poses(ground_truth, "ground_truth")
    if axes is None:
        axes = view_axes(est) if gt is None else view_axes(est, gt)
    if len(axes) != 2 or len(set(axes)) != 2 or not all(a in (0, 1, 2) for a in axes):
        raise ValueError(f"axes must be two different axis indices out of 0, 1, 2, got {axes}")
    a, b = axes

    figure = Figure(figsize=(7.0, 7.0), dpi=dpi)
    FigureCanvasAgg(figure)
    ax = figure.add_subplot(1, 1, 1)
    if gt is not None:
        ax.plot(gt[:, :3, 3][:, a], gt[:, :3, 3][:, b], color="black", linewidth=1.5, label=ground_truth_label)
    ax.plot(est[:, :3, 3][:, a], est[:, :3, 3][:, b], color="tab:red", linewidth=1.2, label=estimate_label)
    start = (gt if gt is not None else est)[0, :3, 3]
    ax.plot(start[a], start[b], marker="s", color="tab:blue", linestyle="none", markersize=6, label="start")
    ax.set_xlabel(f"{_AXIS_NAMES[a]} [m]")
    ax.set_ylabel(f"{_AXIS_NAMES[b]} [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, linewidth=0.4, alpha=0.5)
    ax.legend(loc="best")
    if title:
        ax.set_title(title)
    figure.tight_layout()

    output = Path(path)
    output.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(output, format="png")
    return output
