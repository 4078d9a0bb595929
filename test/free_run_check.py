"""The check every identifier's free run must pass: compiled and through the Python path (the MLP's), on
the same model, the same outputs, clipping and first diverged sample. test_core (one output) and test_mimo
(several) both use it, so the two cannot drift apart."""

from __future__ import annotations

import numpy as np


def _clipped(identifier) -> list[int]:
    return [output.counters["clipped_free_run"] for output in getattr(identifier, "outputs", [identifier])]


def both_ways(identifier, u: np.ndarray, y: np.ndarray, start: int, monkeypatch) -> list[tuple]:
    """[(outputs, last_free_run, clipped per output)] compiled, then in Python; the patch is undone after."""
    from lenn_ros.core import free_run

    runs = []
    for compiled in (True, False):
        if not compiled:
            monkeypatch.setattr(free_run, "_compiled", free_run._python)
        before = _clipped(identifier)
        y_free = identifier.free_run(u, y, start)
        after = _clipped(identifier)
        runs.append((y_free, dict(identifier.last_free_run), [a - b for a, b in zip(after, before, strict=True)]))
    monkeypatch.undo()
    return runs


def assert_same_free_run(identifier, u: np.ndarray, y: np.ndarray, start: int, monkeypatch) -> tuple[np.ndarray, dict]:
    """Compiled == Python to 1e-12, with the same report and clipping; returns the compiled run and its report."""
    (fast, fast_info, fast_clipped), (slow, slow_info, slow_clipped) = both_ways(identifier, u, y, start, monkeypatch)
    np.testing.assert_allclose(fast, slow, rtol=0, atol=1e-12)
    assert fast_info == slow_info and fast_clipped == slow_clipped
    return fast, fast_info


def assert_same_divergence(identifier, u: np.ndarray, y: np.ndarray, start: int, monkeypatch) -> None:
    """An unstable model (the caller made it so) stops at the same sample both ways, NaN from there."""
    (fast, fast_info, _), (slow, slow_info, _) = both_ways(identifier, u, y, start, monkeypatch)
    assert fast_info["diverged_at"] is not None and fast_info["diverged_at"] == slow_info["diverged_at"]
    np.testing.assert_array_equal(np.isnan(fast), np.isnan(slow))
