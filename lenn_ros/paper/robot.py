"""A simulated robot: a paper plant stepped on its own clock, fed by another process's commands.

The ROS-free half of ``robot_simulator`` (the driver) and the offline side of its
test. On a robot the command comes from a controller at the controller's rate and
the driver samples the plant at its own: the plant step k at time t_k applies the
latest command received at or before t_k (zero-order hold, :class:`CommandHold`).
:class:`SimulatedRobot` steps the plant with plant-input noise, adds measurement
noise, decides which measurements are lost and how late each is published, and
keeps the plant's own series in a :class:`RobotLog`: the u actually applied and
y_p at every step, published or not. That series is what a lockstep simulator
would have given the identifier, so :func:`lockstep_nmse` turns it into the
reference a live, asynchronous identification is judged against.
"""

from __future__ import annotations

import bisect
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lenn_ros.core.metrics import nmse_db
from lenn_ros.core.structure import Identifier
from lenn_ros.paper.plants import Plant
from lenn_ros.paper.signals import noise_std

#: Arrays of a saved log, one entry per plant step.
LOG_ARRAYS = ("stamp_ns", "u", "u_received_ns", "noise", "y", "y_measured", "published")


class CommandHold:
    """Zero-order hold of a command stream by receive time.

    Commands are kept in time order; :meth:`at` answers with the latest one received
    at or before a time (and when it was received), and forgets what no later query
    can need (queries are expected in increasing time, as plant steps are). Before
    the first command the robot holds ``initial`` (a driver at rest commands nothing),
    received at -1.
    """

    def __init__(self, initial: float = 0.0) -> None:
        self.initial = initial
        self._times: list[int] = []
        self._values: list[float] = []
        self.received = 0
        self.latest_ns = -1  # receive time of the newest command

    def add(self, time_ns: int, value: float) -> None:
        position = bisect.bisect_right(self._times, time_ns)
        self._times.insert(position, time_ns)
        self._values.insert(position, value)
        self.received += 1
        self.latest_ns = max(self.latest_ns, time_ns)

    def at(self, time_ns: int) -> tuple[float, int]:
        """(command held at ``time_ns``, its receive time in ns)."""
        position = bisect.bisect_right(self._times, time_ns) - 1
        if position < 0:
            return self.initial, -1
        value, received = self._values[position], self._times[position]
        if position:  # older commands can no longer be the latest one
            del self._times[:position]
            del self._values[:position]
        return value, received


@dataclass
class RobotLog:
    """The plant's own series: per step its time, applied command (and when it came), noise, outputs."""

    period_ns: int
    example: int = 0
    stamp_ns: list[int] = field(default_factory=list)
    u: list[float] = field(default_factory=list)
    u_received_ns: list[int] = field(default_factory=list)
    noise: list[float] = field(default_factory=list)
    y: list[float] = field(default_factory=list)
    y_measured: list[float] = field(default_factory=list)
    published: list[bool] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.stamp_ns)

    def arrays(self) -> dict[str, np.ndarray]:
        return {
            "stamp_ns": np.asarray(self.stamp_ns, dtype=np.int64),
            "u": np.asarray(self.u, dtype=np.float64),
            "u_received_ns": np.asarray(self.u_received_ns, dtype=np.int64),
            "noise": np.asarray(self.noise, dtype=np.float64),
            "y": np.asarray(self.y, dtype=np.float64),
            "y_measured": np.asarray(self.y_measured, dtype=np.float64),
            "published": np.asarray(self.published, dtype=bool),
        }

    def save(self, path: str | os.PathLike) -> Path:
        """Write an .npz atomically (a reader never sees half a file)."""
        target = Path(path).expanduser()
        target.parent.mkdir(parents=True, exist_ok=True)
        handle, temporary = tempfile.mkstemp(dir=target.parent, prefix=target.name, suffix=".tmp")
        with os.fdopen(handle, "wb") as file:
            np.savez(file, period_ns=np.int64(self.period_ns), example=np.int64(self.example), **self.arrays())
        os.replace(temporary, target)
        return target

    @classmethod
    def load(cls, path: str | os.PathLike) -> RobotLog:
        with np.load(Path(path).expanduser()) as data:
            missing = [name for name in LOG_ARRAYS if name not in data]
            if missing:
                raise ValueError(f"{path}: not a robot log (no {', '.join(missing)})")
            return cls(
                period_ns=int(data["period_ns"]),
                example=int(data["example"]),
                **{name: data[name].tolist() for name in LOG_ARRAYS},
            )


