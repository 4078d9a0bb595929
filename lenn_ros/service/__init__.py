"""The service layer: what every front-end (the nodes, ``evaluate``, ``fit``, ``replay``, the twin and
``load_model``) builds through, so that each rule is written once and offline equals live.

- :mod:`~lenn_ros.service.reading`: what is read from a recording (topics, fields, channel names,
  pairing, sample period), one way for every command, spelled like the node's parameters;
- :mod:`~lenn_ros.service.recording`: a recording to samples: every message of any rosbag2 bag,
  paired by the node's own session (:func:`~lenn_ros.service.recording.pair_raw`, the one pairing of raw
  topics), numbered as the node numbers them;
- :mod:`~lenn_ros.service.params`: which parameters a params file gives a node (rcl's matching rules,
  the one matcher: the node's warning, every offline reader);
- :mod:`~lenn_ros.service.building`: parameters to an identifier (the one factory, any number of
  channels; ``weights_in``; the configuration a bag recorded);
- :mod:`~lenn_ros.service.scoring`: a test part scored, one-step and in free run across breaks;
- :mod:`~lenn_ros.service.evaluation`: a recording evaluated offline (``evaluate``), the node's session
  over it.

Nothing here knows ROS: the nodes hand it what they received.
"""


class RecordingError(ValueError):
    """A recording, or the configuration to read it with, that cannot be used; the message names the fix.

    Defined here, where nothing heavy is imported: the command line knows it without loading a reader.
    """
