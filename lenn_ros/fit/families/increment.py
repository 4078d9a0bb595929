"""The ``increment`` family: the model predicts the change y(k+1) - y(k), y(k) passed through.

From the increments of the output, the inputs and, from degree 2, friction-like functions
of the velocity: tanh (Coulomb friction), |v| and v|v| (drag), and stiction: tanh(a v + b d),
friction that opposes the motion when moving and the net drive d at rest (where a tanh of
the velocity is 0 and the model would creep); degree 3 adds polynomials of the position
(gravity, a spring) and of the input. A plant that integrates (a motor position driven by a
torque) keeps its integrator exactly instead of a least-squares estimate of it that drifts.
For lag spans beyond 10 samples (a record sampled far faster than its dynamics, such as a
1 kHz robot) the increments are taken over spans 1, 2, 4, ... and the input averaged over
them (multi-scale, :func:`multi_scale`), so a long memory costs a few terms, not one per
sample. Its linear part is also the ``stick`` family's (:func:`linear_increments`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from lenn_ros.fit.families.base import RECENT, Builder, Dictionary, view_columns

if TYPE_CHECKING:
    from lenn_ros.fit.families import Spec

#: lags (equal for y and u) tried
INCREMENT_LAGS = (2, 3, 4, 6, 10)
#: long lag spans (multi-scale increments) for records sampled far faster than their dynamics
LONG_SPANS = (17, 33, 65)
#: sharpness of the tanh velocity terms, in units of the velocity's standard deviation
VELOCITY_SHARPNESS = (3.0, 10.0, 30.0)


def multi_scale(lags: int) -> bool:
    """Whether an increment-form model of ``lags`` takes its increments over spans 1, 2, 4, ... (beyond
    INCREMENT_LAGS: a record sampled far faster than its dynamics)."""
    return lags > max(INCREMENT_LAGS)


def time_scale(spec: Spec) -> str:
    """What the report says of an increment-form model's lag spans (the ``stick`` family's too)."""
    if multi_scale(spec.lags):
        return (
            f"multi-scale increments over {spec.lags - 1} samples (spans 1, 2, 4, ...): the record is sampled "
            "far faster than its dynamics; the model runs at the recorded rate"
        )
    return "increment form: y(k+1) = y(k) + f(increments, inputs), the integrator kept exactly"


def dictionary(spec: Spec, x: np.ndarray) -> Dictionary:
    """y(k+1) - y(k) from output increments, inputs, and (degree >= 2) velocity and position nonlinearities."""
    lags = spec.lags
    built, read, spans = linear_increments(spec, x)
    if spec.degree >= 2 and lags >= 2:
        velocity_spans = sorted({1, spans[len(spans) // 2], spans[-1]})
        for span in velocity_spans:
            _velocity_terms(built, x, span)
            if 2 * span < lags:
                _stiction_terms(built, x, read, span)
        for start in read:
            built.add(built.power(start, 2))
    if spec.degree >= 3:
        for degree in (1, 2, 3):
            built.add(built.power(0, degree))
        for start in read:
            built.add(built.power(start, 3))
    return built.build(increment=True)


def linear_increments(spec: Spec, x: np.ndarray) -> tuple[Builder, list[int], list[int]]:
    """The increment form's linear part: the bias, the output's increments and every column read (multi-scale
    beyond INCREMENT_LAGS). Returns (the terms so far, where each column read starts, the increments' spans)."""
    lags = spec.lags
    read = [c * lags for c in range(1, view_columns(spec, x))]  # where each column read besides the output starts
    built = Builder(x.shape[1])
    built.add()  # the bias: a constant force (gravity at rest, an offset)
    doubling = multi_scale(lags)
    spans = [s for s in (1, 2, 4, 8, 16, 32, 64, 128) if s < lags] if doubling else list(range(1, lags))
    for s in spans:
        # multi-scale: y(k) - y(k-s); else consecutive increments y(k-j+1) - y(k-j)
        first = 0 if doubling else s - 1
        built.add(None, "lin", built.unit(first) - built.unit(s))
    for start in read:
        _input_terms(built, start, lags, doubling)
    return built, read, spans


def _velocity_terms(built: Builder, x: np.ndarray, span: int) -> None:
    """tanh at three sharpnesses, |v| and v|v| of v = (x_1 - x_{1+span}) / span, scaled to unit spread."""
    difference = (x[:, 0] - x[:, span]) / span
    spread = float(np.std(difference)) or 1.0
    direction = (built.unit(0) - built.unit(span)) / span / spread
    for sharpness in VELOCITY_SHARPNESS:
        built.add(None, "tanh", direction * sharpness)
    built.add(None, "abs", direction)
    built.add(None, "sqabs", direction)


#: how sharply the stiction terms saturate in the net drive, in units of its spread
DRIVE_SHARPNESS = (1.0, 3.0, 10.0)


def _stiction_terms(built: Builder, x: np.ndarray, read: list[int], span: int) -> None:
    """tanh(a v + b d): friction that opposes the motion v when moving and the net drive d at rest.

    At rest a joint's friction cancels the net drive up to the stiction, which a tanh of
    the velocity alone cannot (it is 0 at rest: the model creeps where the joint sticks).
    The net drive's direction, d = c0 + c . (the inputs' newest samples, the output), comes
    from the training record's own lags: the acceleration over ``span`` samples,
    (y1 - y_{1+s}) - (y_{1+s} - y_{1+2s}), regressed on what drove it (each input's sample
    s lags back, y_{1+s}) and the velocity before it. v is the velocity over the span.
    """
    acceleration = x[:, 0] - 2.0 * x[:, span] + x[:, 2 * span]
    before = x[:, span] - x[:, 2 * span]
    drivers = np.column_stack([np.ones(len(x)), *(x[:, start + span] for start in read), x[:, span], before])
    coefficients = np.linalg.lstsq(drivers, acceleration, rcond=None)[0]
    w = np.zeros(built.n)
    for start, c in zip(read, coefficients[1:-2], strict=True):
        w[start] = c
    w[0] = coefficients[-2]
    drive_spread = float(np.std(x @ w + coefficients[0])) or 1.0
    velocity_spread = float(np.std(x[:, 0] - x[:, span])) or 1.0
    direction = (built.unit(0) - built.unit(span)) / velocity_spread
    for sharpness in VELOCITY_SHARPNESS:
        for drive_sharpness in DRIVE_SHARPNESS:
            built.add(None, "tanh", direction * sharpness + w * drive_sharpness / drive_spread,
                      coefficients[0] * drive_sharpness / drive_spread)  # fmt: skip


def _input_terms(built: Builder, start: int, lags: int, multi_scale: bool) -> None:
    """The linear terms of one column read (its lags at ``start``..): every lag, or multi-scale averages
    over spans 1, 2, 4, ... and the RECENT newest lags after the first."""
    if not multi_scale:
        for j in range(lags):
            built.add(built.power(start + j, 1))
        return
    for s in [1] + [s for s in (2, 4, 8, 16, 32, 64, 128) if s <= lags]:
        w = np.zeros(built.n)
        w[start : start + s] = 1.0 / s
        built.add(None, "lin", w)
    for j in range(1, min(lags, RECENT)):
        built.add(built.power(start + j, 1))
