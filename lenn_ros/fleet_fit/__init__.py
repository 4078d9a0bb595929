"""``lenn-ros fit-fleet``: one model per entry of a fleet's logs, the entries fitted side by side on a Dask cluster.

An entry (a robot, a joint) is one or several records and fit's flags (:mod:`~lenn_ros.fleet_fit.manifest`).
Each is fitted on a worker by ``lenn-ros fit``'s own in-process entry point, with the argv a serial
``lenn-ros fit`` of the entry would get (:mod:`~lenn_ros.fleet_fit.task`), so a model is the serial one,
bit for bit. The models land in MODELS/NAME/ only when whole (:mod:`~lenn_ros.fleet_fit.store`); the
run submits, collects and summarises (:mod:`~lenn_ros.fleet_fit.run`). The front-end hands in fit's
parser: nothing here imports the command line.
"""
