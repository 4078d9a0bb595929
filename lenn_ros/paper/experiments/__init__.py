"""The experiments of ``lenn-ros reproduce --beyond``, one module per job.

- :mod:`.candidates`: the configurations tried beyond the paper's LeNN, and the winners;
- :mod:`.convergence`: learning curves and "samples to 1 dB";
- :mod:`.identification`: the per-example rows (paper networks, RLS, winner) over seeds;
- :mod:`.tracking`: a plant that changes mid-run, and how fast each rule recovers;
- :mod:`.report`: mean ± std over seeds and table cells, shared with ``reproduce``.

``lenn_ros.paper.beyond`` runs them and prints the tables.
"""
