"""The estimator's CoM velocity: the chest IMU's gyro corrected for the waist joints, and the optional
complementary filter of the ankle ground reaction (Newton) with leg odometry (``com_velocity_time_constant``),
published beside the odometry's as ``com_velocity_fused`` / ``capture_point_fused``."""
import numpy as np
import pinocchio as pin
import pytest

from humfall_ros import scenario
from humfall_ros.model.estimation import CentroidalEstimator
from humfall_ros.model.humanoid import SIDES, load_model
from humfall_ros.sim.closed_loop import ClosedLoop
from humfall_ros.walking.controller import from_scenario

DT = 0.002


@pytest.fixture(scope="module")
def model():
    return load_model()


def _standing(model, weight_share=0.5):
    joints = model.joint_vector(model.standing_posture)
    f = model.total_mass * 9.81 * weight_share
    return joints, {s: (np.array([0.0, 0.0, f]), np.zeros(3)) for s in SIDES}


def test_waist_joint_speed_is_not_read_as_a_base_rotation(model):
    """Feet flat and still, base still, the chest turning: the gyro (on the chest) reads the chest's rate; the
    base must come out still and the CoM velocity must be the chest's contribution alone."""
    joints, wrenches = _standing(model)
    v_joints = np.zeros(model.njoints)
    for name, rate in (("chest_pitch", 0.6), ("chest_yaw", -0.4)):
        v_joints[model.joint_names.index(name)] = rate
    est = CentroidalEstimator(model)
    e0 = est.update(0.0, joints, np.zeros(model.njoints), [0, 0, 0, 1], np.zeros(3), wrenches)
    # the IMU's reading for this motion, from the kinematics (the estimator's pose, base twist 0)
    m, d = model.model, model.model.createData()
    v = np.zeros(m.nv)
    v[6:] = v_joints
    pin.forwardKinematics(m, d, e0.q, v)
    pin.updateFramePlacements(m, d)
    imu = model.frame_ids[model.imu_frame]
    R_imu = d.oMf[imu].rotation
    gyro = pin.getFrameVelocity(m, d, imu, pin.ReferenceFrame.LOCAL).angular
    assert np.linalg.norm(gyro) > 0.3
    est.reset()
    e = est.update(0.0, joints, v_joints, pin.Quaternion(R_imu).coeffs(), gyro, wrenches)
    assert np.abs(e.v[:6]).max() < 1e-9                     # the base twist: still
    pin.centerOfMass(m, d, e.q, v)
    assert e.com_velocity == pytest.approx(d.vcom[0], abs=1e-9)
    assert np.linalg.norm(d.vcom[0]) > 0.02                  # the chest moves the CoM: not a trivial zero


def test_fusion_off_is_leg_odometry_and_on_follows_the_ground_reaction(model):
    joints, wrenches = _standing(model)
    still = np.zeros(model.njoints)
    a = np.array([1.0, -0.5, 0.0])   # m/s^2: the ground reaction says the CoM accelerates, kinematics says still
    push = {s: (w[0] + model.total_mass * a / 2, w[1]) for s, w in wrenches.items()}
    off = CentroidalEstimator(model, com_velocity_time_constant=0.0)
    tau = 0.2
    on = CentroidalEstimator(model, com_velocity_time_constant=tau, com_velocity_band=0.0)   # no band: the filter alone
    for est in (off, on):
        est.update(0.0, joints, still, [0, 0, 0, 1], np.zeros(3), wrenches)
    e_off = off.update(DT, joints, still, [0, 0, 0, 1], np.zeros(3), push)
    e_on = on.update(DT, joints, still, [0, 0, 0, 1], np.zeros(3), push)
    assert np.abs(e_off.com_velocity).max() < 1e-9
    assert np.array_equal(e_off.com_velocity_fused, e_off.com_velocity)       # off: the two are one
    assert np.array_equal(e_off.capture_point_fused, e_off.capture_point)
    # the odometry's velocity and capture point do not move with the filter (the fall trigger reads them)
    assert np.array_equal(e_on.com_velocity, e_off.com_velocity)
    assert np.array_equal(e_on.capture_point, e_off.capture_point)
    # one tick: the predicted velocity a dt, pulled towards kinematics (0) by dt / (tau + dt)
    assert e_on.com_velocity_fused[:2] == pytest.approx(a[:2] * DT * tau / (tau + DT), rel=1e-6)
    assert np.linalg.norm(e_on.capture_point_fused[:2] - e_off.capture_point[:2]) > 0
    # the same stamp again (a retransmitted tick): the same answer, not a second integration
    again = on.update(DT, joints, still, [0, 0, 0, 1], np.zeros(3), push)
    assert again.com_velocity_fused == pytest.approx(e_on.com_velocity_fused, abs=1e-15)
    # a steady force bias leaves a velocity bias a tau (what tau trades against slip and impacts)
    t = DT
    for _ in range(3000):
        t += DT
        e_on = on.update(t, joints, still, [0, 0, 0, 1], np.zeros(3), push)
    assert e_on.com_velocity_fused[:2] == pytest.approx(a[:2] * tau, rel=1e-3)
    assert np.abs(e_on.com_velocity).max() < 1e-9
    # a gap in time (or time going back) starts again from kinematics
    e_gap = on.update(t + 0.5, joints, still, [0, 0, 0, 1], np.zeros(3), push)
    assert np.abs(e_gap.com_velocity_fused).max() < 1e-9


