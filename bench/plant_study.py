"""Free runs of `lenn-ros fit` on plant classes with hard nonlinearities it was never developed on (issue 17).

    python bench/plant_study.py                  # tanks, belt, axis, axis-p2p, backlash, wiener-hammerstein, heater
    python bench/plant_study.py --plants tanks --seeds 3
    python bench/plant_study.py --frols          # and SysIdentPy's FROLS (polynomial NARX) beside them

The issue names what polynomials of low degree cannot follow: overflow and saturation,
a sensor that reads an absolute value, Coulomb friction on an axis sampled far faster
than its dynamics. Each plant here is textbook physics with round parameters chosen
from the physics (time constants, ranges), not from any data set; a seed draws the
excitation and the noise. The first two thirds build the model with ``fit``'s
defaults, the last third is simulated from its measured start. Next to ``fit``: the
linear ARX of ``bench/peer_narx.py`` (lags chosen by free run on the build tail),
scored on the same test part. A plant class where ``fit`` loses to the ARX, or where
its spread over seeds is wide, is a selection that does not generalise.

- ``tanks``: two cascaded tanks (Torricelli outflow), a pump voltage in, the lower
  tank's level out, sampled every 4 s, 1 536 samples. The upper tank overflows above
  its rim (half of the spill reaches the lower tank), so the lower tank's inflow
  saturates with a level the model never sees: no polynomial of degree 3 follows that.
  (The lower tank has a rim too, which this pump does not reach.)
- ``belt``: a motor driving a pulley over an elastic belt (a lightly damped mode at
  1.5 Hz) at 50 Hz, 750 samples; the speed sensor counts pulses, so it reads the
  absolute value of the speed, with 1 % noise.
- ``belt-drag``: the same with the pulley's quadratic air drag (1.0 w_p |w_p| rad/s^2: the speed
  follows a nonlinear law, its sign still hidden); ``belt-1khz``: the belt sampled at 1 kHz (15 000
  samples). Not in the default run.
- ``axis``: a 2 kg carriage with viscous and Coulomb friction (15 N) under a PD position
  controller (force limited to 200 N) that follows a smooth random trajectory, at 1 kHz,
  40 s; u is the force the controller applied, y the encoder position (1 um, 2 um noise).
  The model runs open loop from the force: a free run must keep the integrator and the
  friction right for 13 s.
- ``axis-p2p``: the same carriage moved between random set points; it stands still,
  stuck within the controller's dead band, most of the time. Its free run hinges on the
  Coulomb level: the true equations with Coulomb friction 2 % high score -20 dB.
- ``axis-p2p-200hz``, ``-noisy``, ``-coulomb30``, ``-soft``: the same sampled at 200 Hz,
  with 10 um encoder noise, with twice the Coulomb friction, under a softer loop (kp 1000
  N/m: a dead band four times wider). Not in the default run (``--plants`` names them).
- ``backlash``: a position-controlled joint (a 5 Hz servo on the motor angle) whose load hangs
  on the gear through a spring that pushes only beyond a +-0.01 rad gap, at 200 Hz, 40 s; u the
  commanded angle, y the load encoder. ``backlash-wide``: a +-0.05 rad gap (not in the default run).
- ``wiener-hammerstein``: an amplifier stage: a resonant filter, the static map tanh(2x) +
  0.5 max(x, 0) (a kink and a saturation), a second filter; 6 000 samples of band-limited noise.
  ``wh-clip`` and ``wh-dead-zone`` change the map (a hard clip at +-0.4, a dead zone of +-0.3);
  ``hammerstein`` drops the first filter, ``wiener`` the second (not in the default run).
- ``heater``: a plate heated by up to 300 W that cannot cool (the command in [-0.2, 1.2] is
  clipped to [0, 1]), losing heat by convection and by radiation (T^4), read in deg C at 0.1 K
  resolution every 5 s, 3 000 samples.
- ``ph``: pH neutralisation in a stirred tank (acid, buffer and base streams; the pH solves the charge
  balance, so the gain changes tenfold across the titration curve), the base flow in, every 15 s, 1 500
  samples. ``cstr``: a cooled exothermic reactor (Arrhenius rate), the coolant temperature in (below
  ignition), the reactor temperature out, every 0.05 min, 2 000 samples. Added after every family and rule
  of ``fit`` was fixed, as plants it had never seen (not in the default run).
- ``tanks-idle``, ``heater-idle``: the same, resting for 2 000 samples before the record (the input
  held at its first level; the heater off): a log started long before the experiment moves.
"""

