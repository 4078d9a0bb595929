"""ament_python package that is also a plain pip package (see README, "Install")."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = "lenn_ros"
# Optional features, each its own extra; the code says which extra to install when one is missing
# (lenn_ros.errors.require_extra for plots, lenn_ros.paper.experiments.report.progress for bars).
PLOT = ["matplotlib>=3.8"]  # --plot, the demo's figure (lenn_ros.plotting)
PROGRESS = ["tqdm>=4.66"]  # progress bars of reproduce / reproduce-mimo / --beyond
DOCS = ["mkdocs==1.6.1"]  # the site in docs/ (make docs: mkdocs build --strict)
# lenn-ros fit-fleet: the entries fitted on a Dask cluster (dask[distributed], named as the two it installs)
FLEET = ["dask>=2024.1", "distributed>=2024.1"]

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(include=[PACKAGE, f"{PACKAGE}.*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", sorted(glob("config/*.yaml"))),
        (f"share/{PACKAGE}/launch", sorted(glob("launch/*.launch.py"))),
    ],
    python_requires=">=3.11",
    install_requires=[
        "numpy>=1.26",
        "numba>=0.59",
        "rosbags>=0.11",  # typestore (CDR, msgdefs), QoS types: public API only
        "mcap>=1.6",  # lenn_ros.bag writes through mcap.writer.Writer (flush() since 1.6), repairs with StreamReader
        # lenn_ros.bag.scalars decompresses MCAP chunks itself (the fast path): imported directly,
        # so declared here, not only through mcap's own requirements
        "zstandard>=0.22",
        "lz4>=4",
        "pyyaml>=6",
        "threadpoolctl>=3",  # fit: one BLAS thread for its thousands of small products
    ],
    extras_require={
        # rclpy and its middleware as pip wheels, for machines without a ROS 2 install.
        # On a full ROS 2 Jazzy install these come from apt; do not install this extra there.
        "ros": [
            "ros-jazzy-rclpy",
            "ros-jazzy-std-msgs",
            "ros-jazzy-sensor-msgs",
            "ros-jazzy-geometry-msgs",
            "ros-jazzy-diagnostic-msgs",
            "ros-jazzy-rmw-fastrtps-cpp",
            "ros-jazzy-domain-coordinator",
        ],
        # peer comparison only (bench/peer_narx.py): SysIdentPy's FROLS polynomial NARX.
        # It pins numpy < 2.4 (pip downgrades numpy when this extra is installed).
        "bench": ["sysidentpy>=0.9"],
        "plot": PLOT,
        "progress": PROGRESS,
        "docs": DOCS,
        "fleet": FLEET,
        # the tests draw plots, build the site and run a fleet on a cluster, so they need those extras too
        "test": PLOT
        + PROGRESS
        + FLEET
        + DOCS
        + [
            "pytest>=8",
            "pytest-timeout>=2.3",
            "mcap>=1.2",
            "mcap-ros2-support>=0.5",
            "ruff>=0.6",
            "colcon-common-extensions>=0.3",
        ],
    },
    zip_safe=True,
    maintainer="lenn_ros developers",
    maintainer_email="dev@lenn-ros.local",
    description="Online LeNN / MLP identification of nonlinear dynamic systems for ROS 2",
    license="Apache-2.0",
    tests_require=["pytest"],
    entry_points={
        "console_scripts": [
            "lenn-ros = lenn_ros.cli:main",
            "identifier = lenn_ros.nodes.identifier:main",
            "fleet = lenn_ros.nodes.fleet:main",
            "plant_simulator = lenn_ros.nodes.plant_simulator:main",
            "recorder = lenn_ros.nodes.recorder:main",
            "replay = lenn_ros.nodes.replay:main",
            "robot_controller = lenn_ros.nodes.robot_controller:main",
            "robot_simulator = lenn_ros.nodes.robot_simulator:main",
            "twin = lenn_ros.nodes.twin:main",
        ],
    },
)
