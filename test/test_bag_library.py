"""humfall_ros.recording without a ROS graph: schemas, writer, streaming reader, recover, info, plots.

Messages are serialised with rclpy's CDR serialiser (no node, no DDS), so the
bytes are exactly what the recorder would receive.
"""
from __future__ import annotations

import io
import math
import pathlib

import pytest

pytest.importorskip("rclpy")

from geometry_msgs.msg import Point, Pose, Quaternion, Vector3  # noqa: E402
from humfall_interfaces.msg import CentroidalState, Obstacle, ObstacleArray  # noqa: E402
from rclpy.serialization import serialize_message  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from visualization_msgs.msg import Marker, MarkerArray  # noqa: E402

from humfall_ros.recording import (BagWriter, bag_info, info_main, plot_main, plot_run,  # noqa: E402
                                   read_messages, recover)
from humfall_ros.recording import schema  # noqa: E402

SEP = "=" * 80


def test_schema_of_custom_type_lists_nested_types_once():
    text = schema.build_schema("humfall_interfaces/msg/CentroidalState")
    assert text.startswith("# Centroidal state")
    nested = schema.schema_types(text)
    assert nested == ["std_msgs/msg/Header", "builtin_interfaces/msg/Time",
                      "geometry_msgs/msg/Point", "geometry_msgs/msg/Vector3"]
    assert text.count(SEP + "\nMSG: ") == len(nested)


def test_schema_resolution_rules_with_injected_loader():
    msgs = {
        "p/msg/Root": "Header h\nChild[<=3] kids  # relative\nq/Other other\nint32 K=5\nstring<=8 s\nChild c\n",
        "p/msg/Child": "float64[4] v\nq/msg/Other o\n",
        "q/msg/Other": "uint8 x 7\n",
        "std_msgs/msg/Header": "builtin_interfaces/Time stamp\nstring frame_id\n",
        "builtin_interfaces/msg/Time": "int32 sec\nuint32 nanosec\n",
    }
    text = schema.build_schema("p/Root", loader=lambda n: msgs[n])
    assert schema.schema_types(text) == ["std_msgs/msg/Header", "builtin_interfaces/msg/Time",
                                         "p/msg/Child", "q/msg/Other"]
    with pytest.raises(schema.SchemaError):
        schema.build_schema("p/msg/Missing", loader=lambda n: msgs[n])
    with pytest.raises(schema.SchemaError):
        schema.build_schema("not-a-type")


def test_python_fallback_schema_decodes_real_cdr():
    """A definition rebuilt from the Python class has the same wire layout as the .msg."""
    from mcap_ros2._dynamic import generate_dynamic

    def python_only(name):
        return schema.msg_text_from_python(name)

    m = MarkerArray(markers=[Marker(ns="n", id=3, points=[Point(x=1.5)], text="hi")])
    text = schema.build_schema("visualization_msgs/msg/MarkerArray", loader=python_only)
    dec = generate_dynamic("visualization_msgs/msg/MarkerArray", text)["visualization_msgs/msg/MarkerArray"]
    out = dec(serialize_message(m))
    assert out.markers[0].id == 3 and out.markers[0].points[0].x == 1.5 and out.markers[0].text == "hi"


def centroidal(i: int, n: int) -> CentroidalState:
    """A toy forward fall: CoM moves +x and drops, lean grows."""
    th = 1.2 * i / n
    m = CentroidalState()
    m.header.stamp.sec, m.header.stamp.nanosec = divmod(i * 2_000_000, 10**9)
    m.com = Point(x=0.8 * math.sin(th), y=0.05 * th, z=0.8 * math.cos(th))
    m.com_velocity = Vector3(x=0.8 * math.cos(th), z=-0.8 * math.sin(th))
    m.cop = Point(x=min(0.12, 0.2 * th))
    m.capture_point = Point(x=m.com.x + 0.3 * m.com_velocity.x)
    m.capture_point_fused = Point(x=m.capture_point.x - 0.01)   # the estimator's filtered one
    m.support_polygon = [Point(x=0.12, y=0.17), Point(x=-0.12, y=0.17), Point(x=-0.12, y=-0.17),
                         Point(x=0.12, y=-0.17)]
    m.lean_angle = th
    m.left_contact = m.right_contact = True
    return m


