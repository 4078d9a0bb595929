"""The soak benchmark at CI size: every sample paired and recorded, memory flat."""

from __future__ import annotations

from pathlib import Path

import pytest

pytestmark = [pytest.mark.ros, pytest.mark.slow, pytest.mark.timeout(300)]

REPO = Path(__file__).resolve().parents[1]


def test_soak_at_ci_size(tmp_path: Path, domain: int) -> None:
    from soak import soak

    from lenn_ros.bag import read_run

    report = soak(25_000, str(tmp_path))  # the 10 000-deep queues fill in the first 60 %
    assert report["ok"], report
    run = read_run(report["bag"])
    assert len(run.u) == len(run.y_p) == 25_600
    # Bounded, not flat to the byte: unacknowledged messages of a lagging recorder sit in the
    # identifier's KEEP_LAST(10 000) writer queues (~2 x 10 000 x ~300 B). A leak of even
    # 1 KB per sample would add 10 MB over these 10 000 samples.
    assert report["rss_growth_kb_last_40_percent"] < 8_000, report
