"""EstopController (humfall_ros/estop/controller.py): triggers, phases, bad input, hand-over; a standing stop in
the sim."""
from __future__ import annotations

import dataclasses
import time

import numpy as np
import pytest

from humfall_ros.control.contract import CentroidalObservation, Observation, stamp_ns_of
from humfall_ros.estop.config import EstopConfig
from humfall_ros.estop.controller import TRANSITIONS, EstopController, EstopState, EstopStatus, TopicEvent
from humfall_ros.model.humanoid import load_model
from humfall_ros.sim.world import STANDING_POSTURE

M = load_model()
DT = 0.002


@dataclasses.dataclass
class Pattern:
    """The fields of walking's WalkingState the e-stop reads."""

    walking: bool = True
    support: str = "double"
    phase_fraction: float = 0.0
    step_index: int = 5
    com_ref: np.ndarray = dataclasses.field(default_factory=lambda: np.array([0.06, -0.02, 0.742]))
    com_velocity_ref: np.ndarray = dataclasses.field(default_factory=lambda: np.array([0.2, 0.05, 0.0]))
    zmp_ref: np.ndarray = dataclasses.field(default_factory=lambda: np.array([0.0, -0.09, 0.0]))
    left_foot: tuple = (0.15, 0.09, 0.0, 0.0)
    right_foot: tuple = (0.0, -0.09, 0.0, 0.0)


def obs(t: float, **inputs) -> Observation:
    joints = M.joint_vector(STANDING_POSTURE)
    st = CentroidalObservation(
        com=np.array([0.06, -0.02, 0.742]), com_velocity=np.array([0.2, 0.05, 0.0]), cop=np.array([0.02, -0.09, 0.0]),
        capture_point=np.zeros(3), angular_momentum=np.zeros(3), support_polygon=np.zeros((0, 2)),
        feet_center=np.array([0.075, 0.0, 0.105]), lean_angle=0.0, lean_direction=0.0, normal_force=569.0,
        left_contact=True, right_contact=True, cop_on_edge=False)
    return Observation(stamp_ns_of(t), joints, np.zeros_like(joints), st, "locomotion", dict(inputs))


def test_transition_table_names_every_state():
    assert set(TRANSITIONS) == set(EstopState)
    assert all(isinstance(dst, EstopState) for rules in TRANSITIONS.values() for _, dst in rules)


def test_releases_until_the_scheduled_tick_then_commands():
    ctl = EstopController(M, EstopConfig.defaults(trigger_time=0.01), DT)
    outs = [ctl.step(obs(k * DT, **{"walking/state": Pattern()})) for k in range(8)]
    assert all(o is None for o in outs[:5]) and all(o is not None for o in outs[5:])   # tick 5 is t = 0.01 s
    s = ctl.status
    assert s.state == "stopping" and s.active and s.phase_at_trigger == "double" and s.step_at_trigger == 5
    assert s.trigger_time == pytest.approx(0.01) and s.start_time == pytest.approx(0.01)
    assert s.alpha == pytest.approx(-s.omega_c) and s.beta < s.alpha and np.isfinite(s.n_major).all()
    assert s.feasible and s.reason == ""
    fields = {f.name for f in dataclasses.fields(EstopStatus)}
    assert {"omega_f", "gains_minor", "gains_major", "n_minor_re", "max_zmp_minor", "max_zmp_major", "crouch"} <= fields


def test_single_support_trigger_waits_for_double_support_and_starts_from_its_state():
    ctl = EstopController(M, EstopConfig.defaults(), DT)
    ss = Pattern(support="single_left", phase_fraction=0.5)
    assert ctl.step(obs(0.0, estop=True, **{"walking/state": ss})) is None
    assert ctl.state == EstopState.WAITING and not ctl.status.active
    assert ctl.step(obs(DT, estop=True, **{"walking/state": ss})) is None
    ds = Pattern(com_ref=np.array([0.08, -0.01, 0.742]))
    assert ctl.step(obs(2 * DT, estop=True, **{"walking/state": ds})) is not None
    assert ctl.state == EstopState.STOPPING and ctl.status.phase_at_trigger == "single_left"
    np.testing.assert_allclose(ctl.plan.state.com, ds.com_ref)       # planned from the double-support tick
    assert ctl.status.start_time == pytest.approx(2 * DT)


