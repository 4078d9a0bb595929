"""Input signals of the paper's protocol and the noise that corrupts the plant input."""

from __future__ import annotations

import numpy as np

#: Mean power of u ~ U[-1, 1]: the reference for the noise level in dB (see noise_std).
UNIFORM_INPUT_POWER = 1.0 / 3.0


def uniform_input(n_samples: int, rng: np.random.Generator) -> np.ndarray:
    """Training input: i.i.d. uniform on [-1, 1] (paper, Section IV)."""
    return rng.uniform(-1.0, 1.0, n_samples)


def test_sinusoid(n_samples: int = 600, start: int = 1) -> np.ndarray:
    """Test input of eq. 11, for k = start, start + 1, ...

    u(k) = sin(2 pi k / 250) for k <= 250, then 0.8 sin(2 pi k / 250) + 0.2 sin(2 pi k / 25).
    """
    k = np.arange(start, start + n_samples, dtype=np.float64)
    slow = np.sin(2.0 * np.pi * k / 250.0)
    return np.where(k <= 250, slow, 0.8 * slow + 0.2 * np.sin(2.0 * np.pi * k / 25.0))


def test_sinusoid_sample(k: int) -> float:
    """One sample of eq. 11 (the plant simulator node steps one k at a time)."""
    return float(test_sinusoid(1, start=k)[0])


def noise_std(noise_db: float | None, signal_power: float = UNIFORM_INPUT_POWER) -> float:
    """Standard deviation of white Gaussian noise at ``noise_db`` relative to a signal.

    The paper adds "-10 dB" / "-20 dB" noise to the plant input without saying
    relative to what. We take it as the noise-to-signal power ratio against the
    training input u ~ U[-1, 1] (power 1/3): sigma^2 = 10^(dB/10) / 3, so -10 dB is
    sigma = 0.183 and -20 dB is sigma = 0.058. One sigma holds for the whole run,
    training and test, since the paper's figures show the test "with additive noise"
    too. ``None`` means no noise.
    """
    if noise_db is None:
        return 0.0
    return float(np.sqrt(signal_power * 10.0 ** (noise_db / 10.0)))


SIGNALS = ("paper", "uniform", "sinusoid", "steps")
#: "steps": each level U[-1, 1] held for this many samples (uniform, inclusive): a robot's usual excitation
STEP_HOLD = (10, 60)


