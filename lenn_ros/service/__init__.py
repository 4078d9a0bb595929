"""The service layer: what every front-end (the nodes, ``evaluate``, ``fit``, ``replay``, the twin and
``load_model``) builds through, so that each rule is written once and offline equals live.

- :mod:`~lenn_ros.service.reading`: what is read from a recording (topics, fields, channel names,
  pairing, sample period), one way for every command, spelled like the node's parameters;
- :mod:`~lenn_ros.service.recording`: a recording to samples: every message of any rosbag2 bag,
  paired by the node's own session (:func:`~lenn_ros.service.recording.pair_raw`, the one pairing of raw
  topics), numbered as the node numbers them;
- :mod:`~lenn_ros.service.building`: parameters to an identifier (the node's factory, ``weights_in``,
  the params-file matcher, the configuration a bag recorded);
- :mod:`~lenn_ros.service.scoring`: a test part scored, one-step and in free run across breaks.

Nothing here knows ROS: the nodes hand it what they received.
"""


class RecordingError(ValueError):
    """A recording, or the configuration to read it with, that cannot be used; the message names the fix.

    Defined here, where nothing heavy is imported: the command line knows it without loading a reader.
    """