def test_step_and_phase_trigger():
    # scenario step 3 = the 4th swing: its single support shows step_index 4 in walking/state
    ctl = EstopController(M, EstopConfig.defaults(trigger_step=3, trigger_phase="ss_end"), DT)
    for frac, index in ((0.5, 4), (0.9, 4), (0.97, 3)):
        assert ctl.step(obs(0.0, **{"walking/state": Pattern(support="single_right", phase_fraction=frac,
                                                             step_index=index)})) is None
        assert ctl.state == EstopState.IDLE
    ctl.step(obs(DT, **{"walking/state": Pattern(support="single_right", phase_fraction=0.96, step_index=4)}))
    assert ctl.state == EstopState.WAITING and ctl.status.phase_fraction_at_trigger == pytest.approx(0.96)
    # its double support (before that swing) shows step_index 3
    ctl = EstopController(M, EstopConfig.defaults(trigger_step=3, trigger_phase="ds_mid"), DT)
    assert ctl.step(obs(0.0, **{"walking/state": Pattern(phase_fraction=0.6, step_index=4)})) is None
    assert ctl.step(obs(DT, **{"walking/state": Pattern(phase_fraction=0.4, step_index=3)})) is None
    assert ctl.step(obs(2 * DT, **{"walking/state": Pattern(phase_fraction=0.5, step_index=3)})) is not None


def test_bad_input_rules():
    # a second trigger during a stop is ignored; a fall hands over to safe-fall but the robot keeps a command
    ctl = EstopController(M, EstopConfig.defaults(), DT)
    first = ctl.step(obs(0.0, estop=True, **{"walking/state": Pattern()}))
    assert first is not None
    ctl.step(obs(DT, estop=False, **{"walking/state": Pattern()}))
    assert ctl.step(obs(2 * DT, estop=True, **{"walking/state": Pattern()})) is not None
    assert any("ignored" in m for m in ctl.messages)
    out = ctl.step(obs(3 * DT, fall_event=True, **{"walking/state": Pattern()}))
    assert ctl.state == EstopState.YIELDED and out is not None and "safe-fall" in ctl.status.reason
    # a trigger while falling does not take over
    ctl = EstopController(M, EstopConfig.defaults(), DT)
    assert ctl.step(obs(0.0, estop=True, fall_event=True, **{"walking/state": Pattern()})) is None
    assert ctl.state == EstopState.YIELDED and not ctl.status.active
    # a CoG height outside the model: refused, nothing taken over
    ctl = EstopController(M, EstopConfig.defaults(), DT)
    low = Pattern(com_ref=np.array([0.06, -0.02, 0.3]))
    assert ctl.step(obs(0.0, estop=True, **{"walking/state": low})) is None
    assert ctl.state == EstopState.REFUSED and "CoG height" in ctl.status.reason
    # a trigger before the state is known stays pending and acts on the first known state
    ctl = EstopController(M, EstopConfig.defaults(), DT)
    unknown = obs(0.0, estop=True)
    unknown.state.normal_force = 0.0
    assert ctl.step(unknown) is None and ctl.pending
    assert ctl.step(obs(DT, estop=True, **{"walking/state": Pattern()})) is not None


def test_never_releases_while_moving_and_releases_when_held_still():
    # the feet step of the return home is off here (tested in test_estop_align.py): the release rule alone
    ctl = EstopController(M, EstopConfig.defaults(home_duration=0.2, align_feet=False), DT)
    ctl.step(obs(0.0, estop=True, **{"walking/state": Pattern()}))
    assert ctl.step(obs(DT, estop=True, estop_release=True, **{"walking/state": Pattern()})) is not None
    assert any("release refused" in m for m in ctl.messages)
    t, k = 2 * DT, 2
    end = ctl.plan.end_time + 0.3
    while t < end:
        assert ctl.step(obs(t, estop=True, **{"walking/state": Pattern()})) is not None
        k += 1
        t = k * DT
    assert ctl.state == EstopState.HOLDING
    still = obs(t, estop=True, estop_release=True, **{"walking/state": Pattern()})
    still.state.com_velocity = still.state.com_velocity_fused = np.zeros(3)   # the release reads the fused one
    assert ctl.step(still) is None and ctl.state == EstopState.IDLE and not ctl.status.active


