"""The session of stages: what every front-end (the node, evaluate, fit's bag reading, replay) runs halves through.

:class:`Session` composes the stages (see :mod:`lenn_ros.session.session`); the names below are what
the front-ends use.
"""

from lenn_ros.session.config import PAIRING_MODES, ParameterChange, SessionConfig, json_safe
from lenn_ros.session.hold import MAX_HELD
from lenn_ros.session.notices import SESSION_COUNTERS, Notice
from lenn_ros.session.session import Sample, Session

__all__ = [
    "MAX_HELD",
    "PAIRING_MODES",
    "SESSION_COUNTERS",
    "Notice",
    "ParameterChange",
    "Sample",
    "Session",
    "SessionConfig",
    "json_safe",
]
