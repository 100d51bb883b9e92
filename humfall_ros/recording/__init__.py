"""humfall_ros.recording: MCAP bags with ROS 2 schemas, their reader, summaries and plots.

Public API (what the recorder node, the ``humfall`` CLI and the launcher use):

- ``BagWriter``            raw CDR messages into MCAP with ``ros2msg`` schemas (writer.py)
- ``bag_info(path)``       per-topic counts/types/times/rates and holes (missing stamps); finalized or
                           ``kill -9``-cut bags
- ``read_messages(path)``  decoded messages, streaming (works without footer)
- ``recover(path)``        finalized copy of a cut-off bag
- ``info_main(path)``      ``humfall bag info``
- ``plot_main(path, out_dir=None)`` / ``plot_run(bag, out_dir)``  ``humfall bag plot`` / end of run

``path`` may be a bag file or a run folder holding ``bag.mcap``. Plotting imports
matplotlib only when called.
"""
from humfall_ros.recording.reader import (DecodeErrors, bag_info, iter_raw, read_messages,  # noqa: F401
                                          recover, resolve_bag)
from humfall_ros.recording.summary import info_main  # noqa: F401
from humfall_ros.recording.writer import BAG_FILE, STATS_FILE, BagWriter  # noqa: F401


def plot_run(bag_path, out_dir):
    """See ``humfall_ros.recording.plots.plot_run``."""
    from humfall_ros.recording.plots import plot_run as _plot_run

    return _plot_run(bag_path, out_dir)


def plot_main(path, out_dir=None) -> int:
    """See ``humfall_ros.recording.plots.plot_main``."""
    from humfall_ros.recording.plots import plot_main as _plot_main

    return _plot_main(path, out_dir)
