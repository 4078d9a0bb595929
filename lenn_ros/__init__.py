"""lenn_ros: online identification of nonlinear plants from ROS 2 topics (LeNN, MLP).

The one name for Python users is :func:`load_model` (see :mod:`lenn_ros.model`):
``lenn_ros.load_model(DIR)`` runs what ``lenn-ros fit -o DIR`` wrote, without ROS. It is
imported on first use, so ``import lenn_ros`` (every node does) stays light.
"""

from __future__ import annotations

from typing import Any

__all__ = ["load_model"]


def __getattr__(name: str) -> Any:
    if name == "load_model":
        from lenn_ros.model import load_model

        return load_model
    raise AttributeError(f"module 'lenn_ros' has no attribute {name!r}")
