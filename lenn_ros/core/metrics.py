"""Error measures: the one module that says how a model is scored."""

from __future__ import annotations

import numpy as np


def nmse(y: np.ndarray, y_hat: np.ndarray) -> float:
    """Normalised mean squared error of eq. 12 (linear scale).

    sum (y - y_hat)^2 / (N sigma^2), sigma^2 the variance of the plant output y over
    the same samples. A constant plant output has sigma^2 = 0: the NMSE is then
    undefined and reported as nan rather than a misleading number.
    """
    y = np.asarray(y, dtype=np.float64)
    y_hat = np.asarray(y_hat, dtype=np.float64)
    if y.shape != y_hat.shape or y.size == 0:
        raise ValueError(f"need two equal, non-empty series, got {y.shape} and {y_hat.shape}")
    variance = float(np.var(y))
    if variance == 0.0:
        return float("nan")
    return float(np.mean((y - y_hat) ** 2) / variance)


def nmse_db(y: np.ndarray, y_hat: np.ndarray) -> float:
    """NMSE in dB (10 log10), as the paper reports it; a perfect model gives -inf."""
    value = nmse(y, y_hat)
    with np.errstate(divide="ignore"):
        return float(10.0 * np.log10(value)) if np.isfinite(value) else value


def rmse(y: np.ndarray, y_hat: np.ndarray) -> float:
    """Root mean squared error, in the units of y."""
    y = np.asarray(y, dtype=np.float64)
    return float(np.sqrt(np.mean((y - np.asarray(y_hat, dtype=np.float64)) ** 2)))


class RunningNMSE:
    """NMSE accumulated sample by sample (Welford), for a live identifier.

    Gives the same value as :func:`nmse` over the same samples (to rounding),
    without keeping the samples: an identifier that runs for hours stays flat in memory.
    """

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self.count = 0
        self.mean = 0.0
        self.m2 = 0.0
        self.squared_error = 0.0

    def add(self, y: float, y_hat: float) -> None:
        self.count += 1
        delta = y - self.mean
        self.mean += delta / self.count
        self.m2 += delta * (y - self.mean)
        self.squared_error += (y - y_hat) ** 2

    def extend(self, y: np.ndarray, y_hat: np.ndarray) -> None:
        """Many samples at once (Chan's merge): the same state as :meth:`add` per sample, to rounding."""
        y = np.asarray(y, dtype=np.float64)
        if y.size == 0:
            return
        count = y.size
        mean = float(np.mean(y))
        m2 = float(np.sum((y - mean) ** 2))
        total = self.count + count
        delta = mean - self.mean
        self.m2 += m2 + delta * delta * self.count * count / total
        self.mean += delta * count / total
        self.count = total
        self.squared_error += float(np.sum((y - np.asarray(y_hat, dtype=np.float64)) ** 2))

    @property
    def nmse_db(self) -> float:
        if self.count == 0 or self.m2 == 0.0:
            return float("nan")
        value = self.squared_error / self.m2
        return float(10.0 * np.log10(value)) if value > 0 else float("-inf")

    @property
    def rmse(self) -> float:
        return float(np.sqrt(self.squared_error / self.count)) if self.count else float("nan")
