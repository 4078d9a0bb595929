"""When held pairs may be learnt, and whether pairing by sequence number can work at all.

A live session holds the pairs it forms until two things are true:

- every output that asked for readers (``wait_for_*_subscribers``) has them: the outputs
  are VOLATILE, so what is published before a reader matched is lost to it;
- in ``sequence`` pairing, the graph has shown who publishes u and y_p. Equal indices
  from two nodes are not one sample, so two disjoint sets of publishers refuse the
  pairing (with the fix named), and one node publishing both vouches for it. Node names
  arrive with discovery, a moment after the first messages can; if they never come
  (a publisher that left before they did), the pairs are released after a grace with a
  warning: the session's skew check on source times still refuses halves published apart.

Nothing here reads the graph: the node hands over what it saw (publishers per input,
matched readers per output) and the monotonic time, so every decision is tested
without DDS. The decisions end in :class:`~lenn_ros.session.Session` (release,
refusal, notices), which owns one :class:`HoldGate` while it holds.
"""

from __future__ import annotations

from dataclasses import dataclass, field

#: Seconds of discovery before a missing reader or publisher name is said (and, for the
#: publishers' names, before pairing by sequence number goes ahead unverified).
START_GRACE = 5.0

#: What a publisher is in the graph: (namespace, node name).
NodeName = tuple[str, str]


def node_list(nodes: set[NodeName] | frozenset[NodeName]) -> str:
    """'/ns/node, /other' for a notice."""
    return ", ".join(f"{namespace.rstrip('/')}/{node}" for namespace, node in sorted(nodes))


@dataclass
class HoldGate:
    """The hold's state: what the outputs wait for and what the graph has shown so far."""

    pairing: str
    wanted: dict[str, int]  # output -> readers it waits for (0: none)
    u_name: str = "u"
    y_name: str = "y_p"
    grace: float = START_GRACE
    publishers_known: bool = False  # both inputs' publishers seen with their node names
    _unverified_since: float | None = field(default=None, repr=False)
    _holding_since: float | None = field(default=None, repr=False)

    @property
    def needed(self) -> bool:
        """Whether anything must be waited for at all (else the session never holds)."""
        return any(count > 0 for count in self.wanted.values()) or self.pairing == "sequence"

    def publishers(self, seen: dict[str, set[NodeName]]) -> tuple[bool, str | None]:
        """The publishers of each input ('u', 'y') the graph shows now: (decided, the refusal text or None).

        Not decided while an input has no publisher or a name is not known yet (rmw reports
        ``_NODE_NAME_UNKNOWN_`` until discovery completes).
        """
        u, y = seen.get("u", set()), seen.get("y", set())
        known = all(not name.startswith("_NODE_") for _, name in u | y)
        if not (u and y and known):
            return False, None
        self.publishers_known = True
        if self.pairing != "sequence" or not u.isdisjoint(y):
            return True, None
        return True, (
            f"{self.u_name} (from {node_list(u)}) and {self.y_name} (from {node_list(y)}) come from different "
            "nodes: pairing 'sequence' needs one lockstep publisher of both, nothing is paired; use "
            "pairing:=sample sample_period:=T (or pairing:=stamp)"
        )

    def readers_missing(self, readers: dict[str, int]) -> list[str]:
        """'y_hat has 0 of 1 readers' for every output still short of its readers."""
        return [
            f"{output} has {readers.get(output, 0)} of {wanted} readers"
            for output, wanted in self.wanted.items()
            if readers.get(output, 0) < wanted
        ]

    def vouched(self, now: float) -> tuple[bool, str | None]:
        """Whether the publishers allow learning now, and the one-time 'unverified' text when the grace ran out."""
        if self.pairing != "sequence" or self.publishers_known:
            return True, None
        if self._unverified_since is None:
            self._unverified_since = now
        if now - self._unverified_since < self.grace:
            return False, None
        self.publishers_known = True
        return True, (
            f"the publishers of {self.u_name} and {self.y_name} could not be told from the graph within "
            f"{self.grace:.0f} s: pairing by sequence number unverified (pairs published apart are still refused)"
        )

    def waiting_text(self, held: int, readers: dict[str, int], now: float) -> str | None:
        """What the held pairs wait for, once the grace has passed (None before)."""
        if self._holding_since is None:
            self._holding_since = now
        if now - self._holding_since < self.grace:
            return None
        waiting = self.readers_missing(readers) or ["the graph to show who publishes u and y_p"]
        return (
            f"{held} pairs held, not learnt, for {now - self._holding_since:.0f} s: waiting until "
            f"{'; '.join(waiting)} (lower wait_for_*_subscribers or start the readers)"
        )
