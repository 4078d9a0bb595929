"""The identifier node, unchanged, run under cProfile (this thread's CPU time).

    python bench/profile_node.py OUT.prof --ros-args -p example:=1 ...

Used by ``bench/speed.py`` to split the node's per-message CPU between the rclpy
executor (building the wait set, taking and dispatching messages) and the node's own
callbacks. The clock is ``time.thread_time``: a node blocked waiting for messages
costs nothing, so the profile shows where the CPU goes, not where the time passes.
"""

from __future__ import annotations

import cProfile
import sys
import time


def main() -> int:
    if len(sys.argv) < 2:
        print("usage: python bench/profile_node.py OUT.prof [--ros-args ...]", file=sys.stderr)
        return 2
    output = sys.argv[1]
    from lenn_ros.nodes import identifier

    profiler = cProfile.Profile(time.thread_time)
    profiler.enable()
    try:
        code = identifier.main([sys.argv[0], *sys.argv[2:]], exit_process=False)  # (the profile is written after)
    finally:
        profiler.disable()
        profiler.dump_stats(output)
    return int(code or 0)


if __name__ == "__main__":
    sys.exit(main())