def _standing_stop(push_force: float):
    """Stand, push forward 0.2 s, trigger at the push's end; the e-stop stops the standing robot."""
    from humfall_ros.control.contract import centroidal_from_estimate
    from humfall_ros.control.standing import StandingBalance
    from humfall_ros.model.estimation import CentroidalEstimator
    from humfall_ros.model.humanoid import point_in_polygon_margin
    from humfall_ros.sim.sensors import Sensors
    from humfall_ros.sim.world import SimWorld

    world = SimWorld(1000.0, 500.0, initial_posture=STANDING_POSTURE)
    try:
        sensors, est = Sensors(world), CentroidalEstimator(world.model)
        balance = StandingBalance(world.model, STANDING_POSTURE)
        ctl = EstopController(world.model, EstopConfig.defaults(trigger_time=0.7), DT)
        world.add_push((push_force, 0.0, 0.0), duration=0.2, start=0.5)
        rows = []
        for _ in range(int(4.5 / DT)):
            r = sensors.read()
            e = est.update(world.time, r.joint_position, r.joint_velocity, r.imu_orientation, r.gyro, r.wrenches)
            cmd = ctl.step(Observation(stamp_ns_of(world.time), r.joint_position, r.joint_velocity,
                                       centroidal_from_estimate(e), joint_targets=world.targets.copy()))
            if cmd is None:
                world.set_joint_targets(balance.command(e.com, e.com_velocity, e.support_polygon, e.feet_center))
            else:
                world.set_joint_targets(cmd.positions, cmd.velocities)
            rows.append((world.time, e.com - e.feet_center, np.hypot(*e.com_velocity[:2]),
                         point_in_polygon_margin(e.cop, e.support_polygon), world.trunk_tilt(), cmd is not None))
            world.step_control()
        return ctl, rows
    finally:
        world.close()


def test_standing_robot_stops_in_the_simulator():
    t0 = time.perf_counter()
    ctl, rows = _standing_stop(100.0)     # at the trigger the CoP is on the toe line, the CoG moving at 4 cm/s
    wall = time.perf_counter() - t0
    plan = ctl.plan
    assert plan is not None and plan.feasible, plan and plan.reason
    t = np.array([r[0] for r in rows])
    taken = np.array([r[5] for r in rows])
    start = t[np.argmax(taken)]
    assert start == pytest.approx(0.7, abs=DT) and taken[t >= start].all()          # never released once taken
    tilt = max(r[4] for r in rows)
    assert tilt < np.radians(3.0)                                                      # no fall
    margins = np.array([r[3] for r in rows])
    # the feet stay down (a lone tick as the sole rocks back from the toe line reads no contact)
    assert np.mean(np.isfinite(margins[t >= start])) > 0.99
    # taken over with the CoP on the toe line, the soles rock for ~0.35 s (tilt <= 0.31 deg), then
    # the CoP stays 1 cm inside the polygon
    assert np.min(margins[t >= start + 0.5]) >= 0.01
    speed = np.array([r[2] for r in rows])
    v0 = float(np.hypot(*plan.state.com_velocity[:2]))
    settle = start + np.log(max(v0, 0.011) / 0.01) / plan.omega_c + 0.3 + 0.5
    assert np.all(speed[t >= settle] < 0.01)
    # the final CoG relative to the feet: on the feet's centre line (Minor) and at n3 (Major)
    mid_feet = 0.5 * (plan.state.feet["l"].position + plan.state.feet["r"].position)
    final_rel = plan.final_com - mid_feet
    np.testing.assert_allclose(rows[-1][1][:2], final_rel[:2], atol=0.01)
    print(f"standing stop: v0 {v0:.3f} m/s, max tilt {np.degrees(tilt):.2f} deg, wall {wall:.1f} s")


def test_topic_events_trigger_and_release_once_each():
    # the node turns every estop / estop/release message into a new TopicEvent; the latched value stays
    ctl = EstopController(M, EstopConfig.defaults(home_duration=0.1, terminal_tolerance=1e-3, align_feet=False), DT)
    trig, rel = TopicEvent(1), TopicEvent(1)
    assert ctl.step(obs(0.0, estop=trig, **{"walking/state": Pattern()})) is not None
    assert ctl.step(obs(DT, estop=trig, estop_release=rel, **{"walking/state": Pattern()})) is not None
    assert any("release refused" in m for m in ctl.messages)                 # moving: refused, and used up
    t, k = 2 * DT, 2
    while ctl.state != EstopState.HOLDING:
        assert ctl.step(obs(t, estop=trig, estop_release=rel, **{"walking/state": Pattern()})) is not None
        k += 1
        t = k * DT
        assert t < ctl.plan.end_time + 1.0
    still = obs(t, estop=trig, estop_release=rel, **{"walking/state": Pattern()})
    still.state.com_velocity = still.state.com_velocity_fused = np.zeros(3)   # the release reads the fused one
    assert ctl.step(still) is not None and ctl.state == EstopState.HOLDING    # the old release is not re-used
    still.inputs["estop_release"] = TopicEvent(2)
    still.stamp_ns += stamp_ns_of(DT)
    assert ctl.step(still) is None and ctl.state == EstopState.IDLE
    still.stamp_ns += stamp_ns_of(DT)
    assert ctl.step(still) is None and ctl.state == EstopState.IDLE           # the latched trigger: no new one
    still.inputs["estop"] = TopicEvent(2)
    still.stamp_ns += stamp_ns_of(DT)
    assert ctl.step(still) is not None and ctl.state == EstopState.STOPPING   # a second `humfall estop`
    ctl.reset()                                                                # sim time went back
    still.inputs["estop"] = TopicEvent(2)
    assert ctl.step(still) is None and ctl.state == EstopState.IDLE           # the latched message: not again


