"""The recorder as a real process against a real publisher (in-process rclpy, own domain).

How a test knows the recorder is listening before it publishes counted messages:
it waits until ``publisher.get_subscription_count()`` shows the recorder's
subscription (the recorder is the only other participant in the test's domain;
on ``/clock`` it has two, its time source and its recording subscription).
Once a reliable writer has matched the reader, every message published after
that is delivered (deep queues on both sides). The latched topic is the
exception on purpose: it is published *before* the recorder starts and must
still arrive through transient-local durability.
"""
from __future__ import annotations

import json
import pathlib
import signal
import subprocess
import sys
import time

import pytest

rclpy = pytest.importorskip("rclpy")

from builtin_interfaces.msg import Time  # noqa: E402
from geometry_msgs.msg import Point  # noqa: E402
from humfall_interfaces.msg import CentroidalState, FallEvent  # noqa: E402
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from rosgraph_msgs.msg import Clock  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from std_msgs.msg import Int32, String  # noqa: E402
from visualization_msgs.msg import Marker, MarkerArray  # noqa: E402

from humfall_ros.recording import reader  # noqa: E402

RELIABLE = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE, history=HistoryPolicy.KEEP_LAST)
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL, history=HistoryPolicy.KEEP_LAST)
JOINTS = [f"j{i}" for i in range(30)]


class PubGraph:
    """An rclpy context of its own in this process, for publishers."""

    def __init__(self):
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx)
        self.node = rclpy.create_node("recorder_test_pub", context=self.ctx)

    def pub(self, cls, topic, qos=RELIABLE):
        return self.node.create_publisher(cls, topic, qos)

    @staticmethod
    def wait_matched(pub, n=1, timeout=20.0):
        end = time.monotonic() + timeout
        while pub.get_subscription_count() < n:
            if time.monotonic() > end:
                raise TimeoutError(f"recorder did not subscribe to {pub.topic_name}")
            time.sleep(0.02)

    def close(self):
        self.node.destroy_node()
        rclpy.shutdown(context=self.ctx)


@pytest.fixture
def graph(in_ros_domain):
    g = PubGraph()
    yield g
    g.close()


def start_recorder(env, out: pathlib.Path, *params: str) -> subprocess.Popen:
    args = [sys.executable, "-m", "humfall_ros.nodes.recorder", "--ros-args",
            "-p", f"output_dir:={out}", "-p", "scenario:=test"]
    for p in params:
        args += ["-p", p]
    log = open(out.parent / f"{out.name}.log", "wb")  # noqa: SIM115 - closed with the process
    return subprocess.Popen(args, env=env, stdout=log, stderr=subprocess.STDOUT)


def stop(proc: subprocess.Popen, sig=signal.SIGINT, timeout=20.0) -> int:
    proc.send_signal(sig)
    try:
        return proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        raise


def log_tail(out: pathlib.Path) -> str:
    p = out.parent / f"{out.name}.log"
    return p.read_text(errors="replace")[-3000:] if p.exists() else ""


def joint_state(i: int) -> JointState:
    # Empty velocity on purpose: FastCDR pads empty float64 sequences; every reader must cope.
    return JointState(name=JOINTS, position=[i + 0.001 * k for k in range(len(JOINTS))],
                      velocity=[], effort=[float(i)] * len(JOINTS))


def centroidal(i: int) -> CentroidalState:
    m = CentroidalState()
    m.header.stamp = Time(sec=100, nanosec=i * 1000)
    m.com.x, m.com.z = 0.01 * i, 0.8
    m.lean_angle = 0.001 * i
    m.support_polygon = [Point(x=0.1, y=0.1), Point(x=-0.1, y=0.1), Point(x=-0.1, y=-0.1)]
    m.left_contact = True
    return m


def markers(i: int) -> MarkerArray:
    return MarkerArray(markers=[Marker(ns="t", id=i, points=[Point(x=float(i))]),
                                Marker(ns="t", id=i + 1000, text=f"m{i}")])


