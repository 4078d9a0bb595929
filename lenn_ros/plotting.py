"""Figures in the style of the paper's Figs. 4-7: plant, model and error over k.

Figures are ``matplotlib.figure.Figure`` objects drawn by the Agg canvas directly: no
pyplot, no ``matplotlib.use``. A program that imports lenn_ros keeps its own backend
(an interactive session, a GUI), and nothing is left in pyplot's figure registry.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lenn_ros.errors import require_extra

require_extra("matplotlib", "plot", "plots")

from matplotlib.axes import Axes  # noqa: E402
from matplotlib.backends.backend_agg import FigureCanvasAgg  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402


def new_figure(width: float = 8.0, height: float = 3.6, dpi: int = 110) -> tuple[Figure, Axes]:
    """One figure with one axis, bound to its own Agg canvas."""
    figure = Figure(figsize=(width, height), dpi=dpi)
    FigureCanvasAgg(figure)
    return figure, figure.add_subplot()


def save(figure: Figure, path: str | Path) -> Path:
    """Write the figure as PNG (creating the directory)."""
    figure.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path)
    return path


def plot_identification(
    path: str | Path,
    y_plant: np.ndarray,
    y_model: np.ndarray,
    title: str,
    y_free_run: np.ndarray | None = None,
    free_run_band: float | None = None,
) -> Path:
    """Write a PNG of plant output, model output and error (one-step), as in the paper.

    ``free_run_band``: half-width of the free run's nominal 95 % band (``fit``'s), drawn around it.
    """
    y_plant = np.asarray(y_plant)
    y_model = np.asarray(y_model)
    k = np.arange(len(y_plant))
    figure, axis = new_figure()
    axis.plot(k, y_plant, color="black", linewidth=1.4, label="plant")
    axis.plot(k, y_model, color="tab:red", linestyle="--", linewidth=1.2, label="model (one step)")
    if y_free_run is not None:
        axis.plot(k, y_free_run, color="tab:green", linestyle=":", linewidth=1.2, label="model (free run)")
        if free_run_band:
            axis.fill_between(k, y_free_run - free_run_band, y_free_run + free_run_band, color="tab:green",
                              alpha=0.15, linewidth=0, label="free run 95 % band")  # fmt: skip
    axis.plot(k, y_plant - y_model, color="tab:blue", linewidth=0.9, label="error")
    axis.set_xlabel("discrete time k (test phase)")
    axis.set_ylabel("plant / model output and error")
    axis.set_title(title, fontsize=10)
    axis.grid(alpha=0.3)
    axis.legend(loc="upper right", fontsize=8, ncol=2)
    return save(figure, path)


def plot_channels(
    path: str | Path,
    names: list[str] | tuple[str, ...],
    y_plant: np.ndarray,
    y_model: np.ndarray,
    title: str,
    y_free_run: np.ndarray | None = None,
) -> Path:
    """:func:`plot_identification` for several output channels: one panel each, columns of the arrays."""
    y_plant = np.asarray(y_plant).reshape(len(y_plant), -1)
    y_model = np.asarray(y_model).reshape(y_plant.shape)
    k = np.arange(len(y_plant))
    figure = Figure(figsize=(8.0, 2.6 * len(names) + 0.6), dpi=110)
    FigureCanvasAgg(figure)
    axes = figure.subplots(len(names), 1, sharex=True, squeeze=False)[:, 0]
    for j, (axis, name) in enumerate(zip(axes, names, strict=True)):
        axis.plot(k, y_plant[:, j], color="black", linewidth=1.4, label="plant")
        axis.plot(k, y_model[:, j], color="tab:red", linestyle="--", linewidth=1.2, label="model (one step)")
        if y_free_run is not None:
            axis.plot(k, np.asarray(y_free_run)[:, j], color="tab:green", linestyle=":", linewidth=1.2,
                      label="model (free run)")  # fmt: skip
        axis.plot(k, y_plant[:, j] - y_model[:, j], color="tab:blue", linewidth=0.9, label="error")
        axis.set_ylabel(name)
        axis.grid(alpha=0.3)
    axes[0].set_title(title, fontsize=10)
    axes[0].legend(loc="upper right", fontsize=8, ncol=4)
    axes[-1].set_xlabel("discrete time k (test phase)")
    return save(figure, path)
