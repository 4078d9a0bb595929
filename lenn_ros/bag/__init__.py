"""Run recordings as rosbag2 bags with MCAP storage, without needing a ROS install.

Why not rosbag2: the offline tools (``lenn-ros evaluate``, ``bag-info``, ``bag-repair``,
``import-csv``) must run where only pip is available, and a bag written here must open
in ``ros2 bag info`` / Foxglove on a full ROS 2 install. The modules:

* :mod:`~lenn_ros.bag.writer`: :class:`BagWriter` on the public ``mcap`` writer, with a
  bounded loss if the process is killed (the choice is explained there);
* :mod:`~lenn_ros.bag.reader`: :func:`iter_messages` / :func:`topic_types` for any type;
* :mod:`~lenn_ros.bag.scalars` and :mod:`~lenn_ros.bag.run`: numeric series decoded with
  numpy (:func:`read_run`, :func:`read_samples`);
* :mod:`~lenn_ros.bag.info`: :func:`bag_info`, with the messages lost per topic;
* :mod:`~lenn_ros.bag.repair`: :func:`recover` for a killed recorder's file;
* :mod:`~lenn_ros.bag.csv_import`: :func:`import_csv`.
"""

from lenn_ros.bag.csv_import import import_csv
from lenn_ros.bag.errors import BagError
from lenn_ros.bag.info import bag_info, sequence_gaps
from lenn_ros.bag.qos import default_qos, qos_from_profile
from lenn_ros.bag.reader import BagMessage, iter_messages, topic_types
from lenn_ros.bag.repair import RecoveryReport, recover
from lenn_ros.bag.run import RunData, SampleSeries, read_run, read_samples
from lenn_ros.bag.writer import DEFAULT_CHUNK_SIZE, BagWriter

__all__ = [
    "DEFAULT_CHUNK_SIZE",
    "BagError",
    "BagMessage",
    "BagWriter",
    "RecoveryReport",
    "RunData",
    "SampleSeries",
    "bag_info",
    "default_qos",
    "import_csv",
    "iter_messages",
    "qos_from_profile",
    "read_run",
    "read_samples",
    "recover",
    "sequence_gaps",
    "topic_types",
]