from __future__ import annotations

import argparse
import functools
import math
from dataclasses import dataclass

import numpy as np
from joint_study import spread, timed_fit
from peer_narx import Split, run_arx, run_frols

from lenn_ros.core.jit import njit


def _smooth_levels(rng: np.random.Generator, n: int, hold: tuple[int, int], low: float, high: float) -> np.ndarray:
    """Random levels in [low, high] held for ``hold`` samples each."""
    out = np.empty(n)
    k = 0
    while k < n:
        length = int(rng.integers(hold[0], hold[1] + 1))
        out[k : k + length] = rng.uniform(low, high)
        k += length
    return out


@njit(cache=True)
def _tanks(u: np.ndarray, period: float) -> np.ndarray:
    rim1, rim2, pump, k1, k2 = 10.0, 10.0, 0.04, 0.06, 0.07
    h1, h2 = 2.0, 2.0
    out = np.empty(len(u))
    substeps = 40
    h = period / substeps
    for k in range(len(u)):
        out[k] = h2
        for _ in range(substeps):
            flow1 = k1 * math.sqrt(max(h1, 0.0))
            h1 += h * (pump * u[k] - flow1)
            spill = 0.0
            if h1 > rim1:
                spill = h1 - rim1
                h1 = rim1
            h2 += h * (flow1 - k2 * math.sqrt(max(h2, 0.0))) + 0.5 * spill
            h2 = min(h2, rim2)
    return out


