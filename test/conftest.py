"""Fixtures shared by the tests that talk over DDS."""

from __future__ import annotations

from collections.abc import Iterator

import pytest


@pytest.fixture
def domain(monkeypatch: pytest.MonkeyPatch) -> Iterator[int]:
    """A ROS domain no concurrent test uses, discovery kept on this machine."""
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    import domain_coordinator

    with domain_coordinator.domain_id() as domain_id:
        monkeypatch.setenv("ROS_DOMAIN_ID", str(domain_id))
        yield domain_id


@pytest.fixture
def talker(domain: int):
    from rosutil import Talker

    t = Talker(domain)
    yield t
    t.close()
