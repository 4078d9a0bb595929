"""Physical plants a robot is made of, for the simulator and the tests: a joint with friction.

The paper's plants are difference equations that are polynomials of their lags. A
real joint is a continuous-time body with friction that is not smooth: Coulomb
friction changes sign with the velocity, and stiction holds the joint at rest until
the torque overcomes it. A model builder must be judged on such plants too (a
polynomial of the lags cannot follow the sign of a velocity), so the simulated robot
can be one.

:class:`FrictionJoint` has the interface :class:`~lenn_ros.paper.robot.SimulatedRobot`
steps (``output``, ``step``, ``reset``) and a whole-run :meth:`FrictionJoint.run`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lenn_ros.core.jit import njit


@njit(cache=True, nogil=True)
def _joint_steps(
    state: np.ndarray, torques: np.ndarray, parameters: np.ndarray, substeps: int, dt: float, out: np.ndarray
) -> None:
    """Advance (angle, velocity) through each torque held for one sample; out[k] = the angle before torque k.

    Semi-implicit Euler on ``substeps`` sub-steps per sample. At rest (|velocity| below
    ``parameters[6]``) the joint stays stuck while the net torque is within stiction; ``parameters[5]`` is the
    actuator's gain on the commanded torque.
    """
    inertia, gravity, viscous, coulomb, stiction, gain, rest = parameters[:7]
    h = dt / substeps
    angle, velocity = state[0], state[1]
    for k in range(len(torques)):
        out[k] = angle
        for _ in range(substeps):
            drive = gain * torques[k] - gravity * math.sin(angle)
            if abs(velocity) < rest and abs(drive) <= stiction:
                velocity = 0.0
                continue
            direction = velocity if velocity != 0.0 else drive
            friction = viscous * velocity + coulomb * (1.0 if direction > 0 else -1.0)
            velocity += h * (drive - friction) / inertia
            angle += h * velocity
    state[0], state[1] = angle, velocity


@dataclass
class FrictionJoint:
    """A pendulum joint: J th'' = tau - m g l sin(th) - b th' - F_c sgn(th'), held by stiction F_s at rest.

    Angles in radians, torques in newton metres; ``period`` is the sample time the
    torque is held for (zero-order hold), ``substeps`` the integration steps within it.
    The defaults make a joint whose natural frequency is about 2 Hz, which random steps
    of torque within +-2 N m swing by up to about +-1 rad (never over the top), and which
    sticks for a while after a reversal.
    """

    period: float = 0.005
    inertia: float = 0.02
    gravity: float = 4.0  # m g l, N m
    viscous: float = 0.1  # N m s / rad
    coulomb: float = 0.1  # N m
    stiction: float = 0.15  # N m
    gain: float = 1.0  # the actuator's: N m applied per N m commanded
    substeps: int = 10
    rest: float = 1e-3  # rad / s below which the joint may stick
    name: str = "friction joint"

    def __post_init__(self) -> None:
        if not (self.period > 0 and self.inertia > 0 and self.substeps >= 1):
            raise ValueError("a joint needs period > 0, inertia > 0 and substeps >= 1")
        self.reset()

    def _parameters(self) -> np.ndarray:
        """What the compiled steps read, from the attributes as they are now (a change may have set them)."""
        return np.array([self.inertia, self.gravity, self.viscous, self.coulomb, self.stiction, self.gain, self.rest])

    def reset(self) -> None:
        """At rest, hanging down."""
        self.state = np.zeros(2)

    @property
    def output(self) -> float:
        """The angle now (before the next torque acts)."""
        return float(self.state[0])

    def step(self, torque: float) -> float:
        """Hold ``torque`` for one period; returns the angle after it."""
        out = np.empty(1)
        _joint_steps(self.state, np.array([float(torque)]), self._parameters(), self.substeps, self.period, out)
        return float(self.state[0])

    def run(self, torques: np.ndarray) -> np.ndarray:
        """Angles y(0..N) for torques u(0..N-1): y[k] is shown before u[k] acts (the package's convention)."""
        torques = np.ascontiguousarray(torques, dtype=np.float64)
        out = np.empty(len(torques) + 1)
        _joint_steps(self.state, torques, self._parameters(), self.substeps, self.period, out[:-1])
        out[-1] = self.state[0]
        return out


@njit(cache=True, nogil=True)
def _servo_steps(
    state: np.ndarray, setpoints: np.ndarray, parameters: np.ndarray, substeps: int, dt: float, out: np.ndarray
) -> None:
    """Advance the belt drive under its PD loop through each setpoint held for one sample; out[k]: load angle before.

    state: motor angle, motor velocity, load angle, load velocity. Semi-implicit Euler on ``substeps`` sub-steps.
    """
    gain, j_motor, j_load, stiffness, damping, viscous, coulomb, kp, kd, limit = parameters[:10]
    h = dt / substeps
    motor, motor_v, load, load_v = state[0], state[1], state[2], state[3]
    for k in range(len(setpoints)):
        out[k] = load
        for _ in range(substeps):
            command = kp * (setpoints[k] - motor) - kd * motor_v
            command = min(max(command, -limit), limit)
            belt = stiffness * (motor - load) + damping * (motor_v - load_v)
            sign = 1.0 if motor_v > 0 else (-1.0 if motor_v < 0 else 0.0)
            motor_v += h * (gain * command - belt - viscous * motor_v - coulomb * sign) / j_motor
            load_v += h * (belt - viscous * load_v) / j_load
            motor += h * motor_v
            load += h * load_v
    state[0], state[1], state[2], state[3] = motor, motor_v, load, load_v


@dataclass
class ServoAxis:
    """A belt-driven positioning axis under its own PD loop: u the position setpoint, y the load's angle (rad).

    J_m th_m'' = g tau - k (th_m - th_l) - c (th_m' - th_l') - b th_m' - F_c sgn(th_m'),
    J_l th_l'' = k (th_m - th_l) + c (th_m' - th_l') - b th_l', tau = sat(K_p (r - th_m) - K_d th_m'):
    the loop closes on the motor's encoder, so the belt's compliance and the friction show in the load's
    angle (a PD loop leaves a friction-dependent error). About 4 Hz closed-loop bandwidth, sampled at
    ``period``. Its changes (:data:`PLANT_CHANGES`): ``gain`` (the amplifier's, g), ``friction`` (F_c and b),
    ``payload`` (J_l), ``offset`` (added to y by :func:`changed_run`).
    """

    period: float = 0.01
    gain: float = 1.0
    motor_inertia: float = 1.0e-4  # kg m^2
    payload: float = 5.0e-4  # the load's inertia, kg m^2
    stiffness: float = 20.0  # the belt's, N m / rad
    damping: float = 0.02  # N m s / rad
    viscous: float = 2.0e-3  # N m s / rad
    coulomb: float = 0.02  # N m
    kp: float = 0.5  # N m / rad
    kd: float = 0.02  # N m s / rad
    limit: float = 1.0  # N m
    substeps: int = 100
    name: str = "servo axis"

    def __post_init__(self) -> None:
        if not (self.period > 0 and self.motor_inertia > 0 and self.payload > 0 and self.substeps >= 1):
            raise ValueError("a servo axis needs period > 0, inertias > 0 and substeps >= 1")
        self.reset()

    def _parameters(self) -> np.ndarray:
        return np.array(
            [self.gain, self.motor_inertia, self.payload, self.stiffness, self.damping, self.viscous, self.coulomb,
             self.kp, self.kd, self.limit]
        )  # fmt: skip

    def reset(self) -> None:
        """At rest at 0."""
        self.state = np.zeros(4)

    @property
    def output(self) -> float:
        """The load's angle now."""
        return float(self.state[2])

    def step(self, setpoint: float) -> float:
        """Hold ``setpoint`` for one period; returns the load's angle after it."""
        out = np.empty(1)
        _servo_steps(self.state, np.array([float(setpoint)]), self._parameters(), self.substeps, self.period, out)
        return float(self.state[2])

    def run(self, setpoints: np.ndarray) -> np.ndarray:
        """Angles y(0..N) for setpoints u(0..N-1): y[k] is shown before u[k] acts."""
        setpoints = np.ascontiguousarray(setpoints, dtype=np.float64)
        out = np.empty(len(setpoints) + 1)
        _servo_steps(self.state, setpoints, self._parameters(), self.substeps, self.period, out[:-1])
        out[-1] = self.state[2]
        return out


PHYSICAL_PLANTS = {"friction_joint": FrictionJoint, "servo_axis": ServoAxis}

#: A plant change: what it scales on each physical plant (``offset`` is added to the output instead).
PLANT_CHANGES: dict[str, dict[str, tuple[str, ...]]] = {
    "gain": {"servo_axis": ("gain",), "friction_joint": ("gain",)},
    "friction": {"servo_axis": ("coulomb", "viscous"), "friction_joint": ("viscous", "coulomb", "stiction")},
    "payload": {"servo_axis": ("payload",), "friction_joint": ("inertia", "gravity")},
    "offset": {"servo_axis": (), "friction_joint": ()},
}


def change_plant(plant: FrictionJoint | ServoAxis, kind: str, size: float) -> None:
    """Change ``plant`` in place: ``kind`` (:data:`PLANT_CHANGES`) by the relative ``size`` (-0.2: 20 % less),
    keeping its state (a change happens to a running plant). ``offset`` changes nothing here: the caller adds it
    to the output (:func:`changed_run`)."""
    if kind not in PLANT_CHANGES:
        raise ValueError(f"unknown plant change {kind!r}; known: {', '.join(PLANT_CHANGES)}")
    key = "servo_axis" if isinstance(plant, ServoAxis) else "friction_joint"
    for name in PLANT_CHANGES[kind][key]:
        setattr(plant, name, getattr(plant, name) * (1.0 + size))


def changed_run(
    plant: FrictionJoint | ServoAxis, u: np.ndarray, at: int | None, kind: str = "gain", size: float = 0.0
) -> np.ndarray:
    """Outputs y(0..N-1) of ``plant`` driven by u, changed (:func:`change_plant`) from sample ``at`` on (None:
    never): y[at] is the first output the changed plant made. ``offset``: ``size`` is added to y[at:]."""
    u = np.asarray(u, dtype=np.float64)
    if at is None or at >= len(u):
        return plant.run(u)[:-1]
    first = plant.run(u[: at - 1])  # y(0..at-1); the state now makes y(at-1) -> after u(at-1)
    change_plant(plant, kind, size)
    y = np.concatenate([first[:-1], plant.run(u[at - 1 :])[:-1]])
    if kind == "offset":
        y[at:] += size
    return y


def physical_plant(name: str, period: float) -> FrictionJoint:
    """A physical plant by name, sampled every ``period`` s (one error line for an unknown one)."""
    if name not in PHYSICAL_PLANTS:
        raise ValueError(f"unknown physical plant {name!r}; known: {', '.join(PHYSICAL_PLANTS)}")
    return PHYSICAL_PLANTS[name](period=period)
