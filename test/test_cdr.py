"""The fast CDR decoder (recording/cdr.py) against rclpy's own deserialisation, field by field."""
from __future__ import annotations

import importlib
import random

import numpy as np
import pytest
from rclpy.serialization import serialize_message

from humfall_ros.recording import cdr

HOT_AND_OURS = ["sensor_msgs/JointState", "sensor_msgs/Imu", "geometry_msgs/WrenchStamped", "geometry_msgs/Twist",
                "rosgraph_msgs/Clock", "humfall_interfaces/CentroidalState", "humfall_interfaces/MuxState",
                "humfall_interfaces/WalkingState", "humfall_interfaces/FtbStatus", "humfall_interfaces/FallEvent",
                "humfall_interfaces/EstopStatus", "humfall_interfaces/SafeFallDecision",
                "humfall_interfaces/ObstacleArray", "humfall_interfaces/LandingReport",
                "humfall_interfaces/PlanSegment"]

INTS = {"int64": (-2**63, 2**63 - 1), "uint64": (0, 2**64 - 1), "int32": (-2**31, 2**31 - 1), "uint32": (0, 2**32 - 1),
        "int16": (-2**15, 2**15 - 1), "uint16": (0, 2**16 - 1), "int8": (-128, 127), "uint8": (0, 255)}


def cls_of(name: str) -> type:
    pkg, typ = name.split("/")[0], name.split("/")[-1]
    return getattr(importlib.import_module(f"{pkg}.msg"), typ)


def rand_value(t: str, rng: random.Random):
    kind, base, n = cdr._split_type(t)
    if kind != "single":
        count = n if kind == "array" else rng.choice([0, 0, 1, 2, 3, 7])
        vals = [rand_value(base, rng) for _ in range(count)]
        if base in ("double", "float"):
            return np.array(vals, dtype=float) if kind == "array" else vals
        return vals
    if base == "double":
        return rng.choice([0.0, -0.0, 1.5, float("inf"), float("nan"), rng.uniform(-1e6, 1e6), 5e-324])
    if base == "float":
        return float(np.float32(rng.uniform(-1e3, 1e3)))
    if base == "boolean":
        return rng.random() < 0.5
    if base in INTS:
        return rng.randint(*INTS[base])
    if base in ("octet", "byte"):
        return bytes([rng.randint(0, 255)])
    if base.startswith("string"):
        return "".join(rng.choice("abcxyz_é") for _ in range(rng.choice([0, 1, 2, 3, 4, 5, 11])))
    return rand_msg(cls_of(base), rng)


def rand_msg(cls: type, rng: random.Random):
    m = cls()
    for name, t in cls.get_fields_and_field_types().items():
        setattr(m, name, rand_value(t, rng))
    return m


def assert_same(ours, theirs, t: str, path: str) -> None:
    kind, base, _ = cdr._split_type(t)
    if kind != "single":
        assert len(ours) == len(theirs), path
        for i, (a, b) in enumerate(zip(ours, theirs)):
            assert_same(a, b, base, f"{path}[{i}]")
        return
    if base in cdr.PRIMITIVES or base.startswith("string"):
        if base in ("octet", "byte"):
            theirs = theirs[0] if isinstance(theirs, bytes) else theirs
        if isinstance(theirs, float) and np.isnan(theirs):
            assert np.isnan(ours), path
        else:
            assert ours == theirs and type(ours) is not bool or ours is theirs, (path, ours, theirs)
            if isinstance(theirs, float):  # bit for bit, -0.0 included
                assert np.float64(ours).tobytes() == np.float64(theirs).tobytes(), path
        return
    for name, ft in type(theirs).get_fields_and_field_types().items():
        assert_same(getattr(ours, name), getattr(theirs, name), ft, f"{path}.{name}")


@pytest.mark.parametrize("type_name", HOT_AND_OURS)
def test_decoder_matches_rclpy_on_random_messages(type_name):
    from rclpy.serialization import deserialize_message

    cls = cls_of(type_name)
    dec = cdr.decoder(cls)
    rng = random.Random(type_name)
    for _ in range(60):
        msg = rand_msg(cls, rng)
        data = serialize_message(msg)
        assert_same(dec(data), deserialize_message(data, cls), type_name, type_name)


