"""FirstAnswerHold: a lockstep node's first answer waits until the readers its graph knows of are matched."""
from __future__ import annotations

import time

import pytest


@pytest.fixture
def nodes(in_ros_domain):
    import rclpy

    rclpy.init()
    made = []

    def make(name):
        made.append(rclpy.create_node(name))
        return made[-1]

    yield make
    for n in made:
        n.destroy_node()
    rclpy.try_shutdown()


def _until(cond, timeout=10.0):
    end = time.monotonic() + timeout
    while not cond():
        assert time.monotonic() < end, "timed out"
        time.sleep(0.01)


def test_a_reader_the_graph_lists_but_the_writer_has_not_matched_holds_the_first_answer_until_the_hold_ends(nodes):
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from std_msgs.msg import Empty

    from humfall_ros.nodes.common import QOS_TICK_WRITER, FirstAnswerHold

    writer = nodes("writer")
    pub = writer.create_publisher(Empty, "tick_topic", QOS_TICK_WRITER)
    assert FirstAnswerHold(writer, hold_s=5.0).ready([pub])  # nobody listed: nothing to wait for
    # a transient-local reader never matches a volatile writer: listed by the graph, never matched
    nodes("stranger").create_subscription(Empty, "tick_topic", lambda m: None, QoSProfile(
        depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL))
    _until(lambda: writer.count_subscribers("/tick_topic") == 1)
    hold = FirstAnswerHold(writer, hold_s=0.5)
    t0 = time.monotonic()
    assert not hold.ready([pub])
    time.sleep(0.2)
    assert not hold.ready([pub]) and not hold.released
    _until(lambda: hold.ready([pub]), timeout=5.0)
    assert time.monotonic() - t0 >= 0.5 and hold.released
    assert hold.ready([pub])  # released for good


def test_a_matched_reader_releases_the_first_answer_at_once(nodes):
    from std_msgs.msg import Empty

    from humfall_ros.nodes.common import QOS_RELIABLE, QOS_TICK_WRITER, FirstAnswerHold

    writer = nodes("writer")
    pub = writer.create_publisher(Empty, "tick_topic", QOS_TICK_WRITER)
    nodes("reader").create_subscription(Empty, "tick_topic", lambda m: None, QOS_RELIABLE)
    _until(lambda: writer.count_subscribers("/tick_topic") == 1 and pub.get_subscription_count() == 1)
    hold = FirstAnswerHold(writer, hold_s=60.0)
    assert hold.ready([pub]) and hold.released