def test_feet_are_held_where_the_applied_targets_put_them():
    """Bumpless feet: the IK holds both feet where the applied joint targets have them at the take-over (walking's
    sole sinkage / ankle offsets), not at the pattern's flat poses; the rear foot sits at its pattern pose."""
    import pinocchio as pin

    from humfall_ros.estop.controller import feet_from_soles

    ctl = EstopController(M, EstopConfig.defaults(trigger_time=0.0), DT)
    applied = M.joint_vector(STANDING_POSTURE)
    applied[M.joint_index("l_ankle_pitch")] += 0.03           # a walking ankle offset on the front foot
    pattern = Pattern()
    out = None
    for k in range(20):
        o = dataclasses.replace(obs(k * DT, **{"walking/state": pattern}), joint_targets=applied.copy())
        out = ctl.step(o)
    assert out is not None and ctl.state == EstopState.STOPPING
    d = M.model.createData()
    pin.framesForwardKinematics(M.model, d, ctl.q_ik)
    feet = {s: d.oMf[M.frame_ids[M.foot_link[s]]] for s in "lr"}
    for s in "lr":
        assert np.linalg.norm(feet[s].translation - ctl._hold_feet[s].translation) < 1e-3
        assert np.linalg.norm(pin.log3(feet[s].rotation.T @ ctl._hold_feet[s].rotation)) < 2e-3
    rear = feet_from_soles(M, {"l": pattern.left_foot, "r": pattern.right_foot})["r"]
    assert np.linalg.norm(ctl._hold_feet["r"].translation - rear.position) < 1e-9
    # the front foot is not moved to the pattern's (0.15 m ahead): the applied legs' geometry is kept
    pitch = [M.joint_index(f"{s}_ankle_pitch") for s in "lr"]
    assert out.positions[pitch[0]] - out.positions[pitch[1]] == pytest.approx(0.03, abs=3e-3)