def test_joint_names_are_reused_only_when_their_bytes_repeat():
    from sensor_msgs.msg import JointState

    dec = cdr.decoder(JointState)
    a = dec(serialize_message(JointState(name=["hip", "knee"], position=[1.0, 2.0])))
    b = dec(serialize_message(JointState(name=["hip", "knee"], position=[3.0, 4.0])))
    c = dec(serialize_message(JointState(name=["hip", "kneX"], position=[5.0, 6.0])))
    d = dec(serialize_message(JointState(name=["hip"], position=[7.0])))
    assert a.name == b.name == ["hip", "knee"] and c.name == ["hip", "kneX"] and d.name == ["hip"]
    assert a.name is not b.name  # each message its own list: a caller may change it
    assert list(b.position) == [3.0, 4.0] and list(d.position) == [7.0]


def test_bad_data_is_refused():
    from humfall_interfaces.msg import CentroidalState

    dec = cdr.decoder(CentroidalState)
    good = serialize_message(CentroidalState())
    with pytest.raises(ValueError, match="little-endian"):
        dec(b"\x00\x00\x00\x00" + good[4:])  # big-endian encapsulation
    with pytest.raises(Exception):  # noqa: B017 - struct.error or ValueError: short data never decodes
        dec(good[:40])


def test_the_comparison_sees_a_difference():
    """The field-by-field check above is not vacuous: two different random messages differ in it."""
    from humfall_interfaces.msg import CentroidalState

    rng = random.Random(1)
    a, b = rand_msg(CentroidalState, rng), rand_msg(CentroidalState, rng)
    with pytest.raises(AssertionError):
        assert_same(cdr.decoder(CentroidalState)(serialize_message(a)), b, "x", "x")
    from rclpy.serialization import deserialize_message

    data = serialize_message(b)
    flipped = deserialize_message(data, CentroidalState)
    flipped.left_contact = not flipped.left_contact  # one bool apart
    with pytest.raises(AssertionError):
        assert_same(cdr.decoder(CentroidalState)(data), flipped, "x", "x")


# ------------------------------------------------------------------ the encoder
ENCODED = HOT_AND_OURS + ["nav_msgs/Odometry", "tf2_msgs/TFMessage", "std_msgs/String"]


@pytest.mark.parametrize("type_name", ENCODED)
def test_encoder_round_trips_through_rclpy_on_random_messages(type_name):
    """What the encoder writes, rclpy reads back as the message it was given, field by field and bit for bit;
    from the message itself and from its namespace copy (what the nodes fill) alike."""
    from rclpy.serialization import deserialize_message

    cls = cls_of(type_name)
    enc = cdr.encoder(cls)
    rng = random.Random("enc" + type_name)
    for _ in range(60):
        msg = rand_msg(cls, rng)
        data = enc(msg)
        assert data[:4] == b"\x00\x01\x00\x00"
        assert_same(deserialize_message(data, cls), msg, type_name, type_name)
        assert enc(cdr._to_ns(msg)) == data
        # rclpy's own bytes are the same length or longer (it may leave trailing bytes; its padding is not zeroed)
        assert len(data) <= len(serialize_message(msg))
        assert_same(cdr.decoder(cls)(data), msg, type_name, type_name)


def test_encoder_takes_numpy_arrays_and_a_blank_namespace():
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import JointState

    ns = cdr.blank(JointState)
    assert ns.name == [] and ns.header.frame_id == "" and ns.header.stamp.sec == 0
    ns.name, ns.position, ns.velocity = ["hip", "knee"], np.array([0.5, -1.25]), np.array([2.0, 3.0])
    ns.header.stamp.sec, ns.header.stamp.nanosec = 7, 500
    back = deserialize_message(cdr.encoder(JointState)(ns), JointState)
    assert list(back.name) == ["hip", "knee"] and list(back.position) == [0.5, -1.25]
    assert list(back.velocity) == [2.0, 3.0] and list(back.effort) == [] and back.header.stamp.sec == 7
    # the names' bytes are reused only while the list is equal
    ns.name = ["hip", "kneX"]
    assert list(deserialize_message(cdr.encoder(JointState)(ns), JointState).name) == ["hip", "kneX"]


def test_encoder_refuses_what_does_not_fit():
    from humfall_interfaces.msg import CentroidalState
    from sensor_msgs.msg import Imu

    imu = cdr.blank(Imu)
    imu.orientation_covariance = np.zeros(8)
    with pytest.raises(ValueError, match="array of 9"):
        cdr.encoder(Imu)(imu)
    cs = cdr.blank(CentroidalState)
    cs.header.frame_id = 3  # not a string
    with pytest.raises(AttributeError):
        cdr.encoder(CentroidalState)(cs)
    cs = cdr.blank(CentroidalState)
    cs.header.stamp.nanosec = -1  # uint32
    with pytest.raises(Exception):  # noqa: B017 - struct.error
        cdr.encoder(CentroidalState)(cs)
