"""The soak benchmark at CI size: every sample paired and recorded, memory flat."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

pytestmark = [pytest.mark.ros, pytest.mark.slow, pytest.mark.timeout(300)]

REPO = Path(__file__).resolve().parents[1]


def test_soak_at_ci_size(tmp_path: Path, domain: int) -> None:
    sys.path.insert(0, str(REPO / "bench"))
    from soak import soak

    from lenn_ros.bag import read_run

    report = soak(20_000, str(tmp_path))
    assert report["ok"], report
    run = read_run(report["bag"])
    assert len(run.u) == len(run.y_p) == 20_600
    assert report["rss_growth_kb_per_100k_samples"] < 5_000, report