class Excitation:
    """The input u(k) and the plant-input noise n(k), sample after sample.

    ``"paper"``: uniform random for ``train_samples``, then eq. 11 for
    ``test_samples`` (then exhausted); ``"uniform"`` / ``"sinusoid"``: one of the
    two forever; ``"steps"``: random levels held for STEP_HOLD samples, forever
    (the usual excitation of a joint: white noise barely moves a body with inertia).
    Values are drawn in blocks from two seeded streams (input, noise), and a block
    draw equals the same draws one by one, so the live plant simulator and the
    offline ``simulate`` produce identical data for the same seed.
    """

    block = 4096

    def __init__(
        self,
        seed: int,
        signal: str = "paper",
        train_samples: int = 50_000,
        test_samples: int = 600,
        noise_db: float | None = None,
        test_noise: bool = False,
        channel: int = 0,
    ) -> None:
        """``channel`` > 0: input i of a MIMO plant, its own random streams (channel 0 is the SISO
        excitation, unchanged) and its test sinusoid a quarter period (62 samples) later per channel,
        so the inputs of a test are not one and the same signal."""
        if signal not in SIGNALS:
            raise ValueError(f"signal must be one of {', '.join(SIGNALS)}, not {signal!r}")
        self.signal = signal
        self.train_samples = train_samples if signal == "paper" else (0 if signal == "sinusoid" else -1)
        self.test_samples = test_samples
        self.sigma = noise_std(noise_db)
        self.test_noise = test_noise
        streams = [seed] if channel == 0 else [seed, 2 + channel]  # [seed, 0 / 1] are channel 0's
        self._input_rng = np.random.default_rng([*streams, 0])
        self._noise_rng = np.random.default_rng([*streams, 1])
        self._test_shift = 62 * channel
        self._u = np.empty(0)
        self._noise = np.empty(0)
        self._offset = 0  # k of self._u[0]
        self._level, self._left = 0.0, 0  # "steps": the level held and for how many more samples

    @property
    def length(self) -> int | None:
        """Total samples, or None if endless."""
        return self.train_samples + self.test_samples if self.signal == "paper" else None

    @property
    def test_start(self) -> int | None:
        """k of the first test sample (None: no test phase)."""
        return self.train_samples if self.signal == "paper" else None

    def in_training(self, k: int) -> bool:
        return self.train_samples < 0 or k < self.train_samples

    def sample(self, k: int) -> tuple[float, float]:
        """(u(k), n(k)) for k = 0, 1, 2, ... (never more than a block backwards)."""
        if self.length is not None and k >= self.length:
            raise IndexError("the excitation is exhausted")
        while k >= self._offset + len(self._u):
            self._extend()
        if k < self._offset:
            raise IndexError(f"sample {k} was already discarded")
        return float(self._u[k - self._offset]), float(self._noise[k - self._offset])

    def series(self) -> tuple[np.ndarray, np.ndarray]:
        """All of a finite excitation at once."""
        if self.length is None:
            raise ValueError("an endless signal has no whole series")
        u, noise = self._draw(0, self.length)
        return u, noise

    def _extend(self) -> None:
        """Next block; an endless signal keeps only the previous block besides it."""
        start = self._offset + len(self._u)
        count = self.block if self.length is None else self.length - start
        u, noise = self._draw(start, count)
        if len(self._u) > self.block:
            self._offset += len(self._u) - self.block
            self._u, self._noise = self._u[-self.block :], self._noise[-self.block :]
        self._u = np.concatenate([self._u, u])
        self._noise = np.concatenate([self._noise, noise])

    def _draw(self, start: int, count: int) -> tuple[np.ndarray, np.ndarray]:
        k = np.arange(start, start + count)
        train = (k < self.train_samples) | (self.train_samples < 0)
        u = np.empty(count)
        u[train] = (
            self._steps(int(train.sum()))
            if self.signal == "steps"
            else uniform_input(int(train.sum()), self._input_rng)
        )
        test_k = k[~train] - max(self.train_samples, 0) + 1
        if len(test_k):
            u[~train] = test_sinusoid(len(test_k), start=int(test_k[0]) + self._test_shift)
        noise = self._noise_rng.normal(0.0, 1.0, count) * self.sigma
        if not self.test_noise:
            noise[~train] = 0.0
        return u, noise

    def _steps(self, count: int) -> np.ndarray:
        """The next ``count`` samples of random steps; the level held carries over from the last block."""
        out = np.empty(count)
        filled = 0
        while filled < count:
            if self._left == 0:
                self._level = float(self._input_rng.uniform(-1.0, 1.0))
                self._left = int(self._input_rng.integers(STEP_HOLD[0], STEP_HOLD[1] + 1))
            n = min(self._left, count - filled)
            out[filled : filled + n] = self._level
            self._left -= n
            filled += n
        return out


def point_to_point(
    rng: np.random.Generator,
    samples: int,
    period: float,
    centre: float = 0.0,
    amplitude: float = 1.0,
    speed: float = 2.0,
    dwell: tuple[float, float] = (0.2, 1.5),
) -> np.ndarray:
    """A positioning axis's setpoints: moves at ``speed`` (units/s) to random targets within centre +- amplitude,
    each held for a random dwell (s): how a robot drives an axis (ramps and rests, not white noise). The
    change alarm's excitation changes are other ``centre`` / ``amplitude`` / ``speed`` / ``dwell`` values."""
    out = np.empty(samples)
    position, k = centre, 0
    step = speed * period
    while k < samples:
        target = centre + amplitude * rng.uniform(-1.0, 1.0)
        moves = max(1, int(abs(target - position) / step))
        ramp = np.linspace(position, target, moves + 1)[1:]
        hold = np.full(max(1, int(rng.uniform(*dwell) / period)), target)
        piece = np.concatenate([ramp, hold])[: samples - k]
        out[k : k + len(piece)] = piece
        k += len(piece)
        position = target
    return out
