"""A fitted model to call from Python: ``lenn_ros.load_model(DIR)``.

What ``lenn-ros fit -o DIR`` (or ``weights_out`` with its params file) leaves is a
model that a controller, an MPC or a test bench written in Python can run without ROS:

    model = lenn_ros.load_model("model")
    y = model.simulate(u, y_initial=y_measured[-model.history:], u_initial=u_measured[-model.history:])
    y_next = model.predict(u_measured, y_measured, steps=20, u_future=u_plan)

Everything runs through the one free run the identifier has
(:meth:`~lenn_ros.core.structure.Identifier.free_run`, compiled), so the figures are
the ones ``fit`` reported, the twin node publishes and ``evaluate`` scores: there is no
second simulator to disagree with them. The model is built from the params file by
:func:`lenn_ros.service.building.identifier_from_params`, the same path ``evaluate --params``
takes, so it is the model the node would start from.

Indexing: a run of inputs ``u(0..N-1)`` after a history of ``history`` samples gives
the outputs ``y(0..N-1)``, where ``y(k)`` depends on the inputs up to ``u(k-1)`` (the
models predict y(k) from y(k-1..) and u(k-1..): a plant's output never depends on the
command of the same instant), so ``y(0)`` comes from the history alone and ``u(N-1)``
only matters to a following call. This is exactly ``fit``'s free run over its test
part, seeded with the measured samples before it.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lenn_ros.core.mimo import MimoIdentifier
from lenn_ros.core.structure import Identifier
from lenn_ros.fit.data import REPORT_FILE
from lenn_ros.service.scoring import fit_free_run_bands, fit_free_run_widths


class ModelError(ValueError):
    """A model directory or a call that cannot work, with the reason in one line."""


@dataclass
class Model:
    """A frozen identified model: free run, multi-step prediction, and its uncertainty.

    ``identifier``: the model as the node runs it (SISO :class:`Identifier` or
    :class:`MimoIdentifier`); ``values``: the node parameters it was described by;
    ``report``: ``fit``'s report when the directory has one (``{}`` otherwise), which
    carries the residual statistics the intervals and the twin's noise come from.
    """

    identifier: Identifier | MimoIdentifier
    values: dict[str, Any]
    report: dict[str, Any] = field(default_factory=dict)
    source: str = ""

    @property
    def n_u(self) -> int:
        return self.identifier.n_u

    @property
    def n_y(self) -> int:
        return self.identifier.n_y

    @property
    def history(self) -> int:
        """Samples of (u, y) a run needs before it: the longest lag of any regressor (a MIMO structure's
        ``warm_up`` is every output's common one)."""
        return self.identifier.structure.warm_up

    @property
    def sample_period(self) -> float:
        """Seconds between samples as recorded (0: the model was fitted without one)."""
        return float(self.values.get("sample_period", 0.0) or 0.0)

    @property
    def operating_point(self) -> tuple[np.ndarray, np.ndarray]:
        """(u, y) the scaling is centred on (the training mean): the history at rest by default."""
        s = self.identifier.structure
        u0, y0 = (np.asarray(offset, dtype=np.float64).reshape(-1) for offset in (s.u_offset, s.y_offset))
        return (u0 if u0.size else np.zeros(self.n_u)), (y0 if y0.size else np.zeros(self.n_y))

    def intervals(self) -> dict[str, Any]:
        """``fit``'s nominal 95 % bands as its report gives them (``one_step``, ``free_run``; for the half-widths
        along a run of this model, :meth:`free_run_band`)."""
        return dict(self.report.get("intervals", {}))

    def free_run_band(self, y_free: np.ndarray) -> np.ndarray:
        """Half-widths of ``fit``'s nominal 95 % free-run band at each sample of a run :meth:`simulate` or
        :meth:`predict` returned (shaped like it; NaN after a divergence): narrow at the run's first steps, growing
        with the steps as the held-out runs' errors grew. Read it as ``y_free +- band``.

        The rule is evaluate's (:func:`~lenn_ros.service.scoring.fit_free_run_widths`): by steps since the run's
        start, so a run restarted after a NaN starts narrow again; the median as one number would be too wide
        at first and too narrow late in a long run.
        """
        y_free = np.asarray(y_free, dtype=np.float64)
        columns = y_free.reshape(len(y_free), -1)
        bands = fit_free_run_bands(self.report)
        if columns.shape[1] != self.n_y or len(bands) != self.n_y:
            raise ModelError(f"free_run_band takes a run of {self.n_y} output(s), not {columns.shape[1]}")
        widths = []
        for j, band in enumerate(bands):
            found = fit_free_run_widths(band, columns[:, j])
            if found is None:
                raise ModelError(f"{self.source or 'the model'} has no fit report (fit.json) with a free-run band")
            widths.append(found)
        return np.column_stack(widths).reshape(y_free.shape)

    # -- running the model -------------------------------------------------------------------
    def simulate(
        self,
        u: np.ndarray,
        y_initial: np.ndarray | None = None,
        u_initial: np.ndarray | None = None,
    ) -> np.ndarray:
        """Free run over the inputs ``u`` from a history; returns y(0..N-1), shaped like ``u``'s rows.

        ``y_initial`` / ``u_initial``: the last samples before the run, oldest first (at
        least :attr:`history` of them; more are cut). Left out, the history is the
        operating point at rest. ``u`` is (N,) for one input or (N, n_u); the result
        is (N,) for one output, (N, n_y) otherwise. NaN after a divergence (see
        ``last_free_run``).
        """
        u = self._inputs(u, "u")
        u_before, y_before = self._history(u_initial, y_initial)
        window = self.history
        u_all = np.concatenate([u_before, u])
        y_all = np.concatenate([y_before, np.full((len(u), y_before.shape[1]), np.nan)])
        # (one output: y_abs's history holds the signed outputs the run goes on from)
        return self._read(self.identifier.free_run(u_all, y_all, window, seeds_signed=True))

    @property
    def _reads_abs(self) -> bool:
        """One output read as its absolute value (``y_abs``): its runs go on from signed outputs (:meth:`_history`)."""
        return bool(getattr(self.identifier.structure, "y_abs", False))

    def _read(self, y: np.ndarray) -> np.ndarray:
        """The model's output as the sensor reads it: |y| where it :attr:`_reads_abs`."""
        return np.abs(y) if self._reads_abs else y

    def predict(self, u: np.ndarray, y: np.ndarray, steps: int, u_future: np.ndarray | None = None) -> np.ndarray:
        """The next ``steps`` outputs y(N..N+steps-1) after the measured ``u``, ``y`` (same length >= :attr:`history`).

        y(N) follows from the measurements; each later one needs the input before it:
        ``u_future`` holds u(N..N+steps-2) (more are cut), or, left out, the last input
        is held (the plant's response to a constant command).
        """
        if steps < 1:
            raise ModelError(f"steps must be at least 1, not {steps}")
        u = self._inputs(u, "u")
        y = self._outputs(y)
        if len(u) != len(y):
            raise ModelError(f"u has {len(u)} samples and y {len(y)}: give the same samples of both")
        if u_future is None:
            future = np.repeat(u[-1:], steps - 1, axis=0)
        else:
            future = self._inputs(u_future, "u_future")[: steps - 1]
            if len(future) < steps - 1:
                raise ModelError(f"u_future has {len(future)} inputs; {steps} steps need {steps - 1}")
        # the run's last input predicts nothing within the horizon: any value (the last one) fills it
        run = np.concatenate([future, (future if len(future) else u)[-1:]])
        return self.simulate(run, y_initial=y, u_initial=u)

    def stepper(self, y_initial: np.ndarray | None = None, u_initial: np.ndarray | None = None) -> Stepper:
        """A free run one sample at a time (a twin, a controller in the loop): see :class:`Stepper`."""
        u_before, y_before = self._history(u_initial, y_initial)
        return Stepper(self, u_before, y_before)

    # -- shapes ---------------------------------------------------------------------------------
    def _inputs(self, u: Any, name: str) -> np.ndarray:
        return _samples(u, self.n_u, name, "takes", "input")

    def _outputs(self, y: Any, name: str = "y") -> np.ndarray:
        return _samples(y, self.n_y, name, "gives", "output")

    def _history(self, u_initial: Any, y_initial: Any) -> tuple[np.ndarray, np.ndarray]:
        window = self.history
        u0, y0 = self.operating_point
        u_before = np.tile(u0, (window, 1)) if u_initial is None else self._inputs(u_initial, "u_initial")
        y_before = np.tile(y0, (window, 1)) if y_initial is None else self._outputs(y_initial, "y_initial")
        for name, a in (("u_initial", u_before), ("y_initial", y_before)):
            if len(a) < window:
                raise ModelError(f"{name} has {len(a)} samples; the model needs the last {window} before the run")
        if y_initial is not None and self._reads_abs:
            # |y| measured: signed as the node signs it, over all of the history given (the longer, the surer)
            n = min(len(u_before), len(y_before))
            y_before = y_before.copy()
            y_before[-n:, 0] = self.identifier.signed(u_before[-n:, 0], y_before[-n:, 0])
        return u_before[-window:], y_before[-window:]


def _samples(values: Any, channels: int, name: str, verb: str, kind: str) -> np.ndarray:
    """``values`` as (samples, channels) of finite numbers (one channel may come as a flat series), or why not."""
    a = np.asarray(values, dtype=np.float64)
    if a.ndim == 1 and channels == 1:
        a = a[:, None]
    if a.ndim != 2 or a.shape[1] != channels:
        raise ModelError(f"{name} has shape {np.shape(values)}; the model {verb} {channels} {kind}(s) per sample")
    if not np.all(np.isfinite(a)):
        raise ModelError(f"{name} holds {int(np.count_nonzero(~np.isfinite(a)))} NaN/inf values")
    return a


class Stepper:
    """The free run of a :class:`Model`, one sample at a time, as a plant is sampled.

    ``step(u_k)`` returns y(k), the output measured at the instant u(k) is applied
    (it depends on the inputs up to u(k-1)), then applies u(k): the order of the plant
    simulator, which publishes y_p(k) with u(k). Stepping through ``u`` gives
    :meth:`Model.simulate` of ``u``: each step is the same compiled free run over the last
    :attr:`Model.history` samples, so the two agree bit for bit (the twin node's output
    equals ``fit``'s free run). ``diverged`` is set when the output left the model's
    range; the stepper then returns NaN until :meth:`reset`.
    """

    def __init__(self, model: Model, u_before: np.ndarray, y_before: np.ndarray) -> None:
        self.model = model
        self._start = (u_before.copy(), y_before.copy())
        self.reset()

    def reset(self) -> None:
        """Back to the history the stepper was made with."""
        u_before, y_before = self._start
        # one row more than the history: the slot the free run writes y(k) into
        self._u = np.concatenate([u_before, u_before[-1:]])
        self._y = np.concatenate([y_before, np.full((1, y_before.shape[1]), np.nan)])
        self.steps = 0
        self.diverged = False

    def step(self, u: float | np.ndarray) -> np.ndarray:
        """y(k) (one value per output), then u(k) applied."""
        row = self.model._inputs(np.reshape(np.asarray(u, dtype=np.float64), (1, -1)), "u")[0]
        if self.diverged:
            return np.full(self.model.n_y, np.nan)
        window, model = self.model.history, self.model
        out = np.reshape(model.identifier.free_run(self._u, self._y, window, seeds_signed=True), (-1, model.n_y))[0]
        self.steps += 1
        if not np.all(np.isfinite(out)):
            self.diverged = True
            return out
        self._u[:-1] = np.concatenate([self._u[1:-1], row[None, :]])
        self._y[:-1] = np.concatenate([self._y[1:-1], out[None, :]])
        return self.model._read(out)


def load_model(directory: str | Path, node: str = "/identifier") -> Model:
    """The model ``lenn-ros fit -o DIR`` wrote: ``DIR/params.yaml`` (or a params file), its weights, its report.

    ``directory`` may also name a params file directly (``weights_in`` in it says where
    the weights are). ``node``: whose sections of the file apply (rcl's rules), for a
    file with several nodes. Raises :class:`ModelError` with the reason.
    """
    from lenn_ros.config import ConfigError
    from lenn_ros.service import RecordingError
    from lenn_ros.service.building import identifier_from_params

    path = Path(directory).expanduser()
    params = path / "params.yaml" if path.is_dir() else path
    if not params.is_file():
        raise ModelError(f"{params}: no params file (lenn-ros fit -o DIR writes DIR/params.yaml)")
    try:
        identifier, values = identifier_from_params(str(params), node)
    except (ConfigError, RecordingError, OSError, ValueError) as error:
        raise ModelError(f"{params}: {error}") from None
    if not values.get("weights_in"):
        raise ModelError(f"{params} names no weights_in: it describes a fresh network, not a fitted model")
    report_path = Path(str(values["weights_in"])).expanduser().parent / REPORT_FILE
    report = json.loads(report_path.read_text()) if report_path.is_file() else {}
    identifier.learning = False
    return Model(identifier, values, report, str(params))
