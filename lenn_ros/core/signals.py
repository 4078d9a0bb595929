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
