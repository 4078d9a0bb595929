"""Soak run: a long online identification through the live nodes, checked end to end.

Runs plant_simulator (lockstep) + identifier + recorder for N samples (default 10^6,
about 20 minutes on 2 cores), then checks and prints: every sample paired, none lost,
duplicated or stale; the bag holds exactly N u and N y_p messages (read back by the
independent `mcap` reader); the identifier's resident memory at 10 % of the run vs at
the end (flat: no growth per sample). The first 60 % of the run are left out of the
memory figure: the RELIABLE queues keep the last topics.DATA_DEPTH (10 000) messages of
each topic, and filling them is growth up to a ceiling, not a leak. The same ceiling
lets memory move by a few MB later when a lagging recorder leaves messages
unacknowledged; a leak shows as growth that goes on with the number of samples.

    python bench/soak.py                 # 10^6 samples
    python bench/soak.py --samples 25000 # what CI runs (test/test_soak.py)
"""

from __future__ import annotations

import argparse
import json
import sys

from lenn_ros.demo import run_demo


def soak(samples: int, output: str) -> dict:
    result = run_demo(example=1, network="lenn", train_samples=samples, test_samples=600, output=output)
    counters = result["live"]["counters"]
    topics = result["bag_info"]["topics"]
    total = samples + 600
    rss = [kb for _, kb in result["identifier_rss_kb"]]
    early = rss[(len(rss) * 6) // 10] if rss else 0
    growth = (rss[-1] - early) if rss else 0
    report = {
        "samples": total,
        "seconds": result["seconds"],
        "samples_per_s": round(total / result["seconds"]),
        "paired": counters["paired"],
        "lost": counters["lost"],
        "duplicates": counters["duplicates"],
        "stale": counters["stale"],
        "unpaired": counters["unpaired"],
        "bag_u": topics["/u"]["count"],
        "bag_y_p": topics["/y_p"]["count"],
        "bag_y_hat": topics["/y_hat"]["count"],
        "rss_kb_at_60_percent": early,
        "rss_kb_at_end": rss[-1] if rss else 0,
        "rss_growth_kb_last_40_percent": growth,
        "rss_growth_kb_per_100k_samples": round(growth / (0.4 * total) * 1e5, 1) if rss else None,
        "nmse_db": result["live"]["phase_nmse_db"],
        "bag": result["bag"],
    }
    report["ok"] = (
        report["paired"] == total
        and report["lost"] == report["duplicates"] == report["stale"] == report["unpaired"] == 0
        and report["bag_u"] == report["bag_y_p"] == total
    )
    return report


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=1_000_000)
    parser.add_argument("--output", default="soak_output")
    args = parser.parse_args()
    report = soak(args.samples, args.output)
    print(json.dumps(report, indent=1))
    return 0 if report["ok"] else 1


if __name__ == "__main__":
    sys.exit(main())
