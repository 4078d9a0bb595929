"""The ``--plot`` figures (:mod:`lenn_ros.plotting`): the error on an axis of its own, bands, the legend off the data.

Drawn on the figures' own Agg canvases (no pyplot). The user's case: the heat exchanger's
output near 97 with errors near 0.1 drew the error on the output's axis, so plant and
model were flat lines at the top, and the legend sat on the data.
"""

from __future__ import annotations

import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

pytest.importorskip("matplotlib")

from matplotlib.axes import Axes
from matplotlib.collections import PolyCollection
from matplotlib.figure import Figure

from lenn_ros import evaluate, plotting
from lenn_ros.fit import report

N = 400


def exchanger_like(seed: int = 0, level: float = 97.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Plant near ``level`` (swinging by about 2), one-step model and free run off by about 0.1."""
    rng = np.random.default_rng(seed)
    k = np.arange(N)
    plant = level + 2.0 * np.sin(k / 25.0) + 0.5 * np.sin(k / 7.0)
    model = plant - 0.1 * rng.standard_normal(N)
    model[:3] = np.nan  # seeded: no prediction
    free = plant - 0.05 * np.cos(k / 30.0 + seed)
    return plant, model, free


def axis_with(figure: Figure, y: np.ndarray) -> Axes:
    """The one axis holding a line of exactly ``y``."""
    found = [
        axis
        for axis in figure.get_axes()
        for line in axis.get_lines()
        if len(line.get_ydata()) == len(y) and np.allclose(line.get_ydata(), y, equal_nan=True)
    ]
    assert len(found) == 1, f"{len(found)} axes hold the series"
    return found[0]


def assert_error_on_its_own_axis(figure: Figure, plant: np.ndarray, model: np.ndarray, free: np.ndarray) -> None:
    output = axis_with(figure, plant)
    assert axis_with(figure, model) is output and axis_with(figure, free) is output
    error = axis_with(figure, plant - model)
    assert error is not output and axis_with(figure, plant - free) is error
    assert error.get_shared_x_axes().joined(error, output)
    low, high = output.get_ylim()
    assert low < np.min(plant) and np.max(plant) < high and not low <= 0.0 <= high  # the output's range, not 0
    assert high - low < 3 * (np.max(plant) - np.min(plant))
    wrong = np.concatenate([plant - model, plant - free])
    wrong = wrong[np.isfinite(wrong)]
    low, high = error.get_ylim()
    assert low <= wrong.min() and wrong.max() <= high
    assert high - low < 3 * (wrong.max() - wrong.min())  # fitted to the error, not to outputs near 97


def polygons(axis: Axes) -> list[np.ndarray]:
    """The vertices of each shaded region (fill_between) on the axis."""
    return [
        np.concatenate([path.vertices for path in c.get_paths()])
        for c in axis.collections
        if isinstance(c, PolyCollection) and c.get_paths()
    ]


def shades(axis: Axes, k: np.ndarray, low: np.ndarray, high: np.ndarray) -> bool:
    """Whether one shaded region on the axis spans exactly [low, high] at each k."""
    for vertices in polygons(axis):
        found = True
        for x, lo, hi in zip(k, low, high, strict=True):
            at = vertices[np.isclose(vertices[:, 0], x), 1]
            if not (len(at) and np.isclose(at.min(), lo) and np.isclose(at.max(), hi)):
                found = False
                break
        if found:
            return True
    return False


def assert_legend_off_the_data(figure: Figure) -> None:
    figure.canvas.draw()
    renderer = figure.canvas.get_renderer()
    legends = [axis.get_legend() for axis in figure.get_axes() if axis.get_legend()] + figure.legends
    assert len(legends) == 1
    box = legends[0].get_window_extent(renderer)
    whole = figure.bbox
    assert whole.x0 <= box.x0 and box.x1 <= whole.x1 and whole.y0 <= box.y0 and box.y1 <= whole.y1  # not cut off
    for axis in figure.get_axes():
        assert not box.overlaps(axis.get_window_extent(renderer)), "the legend lies on an axis"
    title = figure._suptitle.get_window_extent(renderer)
    assert not box.overlaps(title)


def test_the_error_has_an_axis_of_its_own_fitted_to_it() -> None:
    plant, model, free = exchanger_like()
    figure = plotting.identification_figure(plant, model, "exchanger", free)
    assert isinstance(figure, Figure) and len(figure.get_axes()) == 2
    assert_error_on_its_own_axis(figure, plant, model, free)
    assert not any(polygons(axis) for axis in figure.get_axes())  # no band given, none drawn
    assert_legend_off_the_data(figure)


def test_without_a_free_run_the_one_step_error_alone() -> None:
    plant, model, _ = exchanger_like(1)
    figure = plotting.identification_figure(plant, model, "no free run")
    output, error = axis_with(figure, plant), axis_with(figure, plant - model)
    assert output is not error and len(error.get_lines()) == 2  # the error and the zero line
    assert output.get_ylim()[0] > 0.0
    assert_legend_off_the_data(figure)


def test_bands_are_shaded_around_the_model_and_around_zero_under_the_error() -> None:
    plant, model, free = exchanger_like(2)
    k = np.arange(N)
    one = 0.2 + 0.05 * np.sin(k / 10.0)  # per sample, as 1.96 * y_hat_std would be
    figure = plotting.identification_figure(plant, model, "bands", free, free_run_band=0.3, one_step_band=one)
    output, error = axis_with(figure, plant), axis_with(figure, plant - model)
    seen = np.isfinite(model)
    assert shades(output, k[seen], (model - one)[seen], (model + one)[seen])
    assert shades(output, k, free - 0.3, free + 0.3)
    assert shades(error, k, -one, one)
    assert shades(error, k, np.full(N, -0.3), np.full(N, 0.3))
    assert not shades(output, k, free - 0.2, free + 0.2)  # the check can fail
    labels = [text.get_text() for text in figure.get_axes()[0].get_legend().get_texts()]
    assert "model (one step), 95 % band" in labels and "model (free run), 95 % band" in labels
    assert_legend_off_the_data(figure)


@pytest.mark.parametrize("band", [None, 0.0, float("nan")])
def test_no_band_is_drawn_for_none_zero_or_nan(band: float | None) -> None:
    plant, model, free = exchanger_like(3)
    figure = plotting.identification_figure(plant, model, "t", free, free_run_band=band, one_step_band=band)
    assert not any(polygons(axis) for axis in figure.get_axes())


def test_several_channels_each_an_output_panel_over_an_error_panel() -> None:
    columns = [exchanger_like(4, 97.0), exchanger_like(5, -30.0), exchanger_like(6, 1500.0)]
    plant, model, free = (np.column_stack([c[i] for c in columns]) for i in range(3))
    figure = plotting.channels_figure(["th", "tc", "p"], plant, model, "three", free, free_run_band=[0.3, None, 0.2])
    axes = figure.get_axes()
    assert len(axes) == 6
    k = np.arange(N)
    for j in range(3):
        assert_error_on_its_own_axis(figure, plant[:, j], model[:, j], free[:, j])
        assert axes.index(axis_with(figure, plant[:, j])) == 2 * j
        assert axes.index(axis_with(figure, plant[:, j] - model[:, j])) == 2 * j + 1
    assert shades(axes[0], k, free[:, 0] - 0.3, free[:, 0] + 0.3) and not polygons(axes[2])
    assert shades(axes[5], k, np.full(N, -0.2), np.full(N, 0.2))
    assert_legend_off_the_data(figure)
    labels = [text.get_text() for text in axes[0].get_legend().get_texts()]
    assert "model (free run), 95 % band" in labels
    free_run_band = [None, None, 0.2]  # the first channel has none: the legend still names the band
    figure = plotting.channels_figure(["th", "tc", "p"], plant, model, "three", free, free_run_band=free_run_band)
    labels = [text.get_text() for text in figure.get_axes()[0].get_legend().get_texts()]
    assert "model (free run), 95 % band" in labels
    with pytest.raises(ValueError, match="2 bands for 3 channels"):
        plotting.channels_figure(["a", "b", "c"], plant, model, "t", free, free_run_band=[0.1, 0.2])


def test_the_writers_still_return_the_png_path_and_leave_pyplot_alone(tmp_path: Path) -> None:
    plant, model, free = exchanger_like(7)
    one = plotting.plot_identification(tmp_path / "a" / "one.png", plant, model, "one", free, 0.3)
    several = plotting.plot_channels(tmp_path / "two.png", ["a", "b"], np.c_[plant, plant], np.c_[model, model], "two")
    for path in (one, several):
        assert isinstance(path, Path) and path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "matplotlib.pyplot" not in sys.modules or not sys.modules["matplotlib.pyplot"].get_fignums()


@pytest.fixture
def drawn(monkeypatch: pytest.MonkeyPatch) -> list[Figure]:
    """The figures the callers hand to :func:`lenn_ros.plotting.save` (written nowhere)."""
    figures = []

    def keep(figure: Figure, path: str | Path) -> Path:
        figures.append(figure)
        return Path(path)

    monkeypatch.setattr(plotting, "save", keep)
    return figures


def output_report(seed: int, free_band: float, one_band: float) -> SimpleNamespace:
    plant, model, free = exchanger_like(seed)
    bands = {"free_run": {"half_width": free_band}, "one_step": {"half_width": one_band}}
    return SimpleNamespace(y_test=plant, y_hat_test=model, y_free_test=free, intervals=bands)


def test_fit_plots_each_outputs_one_step_and_free_run_bands(drawn: list[Figure]) -> None:
    alone = output_report(8, 0.3, 0.25)
    result = SimpleNamespace(alone=True, per_output=[alone], rmse_free_run=0.05, y_test=alone.y_test,
                             y_hat_test=alone.y_hat_test, y_free_test=alone.y_free_test)  # fmt: skip
    report.plot("fit.png", result, "exchanger")
    output, error = axis_with(drawn[0], alone.y_test), axis_with(drawn[0], alone.y_test - alone.y_hat_test)
    k = np.arange(N)
    assert shades(output, k, alone.y_free_test - 0.3, alone.y_free_test + 0.3)
    assert shades(error, k, np.full(N, -0.25), np.full(N, 0.25))
    parts = [output_report(9, 0.3, 0.25), output_report(10, 0.5, 0.4)]
    series = {key: np.column_stack([getattr(p, key) for p in parts]) for key in ("y_test", "y_hat_test", "y_free_test")}
    report.plot("fit.png", SimpleNamespace(alone=False, per_output=parts, outputs=["a", "b"], **series), "two")
    axes = drawn[1].get_axes()
    assert shades(axes[3], k, np.full(N, -0.4), np.full(N, 0.4)) and shades(
        axes[3], k, np.full(N, -0.5), np.full(N, 0.5)
    )
    assert not shades(axes[1], k, np.full(N, -0.4), np.full(N, 0.4))


def test_evaluate_plots_the_fits_free_run_band_by_output_name(drawn: list[Figure], capsys) -> None:
    parts = {name: output_report(seed, 0.0, 0.0) for name, seed in (("th", 11), ("tc", 12))}
    evaluations = {
        name: SimpleNamespace(y_test=p.y_test, y_hat_test=p.y_hat_test, y_free_test=p.y_free_test, nmse_db=-20.0)
        for name, p in parts.items()
    }
    intervals = {"free_run": {"tc": {"half_width": 0.7}}}
    result = SimpleNamespace(single=False, evaluations=evaluations, intervals=intervals)
    evaluate._plot(SimpleNamespace(plot="ev.png"), result, "bag")
    axes, k = drawn[0].get_axes(), np.arange(N)
    assert not polygons(axes[0]) and not polygons(axes[1])
    assert shades(axes[3], k, np.full(N, -0.7), np.full(N, 0.7))
    assert "wrote ev.png" in capsys.readouterr().out
