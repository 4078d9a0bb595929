"""A progress bar on stderr for offline work longer than a few seconds (a long bag, a reproduction).

tqdm is the ``progress`` extra: without it the work goes on without a bar (a bar is no reason to
stop), said in one line when a bar was wanted. Off when asked (``--json``, a test).
"""

from __future__ import annotations

import sys
from typing import Any


class _NoBar:
    """What :func:`progress` returns without tqdm or when off: the same calls, doing nothing."""

    def update(self, count: int = 1) -> None:
        """Nothing to draw."""

    def close(self) -> None:
        """Nothing to close."""


def progress(total: int, enabled: bool, description: str, unit: str = "run") -> Any:
    """A bar of ``total`` ``unit`` on stderr when ``enabled``; else (or without tqdm) one that does nothing."""
    try:
        from tqdm import tqdm
    except ModuleNotFoundError:
        if enabled:
            print(
                f"{description}: no progress bar (tqdm is not installed: pip install 'lenn_ros[progress]')",
                file=sys.stderr,
            )
        return _NoBar()
    return tqdm(total=total, disable=not enabled, unit=unit, desc=description, file=sys.stderr)
