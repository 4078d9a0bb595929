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
    ``parameters[6]``) the joint stays stuck while the net torque is within stiction.
    """
    inertia, gravity, viscous, coulomb, stiction, _, rest = parameters[:7]
    h = dt / substeps
    angle, velocity = state[0], state[1]
    for k in range(len(torques)):
        out[k] = angle
        for _ in range(substeps):
            drive = torques[k] - gravity * math.sin(angle)
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
    substeps: int = 10
    rest: float = 1e-3  # rad / s below which the joint may stick
    name: str = "friction joint"

    def __post_init__(self) -> None:
        if not (self.period > 0 and self.inertia > 0 and self.substeps >= 1):
            raise ValueError("a joint needs period > 0, inertia > 0 and substeps >= 1")
        self._parameters = np.array(
            [self.inertia, self.gravity, self.viscous, self.coulomb, self.stiction, 0.0, self.rest]
        )
        self.reset()

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
        _joint_steps(self.state, np.array([float(torque)]), self._parameters, self.substeps, self.period, out)
        return float(self.state[0])

    def run(self, torques: np.ndarray) -> np.ndarray:
        """Angles y(0..N) for torques u(0..N-1): y[k] is shown before u[k] acts (the package's convention)."""
        torques = np.ascontiguousarray(torques, dtype=np.float64)
        out = np.empty(len(torques) + 1)
        _joint_steps(self.state, torques, self._parameters, self.substeps, self.period, out[:-1])
        out[-1] = self.state[0]
        return out


PHYSICAL_PLANTS = {"friction_joint": FrictionJoint}


def physical_plant(name: str, period: float) -> FrictionJoint:
    """A physical plant by name, sampled every ``period`` s (one error line for an unknown one)."""
    if name not in PHYSICAL_PLANTS:
        raise ValueError(f"unknown physical plant {name!r}; known: {', '.join(PHYSICAL_PLANTS)}")
    return PHYSICAL_PLANTS[name](period=period)
