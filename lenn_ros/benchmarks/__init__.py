"""The parts of ``lenn-ros bench``: offline costs (:mod:`.offline`) and ROS throughput (:mod:`.online`).

:mod:`lenn_ros.bench` runs them and formats the report; see bench/RESULTS.md.
"""
