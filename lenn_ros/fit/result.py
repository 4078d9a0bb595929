"""What ``fit`` made of each output: :class:`OutputFit`, the record the procedure, scoring and export share.

A module of its own so that the procedure that makes it, the scoring of the test part and
the export of the model read it without importing each other.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from lenn_ros.fit.record import Record
from lenn_ros.fit.selection import Candidate
from lenn_ros.fit.termmodel import Layout, TermModel


@dataclass
class OutputFit:
    """What the selection made of one output: its view of the training samples, candidates and choice."""

    name: str
    record: Record
    layout: Layout
    candidates: list[Candidate]
    chosen: Candidate
    refinement: dict[str, Any]
    warnings: list[str] = field(default_factory=list)
    columns: list[int] = field(default_factory=list)  # the view's columns in [y_0.., u_0..]
    #: an output read as its absolute value: what the procedure's fit of its signed record found and did
    sign: dict[str, Any] | None = None
    delays: tuple[int, ...] = ()  # dead time of each column after the output, in samples (() or 0: none)

    @property
    def model(self) -> TermModel:
        return self.chosen.model