def test_a_yawed_robot_result_is_measured_in_the_stop_frame_on_its_measured_feet():
    """The robot stands 15 deg yawed and 0.3 m off its pattern (the estimator's world vs walking's): the status
    carries the stop frame carried onto the measured feet (IMU yaw, measured joints, estimated feet centre), and
    result.json's section measured in it reads the stop as planned; in the pattern's frame it is 5+ cm off."""
    import math

    import pinocchio as pin

    from humfall_ros.estop.controller import measured_sole_centers
    from humfall_ros.estop.metrics import estop_result
    from humfall_ros.model.humanoid import point_in_polygon_margin

    yaw, shift = math.radians(15.0), np.array([0.3, -0.1])
    Rz = np.array([[math.cos(yaw), -math.sin(yaw), 0.0], [math.sin(yaw), math.cos(yaw), 0.0], [0.0, 0.0, 1.0]])
    joints = M.joint_vector(STANDING_POSTURE)
    d = M.model.createData()
    pin.framesForwardKinematics(M.model, d, M.configuration([0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0], joints))
    soles = {s: d.oMf[M.frame_ids[M.sole_frame[s]]].translation.copy() for s in "lr"}
    ankles = {s: d.oMf[M.frame_ids[M.foot_link[s]]].translation.copy() for s in "lr"}
    pattern = Pattern(left_foot=(soles["l"][0], soles["l"][1], 0.0, 0.0),
                      right_foot=(soles["r"][0], soles["r"][1], 0.0, 0.0),
                      com_ref=np.array([0.5 * (soles["l"][0] + soles["r"][0]), 0.0, 0.74]),
                      zmp_ref=np.array([soles["r"][0], soles["r"][1] + 0.03, 0.0]))
    imu = Rz @ d.oMf[M.frame_ids[M.imu_frame]].rotation
    q = pin.Quaternion(imu).coeffs()                                 # x, y, z, w
    mid = 0.5 * (ankles["l"] + ankles["r"])
    feet_center = Rz @ mid + np.array([*shift, 0.0])
    meas = measured_sole_centers(M, joints, feet_center, q)
    from humfall_ros.estop.frame import FootPose

    for s in "lr":                                                  # the soles turned and shifted with the robot
        c = FootPose(ankles[s], d.oMf[M.frame_ids[M.foot_link[s]]].rotation).sole_center(M, s)
        np.testing.assert_allclose(meas[s][:2], (Rz @ (c - mid))[:2] + feet_center[:2], atol=1e-6)
    ctl = EstopController(M, EstopConfig.defaults(trigger_time=0.0), DT)
    o = obs(0.0, **{"walking/state": pattern, "imu": (q, np.zeros(3))})
    o = dataclasses.replace(o, state=dataclasses.replace(o.state, feet_center=feet_center))
    assert ctl.step(o) is not None and ctl.state == EstopState.STOPPING, ctl.messages
    s, plan = ctl.status, ctl.plan
    assert s.feet_yaw_off_pattern == pytest.approx(yaw, abs=1e-6)
    np.testing.assert_allclose(s.feet_major_axis, Rz[:2, :2] @ plan.frame.major, atol=1e-6)
    moved_origin = Rz[:2, :2] @ (plan.frame.origin - mid[:2]) + feet_center[:2]
    np.testing.assert_allclose(s.feet_frame_origin, moved_origin, atol=1e-6)
    assert len(s.feet_support_polygon) == len(plan.support_polygon)
    # the robot plays the plan exactly, in its own (yawed, shifted) world
    t = np.arange(0.0, plan.end_time + 0.5, DT)
    refs = [plan.sample(x) for x in t]

    def carried(p):
        return np.array([*(Rz[:2, :2] @ (np.asarray(p)[:2] - mid[:2]) + feet_center[:2]), 0.0])

    com = np.array([[*carried(r.com)[:2], r.com[2]] for r in refs])
    cop = np.array([carried(r.zmp) for r in refs])
    poly = np.asarray(s.feet_support_polygon)
    margin = np.array([point_in_polygon_margin(p, poly) for p in cop])
    res = estop_result(plan, t, com, cop, margin, 0.0, False, frame=ctl.feet_frame, polygon=ctl.feet_polygon)
    assert res["final_cog_major_m"] == pytest.approx(plan.major.n3, abs=1e-6)
    assert res["final_cog_minor_m"] == pytest.approx(0.0, abs=1e-6)
    assert res["max_cop_minor_m"] == pytest.approx(abs(plan.minor.max_zmp), abs=2e-3)
    assert res["min_cop_margin_m"] >= plan.min_zmp_margin - 2e-3
    assert res["stop_time_s"] == pytest.approx(plan.stop_time, abs=0.02)
    old = estop_result(plan, t, com, cop, margin, 0.0, False)          # the pattern's frame: wrong
    assert math.hypot(old["final_cog_major_m"] - plan.major.n3, old["final_cog_minor_m"]) > 0.05


def test_a_standing_stop_takes_the_feet_heading_from_the_imu():
    """Without walking/state the stop places the feet from the joints; their heading comes from the IMU (a robot that
    has turned stops in its own frame), as the estimator places them. Without an IMU the heading is 0."""
    import math

    import pinocchio as pin

    from humfall_ros.estop.controller import feet_from_joints
    from humfall_ros.model.humanoid import SIDES

    m = load_model()
    joints = m.joint_vector(STANDING_POSTURE)
    d = m.model.createData()
    pin.framesForwardKinematics(m.model, d, m.configuration([0, 0, 0], [0, 0, 0, 1], joints))
    imu_in_base = d.oMf[m.frame_ids[m.imu_frame]].rotation

    def heading(feet):
        x = sum(feet[s].rotation[:, 0] for s in SIDES)
        return math.atan2(x[1], x[0])

    center = np.array([0.4, -0.2])
    for yaw in (0.0, 0.7, -2.0):
        Rz = pin.utils.rpyToMatrix(0.0, 0.0, yaw)
        quat = pin.Quaternion(Rz @ imu_in_base).coeffs()       # x, y, z, w
        feet = feet_from_joints(m, joints, center, imu_orientation=quat)
        assert heading(feet) == pytest.approx(yaw, abs=1e-9)
        left_of = feet["l"].position[:2] - feet["r"].position[:2]
        assert math.atan2(left_of[1], left_of[0]) == pytest.approx(yaw + math.pi / 2, abs=0.05)
        mid = 0.5 * (feet["l"].position[:2] + feet["r"].position[:2])
        assert np.allclose(mid, center, atol=1e-9)
        assert all(abs(feet[s].position[2] - feet["l"].position[2]) < 1e-9 for s in SIDES)
    assert heading(feet_from_joints(m, joints, center)) == pytest.approx(0.0, abs=1e-9)


