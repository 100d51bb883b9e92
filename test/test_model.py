"""The robot model: URDF facts, pinocchio vs PyBullet, centroidal helpers."""
import math

import numpy as np
import pybullet as pb
import pytest

from humfall_ros.dynamics.pendulum import GRAVITY, capture_point, lean_angle
from humfall_ros.model.humanoid import (HumanoidModel, cop_from_wrenches, point_in_polygon_margin,
                                        support_polygon)
from humfall_ros.sim.world import SimWorld


@pytest.fixture(scope="module")
def model():
    return HumanoidModel()


def test_urdf_is_hrp2_class(model):
    assert 55.0 <= model.total_mass <= 60.0
    assert model.njoints == 22
    assert abs(model.foot_length - 0.24) < 1e-9 and abs(model.foot_width - 0.14) < 1e-9
    # every joint has position, velocity and effort limits
    lim = model.limits
    assert np.all(lim.upper > lim.lower)
    assert np.all(lim.velocity > 0) and np.all(lim.effort > 0)
    # four sole corners per foot, a hand frame per side, an IMU frame
    for s in ("l", "r"):
        assert len(model.corner_frames[s]) == 4
        assert model.hand_frame[s] in model.frame_ids
    assert model.imu_frame in model.frame_ids


def test_leg_joints_are_the_kinematic_chain_from_the_pelvis_to_the_sole(model):
    """``leg_joint_indices`` (the one list of a leg's joints every controller uses) names, hip to ankle, exactly the
    joints that move the sole relative to the root: the pinocchio chain of the sole frame."""
    for side in ("l", "r"):
        idx = model.leg_joint_indices(side)
        assert len(idx) == 6 and all(model.joint_names[i].startswith(f"{side}_") for i in idx)
        sole = model.model.frames[model.model.getFrameId(model.sole_frame[side])].parentJoint
        chain = [j for j in model.model.supports[sole].tolist() if j > 1]     # 0: universe, 1: the free flyer
        assert [model.model.names[j] for j in chain] == [model.joint_names[i] for i in idx]


def test_pinocchio_and_pybullet_agree_on_mass_and_standing_com(model):
    world = SimWorld(model=model)
    try:
        c = world.client
        pb_mass = sum(pb.getDynamicsInfo(world.robot, i, physicsClientId=c)[0]
                      for i in range(-1, pb.getNumJoints(world.robot, physicsClientId=c)))
        assert pb_mass == pytest.approx(model.total_mass, abs=1e-6)
        # PyBullet's CoM: mass-weighted link CoM positions (getLinkState[0] is the inertial frame)
        com_pb = np.zeros(3)
        pos, _ = pb.getBasePositionAndOrientation(world.robot, physicsClientId=c)
        com_pb += pb.getDynamicsInfo(world.robot, -1, physicsClientId=c)[0] * np.array(pos)
        for i in range(pb.getNumJoints(world.robot, physicsClientId=c)):
            mi = pb.getDynamicsInfo(world.robot, i, physicsClientId=c)[0]
            # computeForwardKinematics: the cached link frames are those of the last step's start; the robot still
            # settles into its servos after the reset (20 ms loop), so they lag the joint positions by v dt
            com_pb += mi * np.array(pb.getLinkState(world.robot, i, computeForwardKinematics=True,
                                                    physicsClientId=c)[0])
        com_pb /= pb_mass
        q, _ = world.pinocchio_state()
        com_pin = model.com(q)
        assert np.linalg.norm(com_pin - com_pb) < 1e-6
        # standing: the CoM is over the support polygon and about 0.74 m high
        model.forward(q)
        poly = support_polygon(np.vstack([model.sole_corners("l"), model.sole_corners("r")]))
        assert point_in_polygon_margin(com_pin, poly) > 0.05
        assert 0.65 < com_pin[2] < 0.85
    finally:
        world.close()