def write_run(path: pathlib.Path, n: int = 500, flush_every: int = 100) -> BagWriter:
    w = BagWriter(path, metadata={"log_time_clock": "sim", "scenario": "unit"})
    cs = w.add_topic("/centroidal_state", "humfall_interfaces/msg/CentroidalState")
    js = w.add_topic("/joint_states", "sensor_msgs/msg/JointState")
    mk = w.add_topic("/markers", "visualization_msgs/msg/MarkerArray")
    ob = w.add_topic("/obstacles", "humfall_interfaces/msg/ObstacleArray",
                     [{"durability": "transient_local", "depth": 1}])
    obstacles = ObstacleArray(obstacles=[
        Obstacle(name="target", pose=Pose(position=Point(x=1.2)), size=Vector3(x=0.4, y=0.6, z=1.0),
                 is_target=True),
        Obstacle(name="wall", pose=Pose(position=Point(y=1.0), orientation=Quaternion(z=0.383, w=0.924)),
                 size=Vector3(x=2.0, y=0.1, z=2.0))])
    w.write(ob, serialize_message(obstacles), 0)
    for i in range(n):
        t = i * 2_000_000
        w.write(cs, serialize_message(centroidal(i, n)), t)
        # All arrays filled: rclpy's serialize_message (rmw_serialize) sizes the buffer by
        # FastCDR's estimate, which for an empty float64[] leaves trailing bytes that rosbags
        # rejects; messages received from the wire carry the exact length (see process tests).
        js_msg = JointState(name=["a", "b"], position=[0.001 * i, -0.002 * i], velocity=[0.0, 0.0],
                            effort=[1.0, 1.0])
        w.write(js, serialize_message(js_msg), t)
        if i % 10 == 0:
            w.write(mk, serialize_message(MarkerArray(markers=[Marker(id=i)])), t)
        if i % flush_every == flush_every - 1:
            w.flush()
    return w


def test_finalized_bag_info_and_independent_readers(tmp_path):
    w = write_run(tmp_path / "bag.mcap")
    w.close()
    info = bag_info(tmp_path)   # a run folder resolves to its bag.mcap
    counts = {t["topic"]: t["count"] for t in info["topics"]}
    assert counts == {"/centroidal_state": 500, "/joint_states": 500, "/markers": 50, "/obstacles": 1}
    assert info["finalized"] and not info["truncated"]
    cs = next(t for t in info["topics"] if t["topic"] == "/centroidal_state")
    assert cs["rate_hz"] == pytest.approx(500.0)
    assert info["duration_s"] == pytest.approx(0.998)

    from mcap_ros2.reader import read_ros2_messages
    from rosbags.highlevel import AnyReader

    got = {m.channel.topic: m.ros_msg for m in read_ros2_messages(str(tmp_path / "bag.mcap"))}
    assert got["/obstacles"].obstacles[0].is_target and got["/obstacles"].obstacles[1].name == "wall"
    assert got["/centroidal_state"].lean_angle == pytest.approx(1.2 * 499 / 500)
    with AnyReader([tmp_path / "bag.mcap"]) as r:
        last = {}
        for c, _, raw in r.messages():
            last[c.topic] = r.deserialize(raw, c.msgtype)
    assert last["/obstacles"].obstacles[0].size.y == pytest.approx(0.6)
    assert len(last["/centroidal_state"].support_polygon) == 4
    assert last["/markers"].markers[0].id == 490