def test_per_foot_cop_damping_turns_a_loaded_ankle_against_its_own_cop_error():
    """``foot_cop_gain`` (walking's loop 5 in the stop): a loaded sole whose own CoP is ahead of its share of the
    stop's ZMP reference turns its toes up (ankle pitch down) against the error, at a rate that grows with the
    gain; a sole under ``foot_cop_min_force`` is left alone; with gain 0 the commands are the stop's own."""
    pattern = Pattern()

    def run(gain: float, right_force: float) -> np.ndarray:
        ctl = EstopController(M, EstopConfig.defaults(trigger_time=0.0, foot_cop_gain=gain), DT)
        out = None
        for k in range(60):
            o = obs(k * DT, **{"walking/state": pattern})
            st = dataclasses.replace(o.state, left_normal_force=400.0, right_normal_force=right_force,
                                     left_cop=np.array([0.30, 0.09, 0.0]), right_cop=np.array([0.025, -0.09, 0.0]))
            out = ctl.step(dataclasses.replace(o, state=st))
        assert ctl.state == EstopState.STOPPING
        return out.positions

    pitch = {s: M.joint_index(f"{s}_ankle_pitch") for s in "lr"}
    off, on, strong = run(0.0, 200.0), run(1.0, 200.0), run(4.0, 200.0)
    d_on, d_strong = on - off, strong - off
    assert d_on[pitch["l"]] < -1e-4                              # the left CoP is 10+ cm ahead of its share
    assert d_strong[pitch["l"]] < 2 * d_on[pitch["l"]]           # faster with a larger gain
    light = run(1.0, 100.0) - off                                # right sole under 150 N: no correction there
    assert abs(light[pitch["r"]]) < 1e-9 and abs(d_on[pitch["r"]]) > 1e-6
    others = np.ones(len(off), bool)
    others[[pitch["l"], pitch["r"], M.joint_index("l_ankle_roll"), M.joint_index("r_ankle_roll")]] = False
    assert np.allclose(d_on[others], 0.0, atol=1e-12)            # only the ankles


def _stop(cfg: dict, ticks: int, left_force: float = 300.0, right_force: float = 269.0, imu=None):
    """A stop from ``Pattern()`` (left foot ahead) run ``ticks`` ticks with the given per-foot forces / IMU."""
    pattern = Pattern()
    ctl = EstopController(M, EstopConfig.defaults(trigger_time=0.0, **cfg), DT)
    out = None
    for k in range(ticks):
        inputs = {"walking/state": pattern} if imu is None else {"walking/state": pattern, "imu": imu}
        o = obs(k * DT, **inputs)
        st = dataclasses.replace(o.state, left_normal_force=left_force, right_normal_force=right_force,
                                 left_cop=np.array([0.175, 0.09, 0.0]), right_cop=np.array([0.025, -0.09, 0.0]))
        out = ctl.step(dataclasses.replace(o, state=st))
    assert ctl.state in (EstopState.STOPPING, EstopState.STOPPED)
    return ctl, out


def test_sole_sinkage_moves_the_held_feet_with_the_stops_load_split():
    """``sole_sinkage_gain`` (walking's sinkage feed-forward in the stop): as the stop's ZMP reference moves onto
    the front (left) sole, its held target goes down and the rear one's up, by the load change over the URDF
    sole stiffness (at most the weight over it), twice as far with gain 2; gain 0 holds the feet as at the start."""
    from humfall_ros.walking.compliance import sole_contact

    stiffness, _ = sole_contact(M)
    weight = M.total_mass * 9.81
    moved = {}
    for g in (0.0, 1.0, 2.0):
        ctl, _ = _stop({"sole_sinkage_gain": g}, 10)
        end = ctl.plan.stop_time + 0.5            # the reference at rest: no damper lead left
        held = ctl._held_feet(end)
        moved[g] = {s: held[s].translation[2] - ctl._hold_feet[s].translation[2] for s in "lr"}
        for s in "lr":
            assert np.allclose(held[s].rotation, ctl._hold_feet[s].rotation)
            assert np.allclose(held[s].translation[:2], ctl._hold_feet[s].translation[:2])
    assert moved[0.0] == {"l": 0.0, "r": 0.0}
    front, rear = moved[1.0]["l"], moved[1.0]["r"]
    assert front < -1e-5 and rear > 1e-5                          # the load moved forward: front in, rear out
    assert abs(front) < 1.01 * weight / stiffness and abs(rear) < 1.01 * weight / stiffness
    assert front + rear == pytest.approx(0.0, abs=0.1 * abs(front))  # one load moved from one sole to the other
    assert moved[2.0]["l"] == pytest.approx(2 * front, rel=1e-9)