def test_support_polygon_is_the_hull_of_both_soles(model):
    q = model.configuration([0, 0, 0.7], [0, 0, 0, 1], np.zeros(model.njoints))
    model.forward(q)
    pts = np.vstack([model.sole_corners("l"), model.sole_corners("r")])
    poly = support_polygon(pts)
    assert len(poly) == 4
    # counter-clockwise: positive signed area = foot length x outer width
    x, y = poly[:, 0], poly[:, 1]
    area = 0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)
    width = pts[:, 1].max() - pts[:, 1].min()
    assert area == pytest.approx(model.foot_length * width, rel=1e-9)
    assert point_in_polygon_margin([10, 0], poly) < 0


def test_cop_from_wrenches_matches_point_forces():
    # two vertical point forces: the CoP is their weighted mean
    w1 = (np.array([0.1, 0.1, 0.1]), np.array([0, 0, 300.0]), np.zeros(3))
    w2 = (np.array([-0.1, -0.1, 0.1]), np.array([0, 0, 100.0]), np.zeros(3))
    # express each wrench at a point 0.1 m above its force's line of action
    cop, fz = cop_from_wrenches([w1, w2])
    assert fz == pytest.approx(400.0)
    assert cop[:2] == pytest.approx([0.05, 0.05])
    assert cop_from_wrenches([(np.zeros(3), np.zeros(3), np.zeros(3))])[0] is None


def test_capture_point_eq_1_2():
    com, vel = np.array([0.1, -0.2, 0.8]), np.array([0.5, 0.25, 0.0])
    cp = capture_point(com, vel)
    k = math.sqrt(0.8 / GRAVITY)
    assert cp == pytest.approx([0.1 + k * 0.5, -0.2 + k * 0.25, 0.0])
    angle, heading = lean_angle([0.3, 0.0, 0.3], [0, 0, 0])
    assert angle == pytest.approx(math.pi / 4) and heading == pytest.approx(0.0)


def test_crb_inertia_is_the_centroidal_inertia(model):
    q = model.configuration([0, 0, 0.7], [0, 0, 0, 1], np.zeros(model.njoints))
    I = model.crb_inertia(q)
    assert np.allclose(I, I.T) and np.all(np.linalg.eigvalsh(I) > 0)
    # cross-check against a spin about the CoM: h = I_G * omega for a rigid rotation
    v = np.zeros(model.model.nv)
    v[3:6] = [0.0, 1.0, 0.0]
    com = model.com(q)
    base = q[:3]
    v[:3] = -np.cross(v[3:6], base - com)  # base velocity of a rotation about the CoM
    _, _, h = model.centroidal(q, v)
    assert h == pytest.approx(I @ v[3:6], rel=1e-9, abs=1e-9)
    # an upright humanoid is taller than wide: pitch/roll inertia exceed yaw
    assert I[0, 0] > I[2, 2] and I[1, 1] > I[2, 2]


def test_support_polygon_matches_scipy_convex_hull():
    from scipy.spatial import ConvexHull

    rng = np.random.default_rng(3)
    for n in range(3, 12):
        pts = rng.uniform(-0.3, 0.3, size=(n, 2))
        ours = support_polygon(pts)
        ref = pts[ConvexHull(pts).vertices]
        assert len(ours) == len(ref)
        assert {tuple(np.round(p, 12)) for p in ours} == {tuple(np.round(p, 12)) for p in ref}
        x, y = ours[:, 0], ours[:, 1]
        assert 0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y) > 0  # counter-clockwise
    # degenerate: collinear points give the segment's ends, a single point itself
    seg = support_polygon([[0, 0], [0.1, 0], [0.2, 0]])
    assert {tuple(p) for p in seg} == {(0.0, 0.0), (0.2, 0.0)}
    assert support_polygon([[0.1, 0.2]]).tolist() == [[0.1, 0.2]]


def test_cop_from_wrenches_with_shear_and_ankle_torques():
    # point forces with shear, each measured as a wrench at an ankle 0.1 m above the ground:
    # the CoP must be the normal-force-weighted mean of the points of application
    rng = np.random.default_rng(7)
    wrenches, points, normals = [], [], []
    for _ in range(3):
        p = np.array([*rng.uniform(-0.2, 0.2, 2), 0.0])
        f = np.array([*rng.uniform(-50, 50, 2), rng.uniform(100, 300)])
        ankle = p + np.array([*rng.uniform(-0.05, 0.05, 2), 0.1])
        wrenches.append((ankle, f, np.cross(p - ankle, f)))
        points.append(p)
        normals.append(f[2])
    cop, fz = cop_from_wrenches(wrenches)
    assert fz == pytest.approx(sum(normals))
    assert cop[:2] == pytest.approx(np.average(points, axis=0, weights=normals)[:2], abs=1e-12)