def tanks(seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng([seed, 1])
    u = _smooth_levels(rng, 1536, (10, 60), 0.5, 6.5)
    y = _tanks(u, 4.0)
    return u, y + rng.normal(0.0, 0.02, len(y))


@njit(cache=True)
def _belt(u: np.ndarray, period: float, drag: float = 0.0) -> np.ndarray:
    # motor speed w_m (first order, 0.15 s), belt spring to the pulley (w_p): a mode near 1.5 Hz, damping 0.08;
    # ``drag``: the pulley's quadratic air drag, drag w_p |w_p| (rad/s^2)
    tau, gain, wn, zeta = 0.15, 2.0, 2.0 * math.pi * 1.5, 0.08
    wm, twist, wp = 0.0, 0.0, 0.0
    out = np.empty(len(u))
    substeps = 20
    h = period / substeps
    for k in range(len(u)):
        out[k] = wp
        for _ in range(substeps):
            wm += h * (gain * u[k] - wm) / tau
            accel = wn * wn * twist + 2.0 * zeta * wn * (wm - wp) - drag * wp * abs(wp)
            wp += h * accel
            twist += h * (wm - wp)
    return out


def belt_speed(seed: int, drag: float = 0.0, period: float = 0.02) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(u, the |speed| sensor's reading, the signed pulley speed it reads): 15 s, commands held 0.06-0.3 s."""
    rng = np.random.default_rng([seed, 2])
    n, hold = round(15.0 / period), (round(0.06 / period), round(0.3 / period))
    levels = _smooth_levels(rng, n, hold, 0.3, 1.5)
    sign = np.where(_smooth_levels(rng, n, hold, -1.0, 1.0) >= 0.0, 1.0, -1.0)
    u = levels * sign
    speed = _belt(u, period, drag)
    y = np.abs(speed)
    return u, y + rng.normal(0.0, 0.01 * np.std(y), len(y)), speed


def belt(seed: int) -> tuple[np.ndarray, np.ndarray]:
    u, y, _ = belt_speed(seed)
    return u, y


@dataclass(frozen=True)
class Carriage:
    """The carriage and its PD loop (the defaults are ``axis`` and ``axis-p2p``; the ``axis-p2p-*`` variants
    change one thing each)."""

    period: float = 0.001  # s
    noise: float = 2e-6  # m, the encoder's noise before its 1 um resolution
    coulomb: float = 15.0  # N
    kp: float = 4000.0  # N / m
    kd: float = 250.0  # N s / m


VARIANTS = {
    "axis-p2p-200hz": Carriage(period=0.005, kd=150.0),
    "axis-p2p-noisy": Carriage(noise=1e-5),
    "axis-p2p-coulomb30": Carriage(coulomb=30.0),
    "axis-p2p-soft": Carriage(kp=1000.0, kd=100.0),
}


@njit(cache=True)
def _axis(
    reference: np.ndarray, period: float, noise: np.ndarray, coulomb: float, kp: float, kd: float
) -> tuple[np.ndarray, np.ndarray]:
    mass, viscous, limit = 2.0, 20.0, 200.0
    x, v = 0.0, 0.0
    force = np.empty(len(reference))
    position = np.empty(len(reference))
    substeps = max(1, round(period / 0.0002))
    h = period / substeps
    previous = 0.0
    for k in range(len(reference)):
        measured = round((x + noise[k]) / 1e-6) * 1e-6
        position[k] = measured
        rate = (measured - previous) / period if k > 0 else 0.0
        previous = measured
        f = kp * (reference[k] - measured) - kd * rate
        f = min(max(f, -limit), limit)
        force[k] = f
        for _ in range(substeps):
            friction = viscous * v + (coulomb if v > 0 else (-coulomb if v < 0 else 0.0))
            if v == 0.0 and abs(f) <= coulomb:
                friction = f
            v_new = v + h * (f - friction) / mass
            if v != 0.0 and v_new * v < 0.0:  # friction stops the carriage, never reverses it
                v_new = 0.0
            v = v_new
            x += h * v
    return force, position


@njit(cache=True)
def _lowpass(x: np.ndarray, corner: float, period: float) -> np.ndarray:
    """x through two first-order lags at ``corner`` Hz."""
    alpha = 1.0 - math.exp(-2.0 * math.pi * corner * period)
    first, second = 0.0, 0.0
    out = np.empty(len(x))
    for k in range(len(x)):
        first += alpha * (x[k] - first)
        second += alpha * (first - second)
        out[k] = second
    return out


def _axis_run(reference: np.ndarray, rng: np.random.Generator, carriage: Carriage) -> tuple[np.ndarray, np.ndarray]:
    c = carriage
    return _axis(reference, c.period, rng.normal(0.0, c.noise, len(reference)), c.coulomb, c.kp, c.kd)


def axis(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """The carriage following a smooth random trajectory (white noise through two first-order lags at
    1.5 Hz, 0.1 m spread): it moves nearly all the time and reverses often."""
    rng = np.random.default_rng([seed, 4])
    n = 40_000
    reference = _lowpass(rng.normal(0.0, 1.0, n), 1.5, 0.001)
    return _axis_run(0.1 * reference / np.std(reference), rng, Carriage())


def axis_p2p(seed: int, carriage: Carriage = Carriage()) -> tuple[np.ndarray, np.ndarray]:
    """The carriage moved between random set points (moves of 0.2 s, held 0.3-1.5 s, 40 s): it stands still,
    stuck by Coulomb friction within the controller's dead band, for most of the run."""
    rng = np.random.default_rng([seed, 3])
    n = round(40.0 / carriage.period)
    targets = _smooth_levels(rng, n, (round(0.3 / carriage.period), round(1.5 / carriage.period)), -0.1, 0.1)
    move = round(0.2 / carriage.period)
    reference = np.convolve(targets, np.ones(move) / move, mode="full")[:n]
    return _axis_run(reference, rng, carriage)


@njit(cache=True)
def _backlash(reference: np.ndarray, period: float, gap: float) -> np.ndarray:
    # a servo holds the motor angle on the reference (5 Hz, damping 0.7); the load (0.01 kg m^2) hangs on the
    # gear through a spring (25 N m/rad: 8 Hz) that pushes only beyond +-gap; viscous friction 0.02 N m s
    wn, zeta = 2.0 * math.pi * 5.0, 0.7
    inertia, stiffness, damping, friction = 0.01, 25.0, 0.1, 0.02
    motor, motor_rate, load, load_rate = 0.0, 0.0, 0.0, 0.0
    out = np.empty(len(reference))
    substeps = 50
    h = period / substeps
    for k in range(len(reference)):
        out[k] = load
        for _ in range(substeps):
            motor_rate += h * (wn * wn * (reference[k] - motor) - 2.0 * zeta * wn * motor_rate)
            motor += h * motor_rate
            twist = motor - load
            torque = 0.0
            if twist > gap:
                torque = stiffness * (twist - gap) + damping * (motor_rate - load_rate)
            elif twist < -gap:
                torque = stiffness * (twist + gap) + damping * (motor_rate - load_rate)
            load_rate += h * (torque - friction * load_rate) / inertia
            load += h * load_rate
    return out


def backlash(seed: int, gap: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """A position-controlled joint whose load hangs on a gear with backlash (200 Hz, 40 s): u the commanded
    angle (random set points, +-1 rad, held 0.3-2 s, through two 2 Hz lags), y the load encoder (0.2 mrad noise)."""
    rng = np.random.default_rng([seed, 3])
    period = 0.005
    u = _lowpass(_smooth_levels(rng, 8000, (60, 400), -1.0, 1.0), 2.0, period)
    y = _backlash(u, period, gap)
    return u, y + rng.normal(0.0, 2e-4, len(y))


@njit(cache=True)
def _filtered(x: np.ndarray, w: float, zeta: float) -> np.ndarray:
    # a second-order low-pass (natural frequency w rad/sample, damping zeta), simulated with substeps
    out = np.empty(len(x))
    state, rate = 0.0, 0.0
    substeps = 20
    h = 1.0 / substeps
    for k in range(len(x)):
        out[k] = state
        for _ in range(substeps):
            rate += h * (w * w * (x[k] - state) - 2.0 * zeta * w * rate)
            state += h * rate
    return out


#: the static maps of the ``wiener-hammerstein`` variants: a diode with saturation, a hard clip, a dead zone
STATIC_MAPS = {
    "diode": lambda x: np.tanh(2.0 * x) + 0.5 * np.maximum(x, 0.0),
    "clip": lambda x: np.clip(x, -0.4, 0.4),
    "dead-zone": lambda x: np.sign(x) * np.maximum(np.abs(x) - 0.3, 0.0),
}


def wiener_hammerstein(
    seed: int, shape: str = "diode", before: bool = True, after: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """A filter, a static map, a filter (an amplifier stage): 6 000 samples of band-limited noise in, 1 % output
    noise. The default map tanh(2x) + 0.5 max(x, 0) has a kink at 0 and saturates; ``before`` / ``after`` False
    drop the first filter (a Hammerstein system) or the second (a Wiener system)."""
    rng = np.random.default_rng([seed, 4])
    u = _filtered(rng.normal(0.0, 1.0, 6000), 2.0 * math.pi * 0.15, 0.7)
    u *= 0.6 / np.std(u)
    x = _filtered(u, 2.0 * math.pi * 0.05, 0.3) if before else u
    mapped = STATIC_MAPS[shape](x)
    y = _filtered(mapped, 2.0 * math.pi * 0.08, 0.5) if after else mapped
    return u, y + rng.normal(0.0, 0.01 * np.std(y), len(y))


@njit(cache=True)
def _heater(u: np.ndarray, period: float) -> np.ndarray:
    # a plate (600 J/K) heated by up to 300 W (it cannot cool: the power is clipped to [0, 300]); convection
    # 2 W/K and radiation to a 293 K room
    capacity, convection, radiation, ambient = 600.0, 2.0, 0.8 * 5.67e-8 * 0.05, 293.0
    temp = ambient
    out = np.empty(len(u))
    substeps = 20
    h = period / substeps
    for k in range(len(u)):
        out[k] = temp - 273.15
        power = 300.0 * min(max(u[k], 0.0), 1.0)
        for _ in range(substeps):
            loss = convection * (temp - ambient) + radiation * (temp**4 - ambient**4)
            temp += h * (power - loss) / capacity
    return out


def heater(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A heated plate read in deg C (5 s, 3 000 samples): the command in [-0.2, 1.2] is clipped to the heater's
    [0, 1], radiation grows with T^4; the sensor reads 0.05 K noise at 0.1 K resolution."""
    rng = np.random.default_rng([seed, 5])
    u = _smooth_levels(rng, 3000, (12, 120), -0.2, 1.2)
    y = _heater(u, 5.0)
    return u, np.round((y + rng.normal(0.0, 0.05, len(y))) / 0.1) * 0.1


@njit(cache=True)
def _ph(u: np.ndarray, period: float) -> np.ndarray:
    # a stirred tank (2 900 ml) neutralising a nitric acid stream (16.6 ml/s) and a bicarbonate buffer stream
    # (0.55 ml/s) with a base stream of u ml/s; the states are the reaction invariants, the pH solves the
    # charge balance (carbonic acid's two dissociation constants), found by bisection
    volume, q1, q2 = 2900.0, 16.6, 0.55
    wa1, wa2, wa3, wb2, wb3, pk1, pk2 = 0.003, -0.03, -3.05e-3, 0.03, 5e-5, 6.35, 10.25
    q3 = u[0]
    wa = (q1 * wa1 + q2 * wa2 + q3 * wa3) / (q1 + q2 + q3)
    wb = (q2 * wb2 + q3 * wb3) / (q1 + q2 + q3)
    out = np.empty(len(u))
    substeps = 30
    h = period / substeps
    for k in range(len(u)):
        low, high = 0.0, 14.0
        for _ in range(60):
            ph = 0.5 * (low + high)
            balance = wa + 10.0 ** (ph - 14.0) - 10.0 ** (-ph)
            balance += wb * (1.0 + 2.0 * 10.0 ** (ph - pk2)) / (1.0 + 10.0 ** (pk1 - ph) + 10.0 ** (ph - pk2))
            if balance > 0.0:
                high = ph
            else:
                low = ph
        out[k] = 0.5 * (low + high)
        q3 = u[k]
        for _ in range(substeps):
            wa += h * (q1 * (wa1 - wa) + q2 * (wa2 - wa) + q3 * (wa3 - wa)) / volume
            wb += h * (q2 * (wb2 - wb) + q3 * (wb3 - wb)) / volume
    return out


def ph(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """pH neutralisation (the titration curve: a gain that changes tenfold around pH 7-9): the base flow in ml/s
    held at random levels in [11, 20], the pH every 15 s with 0.01 noise, 1 500 samples."""
    rng = np.random.default_rng([seed, 13])
    u = _smooth_levels(rng, 1500, (8, 50), 11.0, 20.0)
    return u, _ph(u, 15.0) + rng.normal(0.0, 0.01, len(u))


@njit(cache=True)
def _cstr(u: np.ndarray, period: float) -> np.ndarray:
    # an exothermic first-order reaction in a cooled stirred tank (Arrhenius rate, E/R 8 750 K), the
    # coolant's temperature u in K; one volume a minute flows through
    ca, temp = 0.5, 350.0
    out = np.empty(len(u))
    substeps = 20
    h = period / substeps
    for k in range(len(u)):
        out[k] = temp
        for _ in range(substeps):
            rate = 7.2e10 * math.exp(-8750.0 / temp) * ca
            ca += h * (1.0 - ca - rate)
            temp += h * (350.0 - temp + 209.2 * rate + 2.092 * (u[k] - temp))
    return out


def cstr(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A cooled exothermic reactor: the coolant's temperature held at random levels in [286, 302] K (below
    ignition), the reactor's temperature every 0.05 min with 0.1 K noise, 2 000 samples (its gain and speed
    change with the Arrhenius rate)."""
    rng = np.random.default_rng([seed, 14])
    u = _smooth_levels(rng, 2000, (10, 80), 286.0, 302.0)
    return u, _cstr(u, 0.05) + rng.normal(0.0, 0.1, len(u))


def dead_time(plant, samples: int):
    """``plant`` behind a dead time of ``samples`` (a pipe, a conveyor, a command pipeline): each input acts
    that many samples later than it did."""

    def delayed(seed: int) -> tuple[np.ndarray, np.ndarray]:
        u, y = plant(seed)
        return u[samples:], y[: len(y) - samples]

    return delayed


#: samples a plant rests before its record in the ``-idle`` variants
IDLE = 2000


def tanks_idle(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """The tanks resting for IDLE samples, the pump held at its first level, before their record moves (a log
    started long before the experiment)."""
    u, _ = tanks(seed)
    u = np.r_[np.full(IDLE, u[0]), u]
    return u, _tanks(u, 4.0) + np.random.default_rng([seed, 11]).normal(0.0, 0.02, len(u))


def heater_idle(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """The plate at room temperature, its heater off for IDLE samples, before its record."""
    u, _ = heater(seed)
    u = np.r_[np.zeros(IDLE), u]
    y = _heater(u, 5.0) + np.random.default_rng([seed, 12]).normal(0.0, 0.05, len(u))
    return u, np.round(y / 0.1) * 0.1


PLANTS = {
    "tanks": tanks,
    "tanks-idle": tanks_idle,
    "heater-idle": heater_idle,
    "belt": belt,
    "belt-drag": lambda seed: belt_speed(seed, drag=1.0)[:2],
    "belt-1khz": lambda seed: belt_speed(seed, period=0.001)[:2],
    "axis": axis,
    "axis-p2p": axis_p2p,
    **{name: functools.partial(axis_p2p, carriage=carriage) for name, carriage in VARIANTS.items()},
    "backlash": backlash,
    "backlash-wide": functools.partial(backlash, gap=0.05),
    "wiener-hammerstein": wiener_hammerstein,
    "wh-clip": functools.partial(wiener_hammerstein, shape="clip"),
    "wh-dead-zone": functools.partial(wiener_hammerstein, shape="dead-zone"),
    "hammerstein": functools.partial(wiener_hammerstein, before=False),
    "wiener": functools.partial(wiener_hammerstein, after=False),
    "heater": heater,
    "hammerstein-dead-time": dead_time(functools.partial(wiener_hammerstein, before=False), 8),
    "wh-dead-time": dead_time(wiener_hammerstein, 8),
    "heater-dead-time": dead_time(heater, 6),
    "ph": ph,
    "cstr": cstr,
}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument(
        "--plants", default="tanks,belt,axis,axis-p2p,backlash,wiener-hammerstein,heater,hammerstein-dead-time"
    )
    parser.add_argument(
        "--frols", action="store_true", help="also SysIdentPy's FROLS (polynomial NARX, peer_narx.py's grid)"
    )
    args = parser.parse_args(argv)
    peer = " FROLS free-run NMSE dB, mean (min..max) | fit better than FROLS |" if args.frols else ""
    print("| plant | fit free-run NMSE dB, mean (min..max) | ARX free-run NMSE dB, mean (min..max) | "
          f"fit better than ARX | fit one-step dB, mean | fit time s, mean | models chosen |{peer}")  # fmt: skip
    print("|---|---|---|---|---|---|---|" + ("---|---|" if args.frols else ""))
    for name in args.plants.split(","):
        free, arx, frols, one, seconds, models = [], [], [], [], [], []
        for seed in range(args.seeds):
            u, y = PLANTS[name](seed)
            test_from = len(y) * 2 // 3 + 1
            report, took = timed_fit(u, y, f"{name} seed {seed}", test_from)
            seconds.append(took)
            free.append(report.nmse_free_run_db)
            one.append(report.nmse_db)
            m = report.model
            models.append(f"{m['family']} {m['expansion']['degree']}/{m['structure']['y_lags']}/{m['n_terms']}")
            split = Split(name, u, y, test_from, "")
            arx.append(_db(run_arx(split)["rmse_free_run"], y[test_from - 1 :]))
            if args.frols:
                frols.append(_db(run_frols(split)["rmse_free_run"], y[test_from - 1 :]))
        wins = sum(f < a for f, a in zip(free, arx, strict=True))
        beyond = ""
        if args.frols:  # a FROLS run that diverged (NaN) counts as beaten
            beaten = sum(not f >= p for f, p in zip(free, frols, strict=True))
            finite = [v for v in frols if math.isfinite(v)]
            diverged = f", {len(frols) - len(finite)} diverged" if len(finite) < len(frols) else ""
            beyond = f" {spread(finite) if finite else '-'}{diverged} | {beaten} of {len(free)} |"
        print(
            f"| {name} | {spread(free)} | {spread(arx)} | {wins} of {len(free)} | {np.mean(one):.1f} | "
            f"{np.mean(seconds):.1f} | {', '.join(models)} |{beyond}",
            flush=True,
        )
    return 0


def _db(rmse: float, y_test: np.ndarray) -> float:
    """A peer's free-run RMSE over the test part as NMSE in dB (NaN if its run diverged)."""
    return 10.0 * math.log10(rmse**2 / np.var(y_test)) if math.isfinite(rmse) else math.nan


if __name__ == "__main__":
    raise SystemExit(main())