def test_the_band_holds_the_fused_velocity_near_the_odometry_and_changes_nothing_inside_it(model):
    """``com_velocity_band``: the fused velocity never strays farther than b from the kinematic one (a push, a
    force bias, an unmeasured contact), and while it stays within b the result is the plain filter's."""
    joints, wrenches = _standing(model)
    still = np.zeros(model.njoints)
    tau, band = 0.2, 0.05

    def run(a, b, ticks):
        est = CentroidalEstimator(model, com_velocity_time_constant=tau, com_velocity_band=b)
        push = {s: (w[0] + model.total_mass * np.asarray(a) / 2, w[1]) for s, w in wrenches.items()}
        est.update(0.0, joints, still, [0, 0, 0, 1], np.zeros(3), wrenches)
        out = [est.update(k * DT, joints, still, [0, 0, 0, 1], np.zeros(3), push).com_velocity_fused
               for k in range(1, ticks + 1)]
        return np.array(out)

    small = [0.2, -0.1, 0.0]        # bias a tau = 4.5 cm/s: inside the band, bit for bit the plain filter
    assert np.array_equal(run(small, band, 400), run(small, 0.0, 400))
    big = [1.0, -0.5, 0.0]          # a tau = 22 cm/s without the band
    plain, held = run(big, 0.0, 3000), run(big, band, 3000)
    assert np.linalg.norm(plain[-1][:2]) == pytest.approx(np.hypot(1.0, 0.5) * tau, rel=1e-3)
    assert np.linalg.norm(held, axis=1).max() <= band + 1e-12
    assert np.linalg.norm(held[-1]) == pytest.approx(band, rel=1e-9)
    assert held[-1][:2] / band == pytest.approx(np.array([1.0, -0.5]) / np.hypot(1.0, 0.5), abs=1e-6)  # same way


# A world where the stance foot slips: the servos' position loop of sessions 1-20 (3.3 ms; today's 20 ms loop walks
# 1.35 km/h with 0.02 mm of slip, docs/walking.md "Session 21"), so the filter has a slip to hide.
SLIPPING_SERVOS = "sim.servo_time_constant=0.003333"


def _walk_cp_errors(tau: float) -> tuple[float, float]:
    """(odometry, fused) capture point error relative to the feet, max over a 4-step 1.35 km/h walk [m]."""
    sc = scenario.load("walking", ["walk.speed_kmh=1.35", "walk.steps=4", SLIPPING_SERVOS,
                                   f"params.state_estimator.com_velocity_time_constant={tau}"])
    loop = ClosedLoop(sc, controllers=[from_scenario(sc, load_model())], track_errors=True)
    try:
        loop.run(6.5)
    finally:
        loop.close()
    return loop.errors["capture_point_error_feet_relative"], loop.errors["capture_point_fused_error_feet_relative"]


def test_fusion_hides_the_stance_foot_slip_from_the_capture_point():
    """1.35 km/h on the slipping servos: the stance foot slides ~40 mm/s at the end of each single support, which
    leg odometry reads as a CoM velocity error (the capture point ~1.3 cm off); with the ground reaction fused,
    under 1 cm. The odometry's own capture point is the same with the filter on or off."""
    odometry_off, fused_off = _walk_cp_errors(0.0)
    odometry, fused = _walk_cp_errors(0.2)
    assert fused_off == odometry_off         # off: one estimate
    assert odometry > 0.01
    assert fused < 0.01 and fused < 0.6 * odometry


def test_constructor_defaults_are_the_declared_ones(model):
    """One place: an estimator built without settings is the node's (config/state_estimator.yaml)."""
    from humfall_ros import params

    declared = params.defaults("state_estimator")
    est = CentroidalEstimator(model)
    assert est.contact_force == declared["contact_force"]
    assert est.com_velocity_time_constant == declared["com_velocity_time_constant"] > 0
    assert est.com_velocity_band == declared["com_velocity_band"]
    assert CentroidalEstimator(model, com_velocity_time_constant=0.0).com_velocity_time_constant == 0.0
