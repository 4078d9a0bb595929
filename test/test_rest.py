"""Long rest in a training record (a robot idling before it moves) is left out of ``fit``'s blocks."""

from __future__ import annotations

import numpy as np

from lenn_ros.fit.data import Data
from lenn_ros.fit.procedure import fit
from lenn_ros.fit.report import format_report
from lenn_ros.fit.rest import REST_HEAD, REST_TAIL, SMOOTHING, rest_stretches, without_rest


def cubic(u: np.ndarray) -> np.ndarray:
    """y(k) = 1.5 y(k-1) - 0.7 y(k-2) + 0.35 u(k-1) - 0.4 y(k-1)^3 (test_fit's plant), from rest at 0."""
    y = np.zeros(len(u))
    for k in range(2, len(u)):
        y[k] = 1.5 * y[k - 1] - 0.7 * y[k - 2] + 0.35 * u[k - 1] - 0.4 * y[k - 1] ** 3
    return y


def idle_then_moving(seed: int, idle: int = 3000, moving: int = 600) -> tuple[np.ndarray, np.ndarray]:
    """A log that rests (input held, output settled, sensor noise) for ``idle`` samples, then moves; the last 750
    samples are the test part."""
    rng = np.random.default_rng(seed)
    moves = np.convolve(rng.uniform(-1, 1, moving + 750), np.ones(3) / 3, "same") + 0.3
    u = np.concatenate([np.full(idle, 0.3), moves])
    return u, cubic(u) + 0.002 * rng.standard_normal(len(u))


def near(found: list[tuple[int, int]], expected: list[tuple[int, int]]) -> bool:
    """The stretches found are those expected, each end within the smoothing's half-width (averaging mixes the
    rows on either side of an end)."""
    return len(found) == len(expected) and all(
        abs(a - c) <= SMOOTHING // 2 and abs(b - d) <= SMOOTHING // 2
        for (a, b), (c, d) in zip(found, expected, strict=True)
    )


def test_rest_is_a_stretch_within_the_band_of_every_signal_and_never_crosses_a_break() -> None:
    """Every signal, averaged over SMOOTHING samples, within 1 % of its range: noise at rest does not end it."""
    rng = np.random.default_rng(0)
    moving = rng.uniform(-1, 1, (400, 2))
    resting = np.array([0.2, -0.4]) + 0.006 * rng.standard_normal((1000, 2))  # 3 sigma: 0.9 % of the range (2)
    values = np.vstack([moving, resting, moving, resting[:200]])
    assert near(rest_stretches(values, len(values), [], 500), [(400, 1400)])
    assert rest_stretches(values, len(values), [], 1001) == []  # shorter than asked
    assert near(rest_stretches(values, 1000, [], 500), [(400, 1000)])  # rows before the stop only
    assert near(rest_stretches(values, len(values), [900], 400), [(400, 900), (900, 1400)])  # cut at the break
    held = np.column_stack([values, np.full(len(values), 0.3)])  # a channel held over the whole record
    assert near(rest_stretches(held, len(held), [], 500), [(400, 1400)])  # its averages' rounding breaks nothing
    values[1100:1102, 1] += 0.3  # one signal leaves the band: the rest ends before it, and starts again after
    assert near(rest_stretches(values, len(values), [], 250), [(400, 1100), (1102, 1400)])


def test_fit_leaves_a_long_rest_out_and_simulates_a_plant_that_idled_before_it_moved() -> None:
    """Before, the blocks of the rest judged the candidates and the one block that moved was simulated by weights
    fitted to rest alone: this seed simulated its test part at -4.2 dB (seeds 0-3: -45.2, -4.2, -6.5, -15.2).
    Left out, the rest keeps its first REST_HEAD and last REST_TAIL samples: -45.2 dB (all four seeds -45.2 to
    -45.4), as the same motion logged without the rest."""
    u, y = idle_then_moving(1)
    report = fit(Data(u, y, "idle log"), 3601)
    rest = report.left_out["rest"]
    ((first, last),) = rest["stretches"]
    assert abs(last - 3000) <= SMOOTHING // 2 and rest["samples_left_out"] == last - first + 1 - (REST_HEAD + REST_TAIL)
    assert report.test_from == 3601 and report.train_samples == 3600 and report.samples == 750
    assert report.nmse_free_run_db < -42.0
    text = format_report(report)
    assert "note: the plant rests (every signal within 1% of its training range) in 1 stretch" in text
    assert "free run (from the measured outputs before sample 3601)" in text  # the user's numbering
    moved = fit(Data(u[3000:], y[3000:], "moving only"), 601)
    assert abs(report.nmse_free_run_db - moved.nmse_free_run_db) < 2.0


def test_rest_as_long_as_a_held_command_is_the_plants_own_and_stays() -> None:
    """A command held for a few hundred samples (a joint stuck between moves) is not cut: only rest longer than
    half a block of the selection, and never the test part."""
    u, y = idle_then_moving(2, idle=340, moving=3260)  # blocks of 720: half a block is 360
    data = Data(u, y, "short rest")
    kept, test_from, said = without_rest(data, 3601)
    assert kept is data and test_from == 3601 and said == {}
    u, y = idle_then_moving(2, idle=400, moving=3200)
    assert abs(without_rest(Data(u, y, "longer rest"), 3601)[2]["stretches"][0][1] - 400) <= SMOOTHING // 2
    u, y = idle_then_moving(2, idle=0, moving=3000)
    u[3100:], y[3100:] = u[3099], y[3099]  # a long rest in the test part only
    assert without_rest(Data(u, y, "x"), 3001)[2] == {}
