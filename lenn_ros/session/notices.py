"""What the session must tell the user, as one-line notices, and the counters beside them.

Nothing here knows ROS: the node logs each :class:`Notice` (throttled per kind and subject),
``evaluate`` lists them. A drop that may go on for hours is said at its first occurrence and
then each time its count doubles (:meth:`Notices.doubling`), a handful of lines a run with
the count, which ``status`` carries anyway.
"""

from __future__ import annotations

from dataclasses import dataclass

#: Counters every session keeps (the stages add theirs: pairing, merging, the model).
SESSION_COUNTERS = (
    "u_messages", "y_messages", "nan", "out_of_range", "clipped",
    "no_sequence", "misaligned", "refused", "lone_u", "lone_y", "clock_offset", "held_overflow", "shed",
    "field_errors", "warm_up_discarded", "change_alarms", "test_start_late", "silences",
)  # fmt: skip
#: Notices kept when nobody reads them (the newest win).
KEPT = 1000


@dataclass(frozen=True)
class Notice:
    """Something the user must hear about, in one line; ``kind`` (and ``subject``) select its throttle.

    ``subject``: what the notice is about where one kind concerns several things (a topic):
    a stale /robot/cmd1 at start-up must not silence a stale /robot/right seconds later.
    """

    kind: str
    text: str
    subject: str = ""


class Notices:
    """The notices said so far and not yet taken, and the counters of the session's stages."""

    def __init__(self) -> None:
        self.counters: dict[str, int] = dict.fromkeys(SESSION_COUNTERS, 0)
        self._notices: list[Notice] = []
        self._said_at_count: dict[str, int] = {}  # kinds said when their count doubles: the count then

    def say(self, kind: str, text: str, subject: str = "") -> None:
        self._notices.append(Notice(kind, text, subject))
        if len(self._notices) > KEPT:  # nobody is reading: keep the newest
            del self._notices[: KEPT // 2]

    def doubling(self, kind: str, count: int, text: str) -> None:
        """Say a drop that may go on for hours at its first occurrence, then each time its count doubles.

        Rate-limited without a clock (the offline path has none worth trusting).
        """
        said = self._said_at_count.get(kind)
        if said is None or count >= 2 * said:
            self._said_at_count[kind] = count
            self.say(kind, text)

    def take(self) -> list[Notice]:
        notices, self._notices = self._notices, []
        return notices