def test_records_every_topic_without_loss(graph, ros_env, tmp_path):
    out = tmp_path / "run"
    counts = {"/chatter": 200, "/joint_states": 300, "/centroidal_state": 300, "/markers": 50,
              "/fall_event": 1, "/late": 100}
    # Latched before the recorder exists: only transient-local durability can bring it in.
    fall = graph.pub(FallEvent, "fall_event", LATCHED)
    fall.publish(FallEvent(reason="latched before recording", lean_angle=0.5))

    t_start = time.monotonic()
    rec = start_recorder(ros_env, out)
    try:
        clock = graph.pub(Clock, "/clock")
        pubs = {t: graph.pub(cls, t) for t, cls in (
            ("/chatter", String), ("/joint_states", JointState),
            ("/centroidal_state", CentroidalState), ("/markers", MarkerArray))}
        graph.wait_matched(clock, 2)   # the recorder's time source + its recording subscription
        for p in pubs.values():
            graph.wait_matched(p)
        sim_ns = 100 * 10**9
        clock.publish(Clock(clock=Time(sec=100)))
        published_clock = 1
        for i in range(300):
            sim_ns += 2_000_000
            clock.publish(Clock(clock=Time(sec=sim_ns // 10**9, nanosec=sim_ns % 10**9)))
            published_clock += 1
            pubs["/joint_states"].publish(joint_state(i))
            pubs["/centroidal_state"].publish(centroidal(i))
            if i < counts["/chatter"]:
                pubs["/chatter"].publish(String(data=f"hello {i}"))
            if i % 6 == 0:
                pubs["/markers"].publish(markers(i))
            time.sleep(0.001)
        counts["/clock"] = published_clock
        # A topic that only appears a couple of seconds into the recording.
        time.sleep(max(0.0, 2.0 - (time.monotonic() - t_start)))
        late = graph.pub(Int32, "late")
        graph.wait_matched(late)
        for i in range(counts["/late"]):
            late.publish(Int32(data=i))
        time.sleep(1.0)   # let the last ones arrive before we stop the recorder
        assert rec.poll() is None, log_tail(out)
        rc = stop(rec, signal.SIGINT)
    finally:
        if rec.poll() is None:
            rec.kill()
    assert rc == 0, log_tail(out)

    info = reader.bag_info(out)
    assert info["finalized"] and not info["truncated"]
    recorded = {t["topic"]: t["count"] for t in info["topics"]}
    for topic, n in counts.items():
        assert recorded.get(topic) == n, (topic, recorded.get(topic), n, log_tail(out))
    types = {t["topic"]: t["type"] for t in info["topics"]}
    assert types["/centroidal_state"] == "humfall_interfaces/msg/CentroidalState"
    assert types["/markers"] == "visualization_msgs/msg/MarkerArray"

    # recording_stats.json agrees with the bag
    stats = json.loads((out / "recording_stats.json").read_text())
    assert stats["finalized"] is True
    assert {t["topic"]: t["count"] for t in stats["topics"]} == recorded
    fall_qos = next(t["qos"] for t in stats["topics"] if t["topic"] == "/fall_event")
    assert fall_qos["durability"] == "transient_local"

    # sim-time log times: every message is stamped with a /clock value we sent (or 0 before it)
    last_clock = sim_ns
    for raw in reader.iter_raw(out, ["/joint_states", "/late"]):
        assert raw.log_time == 0 or 100 * 10**9 <= raw.log_time <= last_clock
    assert info["end_ns"] >= 100 * 10**9 and info["end_ns"] <= last_clock

    check_mcap_ros2(out / "bag.mcap", counts)
    check_rosbags(out / "bag.mcap", counts)


def check_mcap_ros2(bag: pathlib.Path, counts: dict[str, int]) -> None:
    from mcap_ros2.reader import read_ros2_messages

    by_topic: dict[str, list] = {}
    for m in read_ros2_messages(str(bag), topics=list(counts)):
        by_topic.setdefault(m.channel.topic, []).append(m.ros_msg)
    assert {t: len(v) for t, v in by_topic.items()} == counts
    cs = by_topic["/centroidal_state"]
    assert [round(m.com.x, 9) for m in cs] == [round(0.01 * i, 9) for i in range(300)]
    assert cs[7].header.stamp.nanosec == 7000 and len(cs[7].support_polygon) == 3
    assert cs[7].support_polygon[1].x == pytest.approx(-0.1)
    js = by_topic["/joint_states"]
    assert list(js[5].name) == JOINTS and js[5].position[3] == pytest.approx(5.003)
    ma = by_topic["/markers"]
    assert [m.markers[0].id for m in ma] == list(range(0, 300, 6))
    assert ma[2].markers[1].text == "m12" and ma[2].markers[0].points[0].x == 12.0
    assert by_topic["/fall_event"][0].reason == "latched before recording"
    assert [m.data for m in by_topic["/late"]] == list(range(100))
    assert [m.data for m in by_topic["/chatter"]][:3] == ["hello 0", "hello 1", "hello 2"]


def check_rosbags(bag: pathlib.Path, counts: dict[str, int]) -> None:
    from rosbags.highlevel import AnyReader

    by_topic: dict[str, list] = {}
    with AnyReader([bag]) as r:
        conns = [c for c in r.connections if c.topic in counts]
        for conn, _ts, raw in r.messages(connections=conns):
            by_topic.setdefault(conn.topic, []).append(r.deserialize(raw, conn.msgtype))
        fall_conn = next(c for c in r.connections if c.topic == "/fall_event")
        assert fall_conn.ext.offered_qos_profiles[0].durability.name == "TRANSIENT_LOCAL"
    assert {t: len(v) for t, v in by_topic.items()} == counts
    cs = by_topic["/centroidal_state"]
    assert cs[42].com.x == pytest.approx(0.42) and cs[42].lean_angle == pytest.approx(0.042)
    assert cs[42].left_contact is True and len(cs[42].support_polygon) == 3
    ma = by_topic["/markers"]
    assert ma[3].markers[0].id == 18 and ma[3].markers[1].text == "m18"
    js = by_topic["/joint_states"]
    assert js[299].effort[0] == 299.0 and list(js[0].name) == JOINTS


def test_kill9_keeps_what_was_flushed(graph, ros_env, tmp_path):
    """Messages published > 1.5 s before a kill -9 are in the bag and recoverable."""
    out = tmp_path / "run"
    rec = start_recorder(ros_env, out, "clock:=wall")
    try:
        js = graph.pub(JointState, "/joint_states")
        graph.wait_matched(js)
        for i in range(400):
            js.publish(joint_state(i))
            time.sleep(0.0005)
        time.sleep(1.6)
        for i in range(400, 450):   # these may or may not make it: that is the last second
            js.publish(joint_state(i))
        rec.send_signal(signal.SIGKILL)
        rec.wait(timeout=10)
    finally:
        if rec.poll() is None:
            rec.kill()
    bag = out / "bag.mcap"
    info = reader.bag_info(bag)
    assert not info["finalized"]
    got = [r for r in reader.read_messages(bag, ["/joint_states"])]
    assert len(got) >= 400, (len(got), log_tail(out))
    assert [m.effort[0] for _, m in got[:400]] == [float(i) for i in range(400)]
    # the periodic stats file exists even without a clean close
    stats = json.loads((out / "recording_stats.json").read_text())
    assert stats["finalized"] is False and stats["message_count"] > 0

    fixed = reader.recover(bag)
    assert reader.bag_info(fixed)["finalized"]
    from mcap_ros2.reader import read_ros2_messages
    from rosbags.highlevel import AnyReader

    assert sum(1 for m in read_ros2_messages(str(fixed), topics=["/joint_states"])) == len(got)
    with AnyReader([fixed]) as r:
        conns = [c for c in r.connections if c.topic == "/joint_states"]
        msgs = [r.deserialize(raw, c.msgtype) for c, _, raw in r.messages(connections=conns)]
    assert len(msgs) == len(got) and msgs[123].effort[0] == 123.0


def test_garbage_messages_do_not_stop_recording(graph, ros_env, tmp_path):
    """Undecodable payloads are recorded as they came, counted by readers, and the node lives on."""
    out = tmp_path / "run"
    rec = start_recorder(ros_env, out, "clock:=wall")
    try:
        cs = graph.pub(CentroidalState, "/centroidal_state")
        text = graph.pub(String, "/text")
        graph.wait_matched(cs)
        graph.wait_matched(text)
        garbage = [b"\x00\x01\x00", b"\x00\x01\x00\x00" + b"\xff\xff\xff\x7f" + b"x" * 10, bytes(range(256))]
        for i in range(20):
            cs.publish(centroidal(i))
            if i % 5 == 0:
                cs.publish(garbage[(i // 5) % len(garbage)])   # raw bytes: not a CentroidalState
        text.publish(garbage[0])
        text.publish(String(data="still alive"))
        time.sleep(1.0)
        assert rec.poll() is None, log_tail(out)
        rc = stop(rec, signal.SIGTERM)
    finally:
        if rec.poll() is None:
            rec.kill()
    assert rc == 0, log_tail(out)
    info = reader.bag_info(out)
    counts = {t["topic"]: t["count"] for t in info["topics"]}
    assert counts["/centroidal_state"] == 24 and counts["/text"] == 2
    errors = reader.DecodeErrors()
    good = list(reader.read_messages(out, ["/centroidal_state", "/text"], errors=errors))
    assert errors.by_topic.get("/centroidal_state") == 4 and errors.by_topic.get("/text") == 1
    assert sum(1 for r, _ in good if r.topic == "/centroidal_state") == 20
    assert next(m.data for r, m in good if r.topic == "/text") == "still alive"
    # plots skip what does not decode
    from humfall_ros.recording.plots import plot_run

    assert plot_run(out / "bag.mcap", tmp_path / "plots")


def test_unknown_types_are_skipped_not_fatal(in_ros_domain, tmp_path, monkeypatch):
    """In-process: a type this environment cannot import, or whose definition cannot be
    built, is skipped (logged, listed in the stats); the node and the bag carry on."""
    from humfall_ros.nodes import recorder as rec_mod
    from humfall_ros.recording import schema as schema_mod

    out = tmp_path / "run"
    # Recorder() uses the default context: initialise it for this test only.
    rclpy.init(args=["--ros-args", "-p", f"output_dir:={out}", "-p", "clock:=wall"])
    node = None
    try:
        node = rec_mod.Recorder()
        node._subscribe("/bogus", ["nonexistent_pkg/msg/Nope"], [])
        node._subscribe("/bogus2", ["std_msgs/msg/DoesNotExist"], [])

        def no_schema(type_name, loader=None):
            raise schema_mod.SchemaError(f"no definition for {type_name}")

        with monkeypatch.context() as m:
            m.setattr("humfall_ros.recording.writer.build_schema", no_schema)
            node._subscribe("/no_schema", ["std_msgs/msg/String"], [])
        node._subscribe("/fine", ["std_msgs/msg/String"], [])
        assert set(node.writer.skipped) == {"/bogus", "/bogus2", "/no_schema"}
        assert "/fine" in node._subs
        node.close()
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    stats = json.loads((out / "recording_stats.json").read_text())
    assert set(stats["skipped_topics"]) == {"/bogus", "/bogus2", "/no_schema"}
    assert stats["finalized"] and reader.bag_info(out)["finalized"]


def _record_through_a_stall(graph, ros_env, out: pathlib.Path, writer_qos, n: int) -> tuple[list[str], list[str], list]:
    """Publish ``n`` joint states while the recorder is stopped (SIGSTOP), then let it go; what was recorded."""
    from humfall_ros.nodes.common import wait_acknowledged

    rec = start_recorder(ros_env, out)
    try:
        pub = graph.pub(JointState, "joint_states", writer_qos)
        graph.wait_matched(pub)
        time.sleep(0.5)  # the recorder's reader is matched both ways before it stops
        rec.send_signal(signal.SIGSTOP)
        try:
            for i in range(n):
                pub.publish(joint_state(i))
                time.sleep(0.0005)
            while_stopped = wait_acknowledged(graph.node, 0.5)
        finally:
            rec.send_signal(signal.SIGCONT)
        after = wait_acknowledged(graph.node, 20.0)
        graph.node.destroy_publisher(pub)  # the writer goes away, as the bridge's does at the end of a run
        time.sleep(0.5)
        assert stop(rec, signal.SIGINT) == 0, log_tail(out)
    finally:
        if rec.poll() is None:
            rec.kill()
    efforts = [m.effort[0] for _raw, m in reader.read_messages(out, ["/joint_states"])]
    return while_stopped, after, efforts


def test_a_stalled_recorder_still_gets_every_tick(graph, ros_env, tmp_path):
    """The recorder starved of CPU (here: stopped) while the bridge runs on: the per-tick writers' history
    (QOS_TICK_WRITER) keeps what it has not acknowledged, and ``wait_acknowledged`` tells the writer when it has
    all of it (the bridge waits so before it exits). With the old depth-20 writers the bag lost ticks (session 28)."""
    from humfall_ros.nodes.common import QOS_TICK_WRITER

    n = 900
    while_stopped, after, efforts = _record_through_a_stall(graph, ros_env, tmp_path / "run", QOS_TICK_WRITER, n)
    assert while_stopped == ["/joint_states"]      # a stopped reader cannot acknowledge
    assert after == []                               # ... and once it runs again it has everything
    assert efforts == [float(i) for i in range(n)], (len(efforts), log_tail(tmp_path / "run"))