def test_sole_flat_turns_each_loaded_ankle_against_its_soles_measured_tilt():
    """``sole_flat_gain``: the IMU reads the trunk pitched 3 mrad forward and rolled 2 mrad over the standing joints,
    so both soles read toes down and their +y edges up: each loaded ankle turns toes up and its +y edge down
    (pitch and roll offsets < 0), bounded by ``sole_flat_max`` and leaking; a sole under ``sole_flat_min_force`` is
    left alone; only the ankles change."""
    import pinocchio as pin

    d = M.model.createData()
    q0 = M.configuration([0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0], M.joint_vector(STANDING_POSTURE))
    pin.framesForwardKinematics(M.model, d, q0)
    R_imu = pin.rpy.rpyToMatrix(0.002, 0.003, 0.0) @ d.oMf[M.frame_ids[M.imu_frame]].rotation
    imu = (pin.Quaternion(R_imu).coeffs().copy(), np.zeros(3))
    pitch = {s: M.joint_index(f"{s}_ankle_pitch") for s in "lr"}
    roll = {s: M.joint_index(f"{s}_ankle_roll") for s in "lr"}
    _, off = _stop({"sole_flat_gain": 0.0}, 100, right_force=100.0, imu=imu)
    ctl, on = _stop({"sole_flat_gain": 20.0, "sole_flat_min_force": 150.0}, 100, right_force=100.0, imu=imu)
    d_on = on.positions - off.positions
    assert d_on[pitch["l"]] < -1e-3 and d_on[roll["l"]] < -5e-4          # loaded: toes up, +y edge down
    assert abs(d_on[pitch["r"]]) < 1e-12 and abs(d_on[roll["r"]]) < 1e-12  # 100 N < 150 N: untouched
    # a steady 3 mrad tilt: the leaky offset is the first-order response towards -gain * T * tilt (18 mrad)
    t = 100 * DT
    assert d_on[pitch["l"]] == pytest.approx(-20.0 * 0.3 * 0.003 * (1.0 - np.exp(-t / 0.3)), rel=0.05)
    _, capped = _stop({"sole_flat_gain": 20.0, "sole_flat_max": 0.005}, 100, right_force=100.0, imu=imu)
    assert (capped.positions - off.positions)[pitch["l"]] == pytest.approx(-0.005, abs=1e-9)
    others = np.ones(len(off.positions), bool)
    others[[pitch["l"], pitch["r"], roll["l"], roll["r"]]] = False
    assert np.allclose(d_on[others], 0.0, atol=1e-12)


def test_foot_force_difference_lifts_the_overloaded_held_sole():
    """``foot_force_gain`` (walking's loop 4 with forces in the stop): the left sole carries 549 of 569 N while the
    stop's ZMP reference starts on the right sole: the left held target goes up and the right one's down, by half
    the loop's difference each, within ``foot_height_max``; gain 0 leaves the held feet alone."""
    import pinocchio as pin

    def feet_z(ctl):
        d = M.model.createData()
        pin.framesForwardKinematics(M.model, d, ctl.q_ik)
        return {s: d.oMf[M.frame_ids[M.foot_link[s]]].translation[2] - ctl._hold_feet[s].translation[2]
                for s in "lr"}

    base, _ = _stop({"foot_force_gain": 0.0}, 40, left_force=549.0, right_force=20.0)
    ctl, _ = _stop({"foot_force_gain": 3e-5}, 40, left_force=549.0, right_force=20.0)
    z0, z = feet_z(base), feet_z(ctl)
    dl, dr = z["l"] - z0["l"], z["r"] - z0["r"]
    assert dl > 1e-5 and dr < -1e-5 and dl == pytest.approx(-dr, rel=0.05)
    assert dl - dr <= 0.0005 + 1e-6                      # foot_height_max