def test_cut_bag_is_readable_at_every_length_and_recoverable(tmp_path):
    """Simulate kill -9 at arbitrary byte offsets: what was flushed before the cut is readable."""
    w = write_run(tmp_path / "live.mcap", n=400, flush_every=100)
    flushed = (tmp_path / "live.mcap").read_bytes()   # 4 flushes of 100 samples, not closed
    w.close()
    prev = 0
    for cut in sorted({len(flushed) * k // 13 for k in range(1, 14)}):
        p = tmp_path / f"cut{cut}.mcap"
        p.write_bytes(flushed[:cut])
        info = bag_info(p)
        assert not info["finalized"]
        n = sum(t["count"] for t in info["topics"] if t["topic"] == "/centroidal_state")
        assert n >= prev and n % 100 == 0   # whole flushed chunks only, never decreasing
        prev = n
    assert prev == 400
    fixed = recover(p)
    assert bag_info(fixed)["finalized"]
    from rosbags.highlevel import AnyReader

    with AnyReader([fixed]) as r:
        assert sum(1 for c, _, _ in r.messages() if c.topic == "/centroidal_state") == 400
    vals = [m.com.x for _, m in read_messages(fixed, ["/centroidal_state"])]
    assert vals == [pytest.approx(centroidal(i, 400).com.x) for i in range(400)]


def test_info_main_prints_topics_and_handles_missing(tmp_path, capsys):
    write_run(tmp_path / "bag.mcap", n=50).close()
    out = io.StringIO()
    assert info_main(tmp_path / "bag.mcap", out=out) == 0
    text = out.getvalue()
    assert "humfall_interfaces/msg/CentroidalState" in text and "finalized" in text
    assert "/joint_states" in text and "500.0" in text
    assert info_main(tmp_path / "nope.mcap") == 1
    assert "no such bag" in capsys.readouterr().err


def test_plots_from_bag(tmp_path):
    write_run(tmp_path / "bag.mcap").close()
    paths = plot_run(tmp_path / "bag.mcap", tmp_path / "plots")
    assert [p.name for p in paths] == ["top_view.png", "centroidal_time.png", "joint_positions.png"]
    for p in paths:
        assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and p.stat().st_size > 10_000
    assert plot_main(tmp_path / "bag.mcap") == 0            # default: next to the bag
    assert (tmp_path / "top_view.png").is_file()
    empty = BagWriter(tmp_path / "empty" / "bag.mcap")
    empty.close()
    assert plot_main(tmp_path / "empty") == 1
    assert plot_main(tmp_path / "missing") == 1


def test_plots_read_both_capture_points(tmp_path):
    """The bag's series carry the leg odometry's capture point and the fused one (the top view draws the fused one
    where the two differ)."""
    from humfall_ros.recording.plots import load_series
    write_run(tmp_path / "bag.mcap", n=50).close()
    cs = load_series(tmp_path / "bag.mcap")["centroidal"]
    assert len(cs["cp"]) == len(cs["cpf"]) == 50
    for i, (cp, cpf) in enumerate(zip(cs["cp"], cs["cpf"])):
        assert cp[0] == pytest.approx(centroidal(i, 50).capture_point.x)
        assert cpf[0] == pytest.approx(cp[0] - 0.01)


def test_bag_info_counts_the_holes_of_periodic_stamped_topics(tmp_path):
    """A tick the recorder never got shows as a hole between stamps (``missing_stamps``); topics without a
    stamp, or whose stamps are not periodic (events), have none to count."""
    from builtin_interfaces.msg import Time
    from geometry_msgs.msg import PointStamped
    from humfall_interfaces.msg import FallEvent
    from rosgraph_msgs.msg import Clock
    from std_msgs.msg import String

    w = BagWriter(tmp_path / "bag.mcap", metadata={"log_time_clock": "sim"})
    com = w.add_topic("/com", "geometry_msgs/msg/PointStamped")
    clock = w.add_topic("/clock", "rosgraph_msgs/msg/Clock")
    events = w.add_topic("/fall_event", "humfall_interfaces/msg/FallEvent")
    text = w.add_topic("/chatter", "std_msgs/msg/String")
    lost = {10, 11, 12, 40}          # a hole of three ticks and one of one
    for i in range(200):
        ns = 5 * 10**9 + i * 2_000_000
        stamp = Time(sec=ns // 10**9, nanosec=ns % 10**9)
        w.write(clock, serialize_message(Clock(clock=stamp)), ns)
        if i not in lost:
            msg = PointStamped()
            msg.header.stamp = stamp
            w.write(com, serialize_message(msg), ns)
        if i in (3, 50, 51, 140, 141, 142, 190, 199, 120, 7, 60, 61):   # events: irregular stamps
            ev = FallEvent()
            ev.header.stamp = stamp
            w.write(events, serialize_message(ev), ns)
        w.write(text, serialize_message(String(data=f"{i}")), ns)
    w.write(com, serialize_message(PointStamped()), 9 * 10**9)   # a stamp of 0: not a hole either
    w.close()

    topics = {t["topic"]: t for t in bag_info(tmp_path)["topics"]}
    assert topics["/com"]["missing_stamps"] == 4
    assert topics["/com"]["stamp_period_s"] == pytest.approx(0.002)
    assert topics["/clock"]["missing_stamps"] == 0
    assert topics["/fall_event"]["missing_stamps"] is None
    assert topics["/chatter"]["missing_stamps"] is None
    out = io.StringIO()
    assert info_main(tmp_path / "bag.mcap", out=out) == 0
    assert "holes:     4 stamps missing on 1 of 2 periodic stamped topics" in out.getvalue()


def test_bag_info_rates_by_the_stamps_where_messages_carry_them(tmp_path):
    """A recorder that fell behind logs a burst at its own (late) clock: the log-time rate reads high, the rate by
    the messages' stamps stays the publisher's; ``humfall bag info`` prints the latter where there is one."""
    from builtin_interfaces.msg import Time
    from geometry_msgs.msg import PointStamped
    from std_msgs.msg import String

    w = BagWriter(tmp_path / "bag.mcap", metadata={"log_time_clock": "sim"})
    com = w.add_topic("/com", "geometry_msgs/msg/PointStamped")
    text = w.add_topic("/chatter", "std_msgs/msg/String")
    for i in range(500):                               # 500 Hz for 1 s by the stamps
        ns = 10**9 + i * 2_000_000
        log_ns = ns if i < 250 else 10**9 + 500_000_000 + (i - 250) * 400_000   # the second half drained in 0.1 s
        msg = PointStamped()
        msg.header.stamp = Time(sec=ns // 10**9, nanosec=ns % 10**9)
        w.write(com, serialize_message(msg), log_ns)
        w.write(text, serialize_message(String(data=f"{i}")), ns)
    w.close()

    topics = {t["topic"]: t for t in bag_info(tmp_path)["topics"]}
    assert topics["/com"]["rate_hz"] > 800                             # by log time: 499 in 0.6 s
    assert topics["/com"]["stamp_rate_hz"] == pytest.approx(500.0)
    assert topics["/com"]["missing_stamps"] == 0
    assert topics["/chatter"]["stamp_rate_hz"] is None                 # no stamp: the log-time rate
    out = io.StringIO()
    assert info_main(tmp_path / "bag.mcap", out=out) == 0
    rows = {line.split()[0]: line.split() for line in out.getvalue().splitlines() if line.startswith("/")}
    assert rows["/com"][3] == "500.0"
    assert rows["/chatter"][3] == "500.0"


def test_stamp_helpers():
    from humfall_ros.recording.cdr import leading_stamp_ns as stamp_ns
    from humfall_ros.recording.reader import leads_with_stamp, missing_stamps, stamp_rate_hz

    log = "uint8 DEBUG=10 # debug\nuint8 INFO = 20\n\nbuiltin_interfaces/Time stamp\nuint8 level\n"
    assert leads_with_stamp(log)                                    # constants and comments skipped
    assert leads_with_stamp("# a comment\nstd_msgs/Header header\nfloat64 x\n")
    assert not leads_with_stamp("float64 data\n")
    assert not leads_with_stamp("Marker[] markers\n" + SEP + "\nMSG: visualization_msgs/Marker\nstd_msgs/Header h\n")
    assert not leads_with_stamp("uint8 A=1\n" + SEP + "\nMSG: std_msgs/Header\nbuiltin_interfaces/Time stamp\n")
    little = bytes([0, 1, 0, 0]) + (7).to_bytes(4, "little") + (5).to_bytes(4, "little")
    big = bytes([0, 0, 0, 0]) + (7).to_bytes(4, "big") + (5).to_bytes(4, "big")
    assert stamp_ns(little) == stamp_ns(big) == 7_000_000_005
    assert stamp_ns(b"\x00\x01\x00\x00\x07") is None                # too short
    holed = [t for t in range(10, 310, 10) if t not in (30, 40, 120)]
    assert missing_stamps(holed) == (3, pytest.approx(1e-8))
    assert missing_stamps([0, 0] + holed) == (3, pytest.approx(1e-8))   # unset stamps are not times
    assert missing_stamps(range(0, 90, 10)) == (None, None)          # fewer than 10 stamps
    assert missing_stamps([0, 10, 20, 30, 31, 32, 45, 80, 81, 200, 900]) == (None, None)   # not periodic
    assert stamp_rate_hz([0, 10**9, 2 * 10**9, 3 * 10**9]) == pytest.approx(1.0)   # the unset stamp left out
    assert stamp_rate_hz([0, 5]) is None and stamp_rate_hz([7, 7]) is None