def test_imu_quaternion_reads_every_shape_of_reading_and_refuses_unusable_ones():
    from types import SimpleNamespace

    from humfall_ros.model.humanoid import imu_quaternion

    q = np.array([0.0, 0.1, 0.0, 0.995])
    for reading in ((q, np.zeros(3)), [q, np.zeros(3)], q, {"orientation": q}, SimpleNamespace(orientation=q)):
        np.testing.assert_array_equal(imu_quaternion(reading), q)          # as given, not normalised
    for bad in (None, (np.full(4, np.nan), np.zeros(3)), (np.zeros(4), np.zeros(3)), (np.ones(3), np.zeros(3)),
                {"gyro": q}, SimpleNamespace(gyro=q), object(), (("a", "b", "c", "d"), None)):
        assert imu_quaternion(bad) is None


def test_swing_com_gain_is_the_com_shift_of_a_sole_moved_by_its_leg_alone():
    """``HumanoidModel.swing_com_gain``: the shared IK moves the left sole 1 cm forward and 0.6 cm sideways with
    the base and the other joints held; the CoM moves by the gain times that (to 2 %; it is a linearisation: 5 cm
    forward moves the CoM 7 % less, 5 cm back 5 % more), and the gain is a fraction of the leg's share of the mass
    (the foot moves fully, the thigh less)."""
    import pinocchio as pin

    from humfall_ros.model.humanoid import load_model
    from humfall_ros.model.ik import FrameTask, PostureTask, WholeBodyIK

    m = load_model()
    q = pin.neutral(m.model)
    q[7:] = m.joint_vector(m.standing_posture)
    gain = m.swing_com_gain(q, "l")
    m.forward(q)
    sole = m.frame_placement(m.sole_frame["l"]).copy()
    move = np.array([0.01, 0.006])
    target = pin.SE3(sole.rotation, sole.translation + np.append(move, 0.0))
    others = [i for i in range(m.njoints) if i not in m.leg_joint_indices("l")]
    w = np.zeros(m.njoints)
    w[others] = 1e3
    ik = WholeBodyIK(m, fixed_base=True)
    r = ik.solve_to_convergence(q, [FrameTask(m.sole_frame["l"], target, weight=1e3), PostureTask(q[7:], weight=w)],
                                dt=0.05, max_iterations=300, tolerance=1e-5)
    assert r.converged
    shift = (m.com(r.q) - m.com(q))[:2]
    assert np.allclose(shift, gain @ move, atol=0.02 * np.linalg.norm(gain @ move))
    leg_mass = sum(m.model.inertias[m.model.joints[m.model.getJointId(f"l_{j}")].id].mass
                   for j in ("hip_yaw", "hip_roll", "hip_pitch", "knee", "ankle_pitch", "ankle_roll"))
    assert 0.3 * leg_mass / m.total_mass < gain[0, 0] < leg_mass / m.total_mass
    assert abs(gain[0, 1]) < 0.1 * gain[0, 0] and abs(gain[1, 0]) < 0.1 * gain[0, 0]


def test_a_model_with_own_data_shares_the_model_but_not_the_kinematics():
    m = HumanoidModel()
    own = m.with_own_data()
    assert own.model is m.model and own.joint_names == m.joint_names and own.data is not m.data
    m.forward(m.neutral())
    before = m.frame_position(m.sole_frame["l"])
    q = m.neutral()
    q[:3] = [1.0, 2.0, 3.0]
    own.forward(q)
    np.testing.assert_allclose(own.frame_position(own.sole_frame["l"]) - before, [1.0, 2.0, 3.0], atol=1e-12)
    np.testing.assert_array_equal(m.frame_position(m.sole_frame["l"]), before)   # untouched
