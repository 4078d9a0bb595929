"""The paper and the simulators: what ``lenn-ros reproduce`` and the simulator nodes run.

- :mod:`.examples`: the paper's four examples (plants, structures, networks, presets);
- :mod:`.plants`, :mod:`.expression`: the simulated plants and user formulas, compiled;
- :mod:`.signals`: the excitation (training input, the eq. 11 test sinusoid, noise);
- :mod:`.complexity`: the networks' cost (Table I);
- :mod:`.robot`, :mod:`.physical`: the robot simulator's parts and its physical joint;
- :mod:`.evaluation`: the paper's protocol (simulate, train and test, least-squares floor);
- :mod:`.reproduce`, :mod:`.beyond`: ``lenn-ros reproduce`` and ``reproduce --beyond``;
- :mod:`.experiments`: the experiments behind ``--beyond`` and ``reproduce-mimo``.

The runtime (:mod:`lenn_ros.core`) never imports this subpackage.
"""
