"""Error measures: the one module that says how a model is scored."""

from __future__ import annotations

import math

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
        error = y - y_hat
        self.squared_error += error * error  # (not ** 2: a float power raises OverflowError where this is inf)

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


class ChannelsNMSE:
    """:class:`RunningNMSE` per output channel of a MIMO model, with one summary figure.

    The summary is the mean of the channels' linear NMSE, in dB: each channel is
    normalised by its own variance first, so a channel in volts does not drown one
    in millivolts (pooling the squared errors would).
    """

    def __init__(self, names: list[str] | tuple[str, ...]) -> None:
        self.names = tuple(names)
        self.channels = [RunningNMSE() for _ in self.names]

    def reset(self) -> None:
        for channel in self.channels:
            channel.reset()

    @property
    def count(self) -> int:
        return self.channels[0].count

    def add(self, y: np.ndarray, y_hat: np.ndarray) -> None:
        for channel, value, estimate in zip(self.channels, y, y_hat, strict=True):
            channel.add(float(value), float(estimate))

    def extend(self, y: np.ndarray, y_hat: np.ndarray) -> None:
        """Rows of samples (N, channels)."""
        y = np.asarray(y, dtype=np.float64).reshape(-1, len(self.channels))
        y_hat = np.asarray(y_hat, dtype=np.float64).reshape(-1, len(self.channels))
        for j, channel in enumerate(self.channels):
            channel.extend(y[:, j], y_hat[:, j])

    @property
    def channels_db(self) -> dict[str, float]:
        return {name: channel.nmse_db for name, channel in zip(self.names, self.channels, strict=True)}

    @property
    def nmse_db(self) -> float:
        if len(self.channels) == 1:  # (one channel's own figure, not back and forth through dB)
            return self.channels[0].nmse_db
        values = [10.0 ** (db / 10.0) for db in self.channels_db.values()]
        if not values or any(not np.isfinite(value) for value in values):
            return float("nan")
        mean = float(np.mean(values))
        return float(10.0 * np.log10(mean)) if mean > 0 else float("-inf")

    @property
    def rmse(self) -> float:
        if len(self.channels) == 1:
            return self.channels[0].rmse
        return float(np.sqrt(np.mean([channel.rmse**2 for channel in self.channels])))


def band_half_width(residuals: np.ndarray, level: float = 0.95) -> float:
    """Half-width of the two-sided ``level`` band of these residuals: their ``level`` quantile of |e|.

    Empirical, not 1.96 sigma: free-run errors are far from normal (a slow drift, a
    heavy tail where the model misses a transient), and a quantile covers what it
    says on the samples it came from whatever their distribution.
    """
    finite = np.abs(np.asarray(residuals, dtype=np.float64))
    finite = finite[np.isfinite(finite)]
    return float(np.quantile(finite, level)) if len(finite) else math.nan


def coverage(measured: np.ndarray, centre: np.ndarray, half_width: float | np.ndarray) -> float:
    """Fraction of the samples with a prediction (finite centre) that lie within centre ± half_width."""
    measured, centre = np.asarray(measured, dtype=np.float64), np.asarray(centre, dtype=np.float64)
    predicted = np.isfinite(centre)
    if not predicted.any():
        return math.nan
    inside = np.abs(measured[predicted] - centre[predicted]) <= np.broadcast_to(half_width, centre.shape)[predicted]
    return float(np.mean(inside))