class SimulatedRobot:
    """A plant stepped every ``period_ns``, with the imperfections of a real driver.

    Each imperfection draws from its own seeded stream, so changing the loss rate
    does not change the noise (and a run is repeatable for a seed):
    - ``input_noise_db``: white noise on the input the plant receives, in dB against
      U[-1, 1] (the paper's convention, :func:`signals.noise_std`); not in the log's u;
    - ``measurement_noise``: standard deviation added to the published y_p;
    - ``loss``: probability that a measurement is never published;
    - ``jitter_s``: each measurement is published ``latency_s`` + U[0, jitter_s] after
      the step it belongs to (its stamp stays the step's time);
    - ``stamp_jitter_s``: the driver's loop does not wake exactly on time: step k runs
      at t_k + U[-stamp_jitter_s, stamp_jitter_s] (:meth:`step_time_ns`), takes the
      command held then and is stamped then, as ros2_control stamps ``joint_states``
      with its loop's time. So the stamps jitter around the nominal grid, and each
      is the true time of its measurement and of its command;
    - ``stamp_offset_s``: the stamps' clock runs this far ahead of the clock the
      commands are received by (:meth:`header_stamp_ns`; negative: behind), as a
      driver on another, unsynchronised machine would stamp. The log keeps true times.
    """

    def __init__(
        self,
        plant: Plant,
        period_ns: int,
        input_noise_db: float | None = None,
        measurement_noise: float = 0.0,
        loss: float = 0.0,
        latency_s: float = 0.0,
        jitter_s: float = 0.0,
        seed: int = 0,
        example: int = 0,
        stamp_jitter_s: float = 0.0,
        stamp_offset_s: float = 0.0,
    ) -> None:
        if period_ns <= 0:
            raise ValueError("period_ns must be > 0")
        if not 0.0 <= stamp_jitter_s * 1e9 < 0.5 * period_ns:
            raise ValueError(f"stamp_jitter must be in [0, half a period), not {stamp_jitter_s} s: steps stay in order")
        if not 0.0 <= loss < 1.0:
            raise ValueError(f"loss must be in [0, 1), not {loss}")
        self.plant = plant
        self.plant.reset()
        self.period_ns = int(period_ns)
        self.sigma = noise_std(input_noise_db)
        self.measurement_noise = float(measurement_noise)
        self.loss = float(loss)
        self.latency_s = float(latency_s)
        self.jitter_s = float(jitter_s)
        self._noise_rng, self._measurement_rng, self._loss_rng, self._jitter_rng = (
            np.random.default_rng([seed, stream]) for stream in range(4)
        )
        # a stream of its own, so jitter on or off leaves the other streams (and earlier runs) as they were
        self._stamp_rng = np.random.default_rng([seed, 4])
        self.stamp_jitter_ns = round(stamp_jitter_s * 1e9)
        self.stamp_offset_ns = round(stamp_offset_s * 1e9)
        self.log = RobotLog(self.period_ns, example)

    def step_time_ns(self, nominal_ns: int) -> int:
        """When the step due at ``nominal_ns`` really runs (draw once per step, in step order)."""
        if not self.stamp_jitter_ns:
            return int(nominal_ns)
        return int(nominal_ns) + int(self._stamp_rng.integers(-self.stamp_jitter_ns, self.stamp_jitter_ns + 1))

    def header_stamp_ns(self, step_ns: int) -> int:
        """The stamp the driver writes for a step run at ``step_ns``: on its own clock."""
        return int(step_ns) + self.stamp_offset_ns

    def step(self, stamp_ns: int, u: float, u_received_ns: int = -1) -> tuple[float, bool, float]:
        """Step k at ``stamp_ns`` with command ``u``: (y_p(k) as measured, published?, delay s).

        y_p(k) is what the plant shows at t_k, before u(k) acts (the paper's sample
        convention: y_p(k+1) = f(..., u(k))).
        """
        y = self.plant.output
        noise = float(self._noise_rng.normal()) * self.sigma
        measured = y + float(self._measurement_rng.normal()) * self.measurement_noise
        published = bool(self._loss_rng.random() >= self.loss)
        delay = self.latency_s + float(self._jitter_rng.random()) * self.jitter_s
        self.plant.step(u + noise)
        log = self.log
        log.stamp_ns.append(int(stamp_ns))
        log.u.append(float(u))
        log.u_received_ns.append(int(u_received_ns))
        log.noise.append(noise)
        log.y.append(y)
        log.y_measured.append(measured)
        log.published.append(published)
        return measured, published, delay


def lockstep_nmse(
    identifier: Identifier,
    log: RobotLog,
    start_ns: int | None = None,
    stop_ns: int | None = None,
) -> float:
    """One-step NMSE (dB) a lockstep identification reaches on the robot's own series.

    The steps stamped in [start_ns, stop_ns] are learnt in order, every one of them
    (lockstep loses nothing), with the applied command and the measured y_p, and the
    a-priori errors are scored as the live identifier scores its training phase. A
    live run over the same span and the same plant is judged against this figure.
    """
    arrays = log.arrays()
    stamps = arrays["stamp_ns"]
    keep = np.ones(len(stamps), dtype=bool)
    if start_ns is not None:
        keep &= stamps >= start_ns
    if stop_ns is not None:
        keep &= stamps <= stop_ns
    u, y = arrays["u"][keep], arrays["y_measured"][keep]
    if len(y) < 2:
        raise ValueError(f"only {len(y)} logged steps in the span: nothing to score")
    y_hat = identifier.run(u, y, learn=np.ones(len(y), dtype=bool))
    scored = np.isfinite(y_hat)
    return nmse_db(y[scored], y_hat[scored])