def test_quintic_blend_starts_and_ends_the_start_offset_without_a_velocity_step():
    """``blend_profile``: the IK model's CoG minus the plan's (the start offset) goes out over ``BLEND_TIME``;
    linear, its rate jumps by offset / BLEND_TIME at the start and at the end (a CoP spike on the robot: measured
    at 1.8 km/h, 2 cm past n3 at 0.32 s); quintic, the rate is ~0 at both ends; both end on the plan."""
    from humfall_ros.estop.controller import BLEND_TIME

    applied = M.joint_vector(STANDING_POSTURE)
    for j in ("l_hip_pitch", "r_hip_pitch"):
        applied[M.joint_index(j)] -= 0.05                 # the trunk leant: a CoG offset to blend out
    rates = {}
    for profile in ("linear", "quintic"):
        ctl = EstopController(M, EstopConfig.defaults(trigger_time=0.0, blend_profile=profile), DT)
        off = []
        for k in range(int(1.3 * BLEND_TIME / DT)):
            o = dataclasses.replace(obs(k * DT, **{"walking/state": Pattern()}), joint_targets=applied.copy())
            ctl.step(o)
            t = k * DT - ctl._t_start
            off.append(M.com(ctl.q_ik)[:2] - ctl.plan.sample(t).com[:2])
        off = np.array(off)
        rates[profile] = np.linalg.norm(np.diff(off, axis=0), axis=1) / DT
        assert np.linalg.norm(off[-1]) < 1e-3                      # on the plan after the blend
        offset0 = np.linalg.norm(ctl._offset0[:2])
    assert offset0 > 0.005
    k_end = int(BLEND_TIME / DT)
    lin, quin = rates["linear"], rates["quintic"]
    assert lin[2] > 0.5 * offset0 / BLEND_TIME and lin[k_end + 3] < 0.2 * lin[2]   # linear: on, then off
    assert quin[2] < 0.1 * lin[2] and quin[k_end - 3] < 0.1 * lin[2]             # quintic: ~0 at both ends


def test_flatten_held_feet_turns_a_tilted_held_foot_flat_over_the_blend():
    """``flatten_held_feet``: the take-over holds the front foot where walking's ankle offset (0.03 rad) tipped it;
    over the start blend the held pose goes flat (roll, pitch 0, yaw and position kept); without it, it stays tipped."""
    import pinocchio as pin

    from humfall_ros.estop.controller import BLEND_TIME

    applied = M.joint_vector(STANDING_POSTURE)
    applied[M.joint_index("l_ankle_pitch")] += 0.03
    tilt = {}
    for flat in (False, True):
        ctl = EstopController(M, EstopConfig.defaults(trigger_time=0.0, flatten_held_feet=flat), DT)
        for k in range(int(1.2 * BLEND_TIME / DT)):
            ctl.step(dataclasses.replace(obs(k * DT, **{"walking/state": Pattern()}), joint_targets=applied.copy()))
        start = ctl._hold_feet["l"]
        held = ctl._held_feet(1.2 * BLEND_TIME)["l"]
        d = M.model.createData()
        pin.framesForwardKinematics(M.model, d, ctl.q_ik)
        ik_foot = d.oMf[M.frame_ids[M.foot_link["l"]]]
        up = ik_foot.rotation[:, 2]
        tilt[flat] = float(np.arccos(np.clip(up[2], -1.0, 1.0)))
        assert np.linalg.norm(held.translation[:2] - start.translation[:2]) < 1e-12
        yaw = [float(np.arctan2(R[1, 0], R[0, 0])) for R in (held.rotation, start.rotation)]
        assert yaw[0] == pytest.approx(yaw[1], abs=1e-9)
    assert tilt[False] == pytest.approx(0.03, abs=3e-3)
    assert tilt[True] < 1e-3


def test_the_final_posture_check_holds_the_arms_where_eq_23_stops_them():
    """The stop's final-posture check sees the upper body where the joints' stop (eq. 23) will leave it, not where the
    arms are at the trigger: a swinging arm ends a third of its velocity times T_b further on."""
    from humfall_ros.estop.statespace import return_home

    ctl = EstopController(M, EstopConfig.defaults(trigger_time=0.0), DT)
    k = M.joint_index("r_shoulder_pitch")
    o = obs(0.0, **{"walking/state": Pattern()})
    v = np.zeros_like(o.joint_position)
    v[k] = 1.5                                               # the arm swinging forward at the trigger
    ctl.step(dataclasses.replace(o, joint_velocity=v))
    assert ctl.state == EstopState.STOPPING
    upper = np.array([not any(j in n for j in ("hip", "knee", "ankle")) for n in M.joint_names])
    end = return_home(o.joint_position[upper], v[upper], ctl._t_b, ctl._t_b)[0]
    checked = ctl.plan.posture.q[7:][upper]
    i = int(np.flatnonzero(np.flatnonzero(upper) == k)[0])
    assert ctl._t_b > 0.0 and end[i] - o.joint_position[k] == pytest.approx(1.5 * ctl._t_b / 3.0)
    assert checked[i] == pytest.approx(end[i], abs=5e-3)      # the check's arm at eq. 23's end, not at the trigger
