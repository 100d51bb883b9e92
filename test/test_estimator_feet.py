"""The estimator's per-foot normal force and CoP (each from its own ankle wrench), and that the controllers see them
identically in process (``centroidal_from_estimate``) and over ROS (``CentroidalState`` -> ``centroidal_from_msg``)."""
import numpy as np
import pytest
import rclpy
from builtin_interfaces.msg import Time
from geometry_msgs.msg import WrenchStamped
from humfall_interfaces.msg import CentroidalState
from sensor_msgs.msg import Imu, JointState

from humfall_ros.control.contract import centroidal_from_estimate
from humfall_ros.model.estimation import CentroidalEstimator
from humfall_ros.model.humanoid import SIDES, load_model
from humfall_ros.recording import cdr

QUAT = [0.0, 0.0, 0.0, 1.0]


@pytest.fixture(scope="module")
def model():
    return load_model()


def _wrenches(model, est_q, forces, cop_offsets):
    """Ankle wrenches (foot axes) of a vertical force ``forces[s]`` acting at ``cop_offsets[s]`` (x, y) [m] from the
    ankle's ground projection, for the configuration ``est_q`` (the estimator's)."""
    model.forward(est_q)
    out = {}
    for s in SIDES:
        M = model.frame_placement(model.foot_link[s])
        r_w = np.array([cop_offsets[s][0], cop_offsets[s][1], -M.translation[2]])   # ankle -> CoP on z = 0
        f_w = np.array([0.0, 0.0, forces[s]])
        tq_w = np.cross(r_w, f_w)
        out[s] = (M.rotation.T @ f_w, M.rotation.T @ tq_w)
    return out


def test_per_foot_force_and_cop_from_each_ankle_wrench(model):
    joints = model.joint_vector(model.standing_posture)
    est = CentroidalEstimator(model)
    zero = {s: (np.array([0.0, 0.0, 300.0]), np.zeros(3)) for s in SIDES}
    e0 = est.update(0.0, joints, np.zeros(model.njoints), QUAT, np.zeros(3), zero)
    forces = {"l": 400.0, "r": 150.0}
    offs = {"l": (0.03, -0.01), "r": (-0.02, 0.015)}
    e = est.update(0.002, joints, np.zeros(model.njoints), QUAT, np.zeros(3), _wrenches(model, e0.q, forces, offs))
    model.forward(e.q)
    for s in SIDES:
        assert e.foot_normal_force[s] == pytest.approx(forces[s], abs=1e-9)
        ankle = model.frame_placement(model.foot_link[s]).translation
        assert e.foot_cop[s] == pytest.approx([ankle[0] + offs[s][0], ankle[1] + offs[s][1], 0.0], abs=1e-9)
    # the total is their force-weighted mean
    mean = sum(e.foot_normal_force[s] * e.foot_cop[s] for s in SIDES) / e.normal_force
    assert e.cop == pytest.approx(mean, abs=1e-12) and e.normal_force == pytest.approx(550.0)
    # an unloaded foot: its CoP below its ankle, its force as measured
    w = _wrenches(model, e.q, {"l": 560.0, "r": 0.0}, {"l": (0.0, 0.0), "r": (0.05, 0.0)})
    e = est.update(0.004, joints, np.zeros(model.njoints), QUAT, np.zeros(3), w)
    ankle_r = model.frame_placement(model.foot_link["r"]).translation
    assert e.foot_normal_force["r"] == pytest.approx(0.0, abs=1e-9)
    assert e.foot_cop["r"] == pytest.approx([ankle_r[0], ankle_r[1], 0.0])
    obs = centroidal_from_estimate(e)
    assert obs.foot_normal_forces == {s: e.foot_normal_force[s] for s in SIDES}
    assert all(np.array_equal(obs.foot_cops[s], e.foot_cop[s]) for s in SIDES)


def test_the_message_carries_the_per_foot_fields_bit_for_bit(in_ros_domain, model):
    from humfall_ros.nodes.controller_node import centroidal_from_msg
    from humfall_ros.nodes.state_estimator import StateEstimator

    rclpy.init()
    node = StateEstimator()
    published = []
    decode = cdr.decoder(CentroidalState)
    node.pub.publish = lambda data: published.append(decode(data))  # the bytes it sends, as a subscriber reads them
    node.hot_loop.batching = True
    try:
        joints = model.joint_vector(model.standing_posture)
        rng = np.random.default_rng(3)
        for k in range(3):
            stamp = Time(sec=0, nanosec=2_000_000 * (k + 1))
            js = JointState(name=model.joint_names, position=joints.tolist(), velocity=[0.0] * model.njoints)
            imu = Imu()
            imu.orientation.w = 1.0
            msgs = {"js": js, "imu": imu}
            for s in SIDES:
                w = WrenchStamped()
                f = rng.uniform([-5, -5, 100], [5, 5, 400])
                t = rng.uniform(-8, 8, 3)
                w.wrench.force.x, w.wrench.force.y, w.wrench.force.z = f.tolist()
                w.wrench.torque.x, w.wrench.torque.y, w.wrench.torque.z = t.tolist()
                msgs[s] = w
            for name in ("l", "r", "imu", "js"):
                msgs[name].header.stamp = stamp
                node._add(name, msgs[name])
            node._on_batch()
            got = centroidal_from_msg(published[-1])
            want = centroidal_from_estimate(node.estimator.last)
            for field in ("left_normal_force", "right_normal_force", "normal_force"):
                assert getattr(got, field) == getattr(want, field)
            for field in ("left_cop", "right_cop", "cop", "com"):
                assert np.array_equal(getattr(got, field), getattr(want, field))
            assert got.left_normal_force > 50.0 and not np.array_equal(got.left_cop, got.right_cop)
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
