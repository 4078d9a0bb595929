"""Figures in the style of the paper's Figs. 4-7: plant, model and error over k.

Figures are ``matplotlib.figure.Figure`` objects drawn by the Agg canvas directly: no
pyplot, no ``matplotlib.use``. A program that imports lenn_ros keeps its own backend
(an interactive session, a GUI), and nothing is left in pyplot's figure registry.

The error has an axis of its own, below the outputs' and sharing k: drawn on the outputs'
axis, an error near 0 under outputs near 97 squeezes both into flat lines. The legend
sits above the axes, never over the data.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from lenn_ros.errors import require_extra

require_extra("matplotlib", "plot", "plots")

from matplotlib.axes import Axes  # noqa: E402
from matplotlib.backends.backend_agg import FigureCanvasAgg  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402
from matplotlib.patches import Rectangle  # noqa: E402

#: Half-width of a 95 % band: one number for every sample, one per sample (e.g. 1.96 * y_hat_std), or none.
Band = float | np.ndarray | None
#: Several outputs' bands: one entry per output (each a :data:`Band`), or an array of samples x outputs.
Bands = Sequence[Band] | np.ndarray | None

PLANT: dict[str, Any] = {"color": "black", "linewidth": 1.4}
ONE_STEP, FREE_RUN = "tab:red", "tab:green"
X_LABEL = "discrete time k (test phase)"


def new_figure(width: float = 8.0, height: float = 3.6, dpi: int = 110) -> tuple[Figure, Axes]:
    """One figure with one axis, bound to its own Agg canvas."""
    figure = Figure(figsize=(width, height), dpi=dpi)
    FigureCanvasAgg(figure)
    return figure, figure.add_subplot()


def save(figure: Figure, path: str | Path) -> Path:
    """Write the figure as PNG (creating the directory); a figure without a layout engine is laid out tight."""
    if figure.get_layout_engine() is None:
        figure.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path)
    return path


def identification_figure(
    y_plant: np.ndarray,
    y_model: np.ndarray,
    title: str,
    y_free_run: np.ndarray | None = None,
    free_run_band: Band = None,
    one_step_band: Band = None,
) -> Figure:
    """Plant and model output (one step, and free run if given) on one axis, their errors on a second below it.

    ``free_run_band``, ``one_step_band``: half-widths of the nominal 95 % bands (``fit``'s
    ``intervals``; a number, or one per sample such as ``1.96 * y_hat_std``), shaded around the
    model's output and around zero under its error.
    """
    y_plant = np.asarray(y_plant, dtype=float).ravel()
    figure, (output, error) = _panels(1, height=4.8)
    free = None if y_free_run is None else np.asarray(y_free_run, dtype=float).ravel()
    y_model = np.asarray(y_model, dtype=float).ravel()
    columns = _draw(output, error, y_plant, y_model, free, free_run_band, one_step_band)
    output.set_ylabel("plant / model output")
    error.set_ylabel("error (plant - model)")
    _finish(figure, [output, error], title, columns)
    return figure


def plot_identification(
    path: str | Path,
    y_plant: np.ndarray,
    y_model: np.ndarray,
    title: str,
    y_free_run: np.ndarray | None = None,
    free_run_band: Band = None,
    one_step_band: Band = None,
) -> Path:
    """Write a PNG of plant and model output over their errors (one step, free run), as the paper's figures but
    the error on an axis of its own: :func:`identification_figure`.

    ``free_run_band``: half-width of the free run's nominal 95 % band (``fit``'s), drawn around it;
    ``one_step_band``: the one-step prediction's, drawn around it.
    """
    return save(identification_figure(y_plant, y_model, title, y_free_run, free_run_band, one_step_band), path)


def channels_figure(
    names: list[str] | tuple[str, ...],
    y_plant: np.ndarray,
    y_model: np.ndarray,
    title: str,
    y_free_run: np.ndarray | None = None,
    free_run_band: Bands = None,
    one_step_band: Bands = None,
) -> Figure:
    """:func:`identification_figure` for several output channels (columns of the arrays): per channel an output
    panel and an error panel below it, all sharing k. Bands: one per channel (:data:`Bands`)."""
    y_plant = np.asarray(y_plant, dtype=float).reshape(len(y_plant), -1)
    y_model = np.asarray(y_model, dtype=float).reshape(y_plant.shape)
    free = None if y_free_run is None else np.asarray(y_free_run, dtype=float).reshape(y_plant.shape)
    free_bands, one_bands = _per_channel(free_run_band, len(names)), _per_channel(one_step_band, len(names))
    figure, axes = _panels(len(names), height=3.2 * len(names) + 1.0)
    drawn = []
    for j, name in enumerate(names):
        output, error = axes[2 * j], axes[2 * j + 1]
        column = None if free is None else free[:, j]
        drawn.append(_draw(output, error, y_plant[:, j], y_model[:, j], column, free_bands[j], one_bands[j]))
        output.set_ylabel(name)
        error.set_ylabel(f"{name} error")
    # the legend's entries: of the first channel with the most bands (one without a band would leave them unnamed)
    columns = max(drawn, key=lambda columns: sum("band" in label for column in columns for _, label in column))
    _finish(figure, axes, title, columns)
    return figure


def plot_channels(
    path: str | Path,
    names: list[str] | tuple[str, ...],
    y_plant: np.ndarray,
    y_model: np.ndarray,
    title: str,
    y_free_run: np.ndarray | None = None,
    free_run_band: Bands = None,
    one_step_band: Bands = None,
) -> Path:
    """:func:`plot_identification` for several output channels: :func:`channels_figure`, written as a PNG."""
    figure = channels_figure(names, y_plant, y_model, title, y_free_run, free_run_band, one_step_band)
    return save(figure, path)


def _panels(channels: int, height: float) -> tuple[Figure, list[Axes]]:
    """Per channel an output axis over an error axis (half as high), all sharing k, laid out by constraints."""
    figure = Figure(figsize=(8.0, height), dpi=110, layout="constrained")
    FigureCanvasAgg(figure)
    axes = figure.subplots(2 * channels, 1, sharex=True, gridspec_kw={"height_ratios": [2, 1] * channels})
    return figure, list(np.ravel(axes))


def _draw(
    output: Axes,
    error: Axes,
    plant: np.ndarray,
    model: np.ndarray,
    free: np.ndarray | None,
    free_band: Band,
    one_band: Band,
) -> list[list[tuple[Any, str]]]:
    """One channel: plant and model on ``output`` with the bands around the model, errors and bands on ``error``.

    Returns the legend's columns: the plant; the one-step model (with its band) over its error; the free run's."""
    k = np.arange(len(plant))
    columns = [[(output.plot(k, plant, **PLANT)[0], "plant")]]
    error.axhline(0.0, color="black", linewidth=0.6)
    for series, color, name, style, band in (
        (model, ONE_STEP, "one step", "--", one_band),
        (free, FREE_RUN, "free run", ":", free_band),
    ):
        if series is None:
            continue
        line = output.plot(k, series, color=color, linestyle=style, linewidth=1.3)[0]
        half = _half_width(band, len(k))
        if half is None:
            entry = (line, f"model ({name})")
        else:
            shade = output.fill_between(k, series - half, series + half, color=color, alpha=0.15, linewidth=0)
            error.fill_between(k, -half, half, color=color, alpha=0.12, linewidth=0)
            entry = ((shade, line), f"model ({name}), 95 % band")
        wrong = error.plot(k, plant - series, color=color, linewidth=0.8)[0]
        columns.append([entry, (wrong, f"error ({name})")])
    for axis in (output, error):
        axis.grid(alpha=0.3)
    return columns


def _finish(figure: Figure, axes: list[Axes], title: str, columns: list[list[tuple[Any, str]]]) -> None:
    """Title over the figure, the legend (a column per series, the first channel's) above the top axis, k below
    the last axis."""
    figure.suptitle(title, fontsize=10)
    rows = max(len(column) for column in columns)
    blank = Rectangle((0, 0), 0, 0, visible=False)
    cells = [cell for column in columns for cell in column + [(blank, "")] * (rows - len(column))]
    handles, labels = zip(*cells, strict=True)
    axes[0].legend(handles, labels, loc="lower center", bbox_to_anchor=(0.5, 1.0), ncol=len(columns), fontsize=8,
                   frameon=False)  # fmt: skip
    axes[-1].set_xlabel(X_LABEL)


def _half_width(band: Band, samples: int) -> np.ndarray | None:
    """A band's half-width per sample, or None where there is none to draw (none given, zero or not finite)."""
    if band is None:
        return None
    half = np.broadcast_to(np.abs(np.asarray(band, dtype=float)), (samples,))
    return half if np.any(np.isfinite(half) & (half > 0)) else None


def _per_channel(bands: Bands, channels: int) -> list[Band]:
    """Several channels' bands as one entry each (a samples x channels array: its columns)."""
    if bands is None:
        return [None] * channels
    entries = list(bands.T) if isinstance(bands, np.ndarray) and bands.ndim == 2 else list(bands)
    if len(entries) != channels:
        raise ValueError(f"{len(entries)} bands for {channels} channels")
    return entries
