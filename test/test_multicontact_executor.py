"""The multicontact executor as a contract controller, on synthetic observations (no simulator)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from humfall_ros.control.contract import CentroidalObservation, Controller, Observation, stamp_ns_of
from humfall_ros.model.humanoid import load_model as load_humanoid
from humfall_ros.multicontact.collocation import Segment
from humfall_ros.multicontact.executor import (ExecutorConfig, MulticontactExecutor, StoredPlan, planned_contacts,
                                               project_to_mode)
from humfall_ros.multicontact.model import load_model


@pytest.fixture(scope="module")
def models():
    return load_model(), load_humanoid()


def _segment(pm, q0, q1, T, change="", ext="", mode=("RF",), target=("RF",)):
    N = 4
    t = np.linspace(0, T, N)
    q = np.linspace(q0, q1, N)
    v = np.tile((q1 - q0) / T, (N, 1))
    return Segment(kind="transition" if change else "self_motion", mode=mode, target_mode=target, change=change,
                   extremity=ext, time=t, q=q, v=v, a=np.zeros_like(q), u=np.zeros((N, pm.m)), lam=np.zeros((N, 0)),
                   rows=[], ke=np.zeros(N), success=True, status="test", iterations=0, nlp_time=0.0,
                   seed_duration=T, attempts=1, max_violation=0.0)


def _obs(hm, t, left=False, right=True, q=None):
    z3 = np.zeros(3)
    st = CentroidalObservation(com=z3, com_velocity=z3, cop=z3, capture_point=z3, angular_momentum=z3,
                               support_polygon=np.zeros((0, 2)), feet_center=z3, lean_angle=0.0,
                               lean_direction=0.0, normal_force=0.0, left_contact=left, right_contact=right,
                               cop_on_edge=False)
    n = len(hm.joint_names)
    return Observation(stamp_ns=stamp_ns_of(t), joint_position=np.full(n, 0.05) if q is None else q,
                       joint_velocity=np.zeros(n), state=st)


def test_executor_tracks_the_plan_holds_the_rest_and_switches_on_touchdown(models):
    pm, hm = models
    q0 = np.zeros(pm.n)
    q1 = q0.copy()
    q1[3:] = np.linspace(0.1, 1.0, pm.m)
    q2 = q1.copy()
    q2[3:] += 0.2
    landing = _segment(pm, q0, q1, 0.4, "add", "LF", ("RF",), ("LF", "RF"))
    settle = _segment(pm, q1, q2, 0.6, mode=("LF", "RF"), target=("LF", "RF"))
    ex = MulticontactExecutor([landing, settle], pm.joint_names, hm.joint_names, ExecutorConfig(hold="measured"))
    assert isinstance(ex, Controller) and ex.source == "multicontact"
    idx = [hm.joint_names.index(j) for j in pm.joint_names]
    others = [i for i in range(len(hm.joint_names)) if i not in idx]
    t0 = 3.0
    first = ex.step(_obs(hm, t0))
    np.testing.assert_allclose(first.positions[idx], q0[3:])
    np.testing.assert_allclose(first.positions[others], 0.05)                  # held where they were
    mid = ex.step(_obs(hm, t0 + 0.2))
    want, dwant = MulticontactExecutor.sample(landing, 0.2)
    np.testing.assert_allclose(mid.positions[idx], want)
    np.testing.assert_allclose(mid.velocities[idx], dwant)
    np.testing.assert_allclose(mid.velocities[others], 0.0)
    # the foot touches down 0.1 s early: the next segment starts then
    ex.step(_obs(hm, t0 + 0.3, left=True))
    assert ex.switches == [(1, pytest.approx(0.3), "touchdown")]
    after = ex.step(_obs(hm, t0 + 0.6, left=True))
    np.testing.assert_allclose(after.positions[idx], MulticontactExecutor.sample(settle, 0.3)[0])
    # past the plan: the final posture, no velocity
    end = ex.step(_obs(hm, t0 + 5.0, left=True))
    np.testing.assert_allclose(end.positions[idx], q2[3:])
    np.testing.assert_allclose(end.velocities, 0.0)


def test_executor_waits_for_a_late_touchdown_then_moves_on(models):
    pm, hm = models
    q0 = np.zeros(pm.n)
    q1 = q0.copy()
    q1[3:] = 0.3
    landing = _segment(pm, q0, q1, 0.4, "add", "LF", ("RF",), ("LF", "RF"))
    settle = _segment(pm, q1, q1, 0.5, mode=("LF", "RF"), target=("LF", "RF"))
    ex = MulticontactExecutor([landing, settle], pm.joint_names, hm.joint_names)
    ex.step(_obs(hm, 0.0))
    held = ex.step(_obs(hm, 0.5))                     # planned end passed, the foot still in the air
    assert ex.switches == [] and np.allclose(held.velocities, 0.0)
    np.testing.assert_allclose(held.positions[[hm.joint_names.index(j) for j in pm.joint_names]], q1[3:])
    ex.step(_obs(hm, 0.65))                           # landing_wait (0.2 s) over
    assert ex.switches and ex.switches[0][2] == "landing wait over"
    ex.reset()
    assert ex.switches == [] and ex._t0 is None
    with pytest.raises(ValueError, match="not in the robot"):
        MulticontactExecutor([landing], ["no_such_joint"], hm.joint_names)


def test_planar_state_of_a_sagittal_3d_state_puts_the_points_where_the_3d_model_has_them(models):
    """The executor's bridge from the 3-D robot to the planner: for a state in the
    sagittal plane, the planar model's contact points and their velocities equal the
    3-D model's frames (pinocchio, free flyer) in x and z."""
    from humfall_ros.multicontact.executor import planar_state
    from humfall_ros.multicontact.initial_state import nominal_configuration
    pm, hm = models
    rng = np.random.default_rng(2)
    qp = nominal_configuration(pm)
    qp[2] = 0.3
    qp[3:] += rng.uniform(-0.2, 0.2, pm.m)
    vp = rng.normal(0, 1.0, pm.n)
    joints = np.zeros(len(hm.joint_names))
    rates = np.zeros(len(hm.joint_names))
    for i, j in enumerate(pm.joint_names):
        joints[hm.joint_names.index(j)] = qp[3 + i]
        rates[hm.joint_names.index(j)] = vp[3 + i]
    quat = np.array([0.0, np.sin(qp[2] / 2), 0.0, np.cos(qp[2] / 2)])      # pitch about y, xyzw
    q3 = hm.configuration([qp[0], 0.0, qp[1]], quat, joints)
    v3 = hm.velocity([vp[0], 0.0, vp[1]], [0.0, vp[2], 0.0], quat, rates)
    q, v = planar_state(pm, hm.joint_names, q3, v3)
    np.testing.assert_allclose(q, qp, atol=1e-12)
    np.testing.assert_allclose(v, vp, atol=1e-12)
    hm.forward(q3, v3)
    import pinocchio as pin
    for point, frame in (("LH", "l_hand"), ("RH", "r_hand")):
        np.testing.assert_allclose(pm.point(point, q), hm.frame_position(frame)[[0, 2]], atol=1e-9)
        vel = pin.getFrameVelocity(hm.model, hm.data, hm.frame_ids[frame], pin.LOCAL_WORLD_ALIGNED).linear
        np.testing.assert_allclose(pm.point_jacobian(point, q) @ v, vel[[0, 2]], atol=1e-9)


def test_executor_releases_before_its_start_then_plans_once_from_the_take_over_tick(models):
    """A plan source is asked once, at the first tick at or after start_time, with that tick's observation;
    the plan's time 0 is that tick; out-of-plane joints go to the planar model's locked value (0)."""
    pm, hm = models
    q0 = np.zeros(pm.n)
    q1 = q0.copy()
    q1[3:] = 0.4
    seg = _segment(pm, q0, q1, 0.5, mode=("LF", "RF"), target=("LF", "RF"))
    calls = []

    def source(obs):
        calls.append(obs.time)
        return [seg]

    ex = MulticontactExecutor([], pm.joint_names, hm.joint_names, ExecutorConfig(start_time=0.6), plan_source=source)
    assert ex.step(_obs(hm, 0.598)) is None and not calls
    first = ex.step(_obs(hm, 0.6))
    assert calls == [pytest.approx(0.6)] and ex.take_over_time == pytest.approx(0.6)
    idx = [hm.joint_names.index(j) for j in pm.joint_names]
    others = [i for i in range(len(hm.joint_names)) if i not in idx]
    np.testing.assert_allclose(first.positions[others], 0.0)
    later = ex.step(_obs(hm, 0.85))
    np.testing.assert_allclose(later.positions[idx], MulticontactExecutor.sample(seg, 0.25)[0])
    assert len(calls) == 1
    ex.reset()                                     # a plan from a source is forgotten on reset
    assert ex.segments == [] and ex.take_over_time is None


def test_executor_without_a_plan_releases_for_good_and_says_why(models):
    pm, hm = models

    def broken(obs):
        raise RuntimeError("solver died")

    ex = MulticontactExecutor([], pm.joint_names, hm.joint_names, plan_source=broken)
    assert ex.step(_obs(hm, 0.0)) is None
    assert ex.failed and "solver died" in ex.reason
    assert ex.step(_obs(hm, 0.1)) is None
    ex2 = MulticontactExecutor([], pm.joint_names, hm.joint_names, plan_source=lambda obs: None)
    assert ex2.step(_obs(hm, 0.0)) is None and ex2.reason == "no plan"
    with pytest.raises(ValueError, match="empty plan"):
        MulticontactExecutor([], pm.joint_names, hm.joint_names)
    with pytest.raises(ValueError, match="hold"):
        ExecutorConfig(hold="sideways")
    with pytest.raises(ValueError, match="swing_control"):
        ExecutorConfig(swing_control="feet")
    with pytest.raises(ValueError, match="swing_clearance"):
        ExecutorConfig(swing_clearance=float("nan"))
    with pytest.raises(ValueError, match="unknown parameters"):
        ExecutorConfig.from_params({"landing_wait": 0.1, "typo": 1})


def test_executor_config_matches_the_node_declaration():
    from humfall_ros import params
    d = params.defaults("multicontact_executor")
    cfg = ExecutorConfig()
    # every field but the take-over time (the node's start_time < 0 means the plan file's) is declared, with the
    # dataclass's default (the node builds its config from the declared values of the fields' names)
    for f in dataclasses.fields(ExecutorConfig):
        if f.name != "start_time":
            assert d[f.name] == getattr(cfg, f.name), f.name


def test_project_to_mode_puts_the_feet_flat_and_still_and_only_removes_energy(models):
    """A measured two-foot state with a sole tilted and sliding: after the projection both feet are
    on the ground (toe and heel, eq. 3), their rows have zero velocity (eq. 4), the energy does not rise
    (eq. 10 is a D-metric projection) and the planner's own checks accept the state."""
    from humfall_ros.multicontact import contacts as C
    from humfall_ros.multicontact.initial_state import nominal_configuration, velocity_for_energy
    from humfall_ros.multicontact.modes import Environment, parse_mode
    from humfall_ros.multicontact.planner import PlannerConfig, validate
    pm, _ = models
    mode = parse_mode("LF/RF")
    q = nominal_configuration(pm)
    v = velocity_for_energy(pm, q, mode, 30.0, 1.0)
    rng = np.random.default_rng(4)
    qm = q.copy()
    qm[pm.q_index["l_ankle_pitch"]] += 0.1           # one end of the left sole comes up
    qm[3:] += rng.normal(0, 0.01, pm.m)
    vm = v + rng.normal(0, 0.1, pm.n)
    env = Environment()
    rows = C.contact_rows(mode, env)
    assert np.abs(C.rows_jacobian(pm, rows, qm) @ vm).max() > 0.05
    p = project_to_mode(pm, qm, vm, mode)
    assert p.gap_before > 0.005
    for r in rows:
        if r.axis == "n":
            assert abs(C.signed_distance(pm, r.point, r.surface, env, p.q)) < 1e-8
    np.testing.assert_allclose(C.rows_jacobian(pm, rows, p.q) @ p.v, 0.0, atol=1e-9)
    assert p.ke_after <= p.ke_before + 1e-9 and p.ke_after > 0.5 * p.ke_before
    assert p.q_shift < 0.1
    validate(pm, {"q": p.q.tolist(), "v": p.v.tolist(), "initial_mode": "LF/RF"}, PlannerConfig())


def test_planned_contacts_and_stored_plans(models, tmp_path):
    pm, _ = models
    from humfall_ros.multicontact.initial_state import nominal_configuration
    q0 = nominal_configuration(pm)
    q1 = q0.copy()
    q1[2] += 0.5                                   # pitched forward: the hand lower
    landing = _segment(pm, q0, q1, 0.4, "add", "LH", ("LF", "RF"), ("LF", "RF", "LH"))
    settle = _segment(pm, q1, q1, 0.6, mode=("LF", "RF", "LH"), target=("LF", "RF", "LH"))
    ev = planned_contacts(pm, [landing, settle])
    assert len(ev) == 1 and ev[0].extremity == "LH" and ev[0].change == "add"
    assert ev[0].time == pytest.approx(0.4)
    np.testing.assert_allclose(ev[0].position, pm.point("LH", q1))
    plan = StoredPlan([landing, settle], 0.6, {"target_ke": 20})
    plan.save(tmp_path / "p.json")
    back = StoredPlan.load(tmp_path / "p.json")
    assert back.take_over_time == 0.6 and back.meta == {"target_ke": 20}
    np.testing.assert_allclose(back.segments[1].q, settle.q)
    assert back.segments[0].extremity == "LH"
    (tmp_path / "bad.json").write_text('{"segments": []}')
    with pytest.raises(ValueError, match="format"):
        StoredPlan.load(tmp_path / "bad.json")


def test_both_hands_copies_the_landing_arm_to_the_other(models):
    pm, hm = models
    from humfall_ros.multicontact.initial_state import nominal_configuration
    q0 = nominal_configuration(pm)
    q1 = q0.copy()
    q1[pm.q_index["l_shoulder_pitch"]] = -1.2
    q1[pm.q_index["l_elbow"]] = -0.1
    q1[pm.q_index["r_shoulder_pitch"]] = 0.7
    landing = _segment(pm, q0, q1, 0.4, "add", "LH", ("LF", "RF"), ("LF", "RF", "LH"))
    settle = _segment(pm, q1, q1, 0.6, mode=("LF", "RF", "LH"), target=("LF", "RF", "LH"))
    ji = {j: hm.joint_names.index(j) for j in ("l_shoulder_pitch", "r_shoulder_pitch", "l_elbow", "r_elbow")}
    plain = MulticontactExecutor([landing, settle], pm.joint_names, hm.joint_names, ExecutorConfig(both_hands=False))
    both = MulticontactExecutor([landing, settle], pm.joint_names, hm.joint_names)
    for ex in (plain, both):
        ex.step(_obs(hm, 0.0))
    a, b = plain.step(_obs(hm, 0.3)), both.step(_obs(hm, 0.3))
    assert a.positions[ji["r_shoulder_pitch"]] != pytest.approx(a.positions[ji["l_shoulder_pitch"]])
    assert b.positions[ji["r_shoulder_pitch"]] == pytest.approx(b.positions[ji["l_shoulder_pitch"]])
    assert b.positions[ji["r_elbow"]] == pytest.approx(b.positions[ji["l_elbow"]])
    assert b.velocities[ji["r_shoulder_pitch"]] == pytest.approx(b.velocities[ji["l_shoulder_pitch"]])
    assert b.positions[ji["l_shoulder_pitch"]] == pytest.approx(a.positions[ji["l_shoulder_pitch"]])
    assert both.mirrored_hand == "RH" and plain.mirrored_hand is None


def test_blend_time_starts_from_the_servo_targets(models):
    pm, hm = models
    q0 = np.zeros(pm.n)
    q1 = q0.copy()
    q1[3:] = 0.5
    seg = _segment(pm, q1, q1, 0.5, mode=("LF", "RF"), target=("LF", "RF"))
    ex = MulticontactExecutor([seg], pm.joint_names, hm.joint_names, ExecutorConfig(blend_time=0.1))
    idx = [hm.joint_names.index(j) for j in pm.joint_names]
    a = ex.step(_obs(hm, 1.0))                    # servo targets unknown: the measured 0.05 rad
    np.testing.assert_allclose(a.positions[idx], 0.05)
    b = ex.step(_obs(hm, 1.05))
    np.testing.assert_allclose(b.positions[idx], 0.5 * 0.05 + 0.5 * 0.5)
    c = ex.step(_obs(hm, 1.2))
    np.testing.assert_allclose(c.positions[idx], 0.5)


def _imu_reading(hm, base_rotation, joints):
    """The IMU's world orientation (xyzw) of the robot with that base rotation and joints, and a zero gyro."""
    from scipy.spatial.transform import Rotation

    q = hm.configuration([0.0, 0.0, 0.8], Rotation.from_matrix(base_rotation).as_quat(), joints)
    hm.forward(q)
    R = hm.frame_placement(hm.imu_frame).rotation
    return Rotation.from_matrix(R).as_quat(), np.zeros(3)


def test_base_pitch_from_the_imu_is_the_planar_states_pitch(models):
    from scipy.spatial.transform import Rotation

    from humfall_ros.multicontact.executor import base_pitch_from_imu, planar_state

    pm, hm = models
    data = hm.model.createData()
    rng = np.random.default_rng(3)
    for _ in range(5):
        joints = rng.uniform(-0.3, 0.3, len(hm.joint_names))      # the chest joints move the IMU in the base
        R = Rotation.from_euler("zyx", [rng.uniform(-1, 1), rng.uniform(-1.5, 1.5), rng.uniform(-0.2, 0.2)])
        imu = _imu_reading(hm, R.as_matrix(), joints)
        q3 = hm.configuration([0.1, 0.0, 0.8], R.as_quat(), joints)
        want = planar_state(pm, hm.joint_names, q3, np.zeros(hm.model.nv))[0][2]
        assert base_pitch_from_imu(hm, data, joints, imu) == pytest.approx(want, abs=1e-9)
        assert base_pitch_from_imu(hm, data, joints, imu[0]) == pytest.approx(want, abs=1e-9)   # orientation alone
    for bad in (None, (np.full(4, np.nan), np.zeros(3)), (np.zeros(4), np.zeros(3)), (np.ones(3), np.zeros(3))):
        assert base_pitch_from_imu(hm, data, joints, bad) is None
    assert base_pitch_from_imu(hm, data, np.full(len(hm.joint_names), np.nan), imu) is None


def test_base_pitch_feedback_offsets_the_hips_by_the_gain_times_the_pitch_error(models):
    from scipy.spatial.transform import Rotation

    pm, hm = models
    q0 = np.zeros(pm.n)
    q0[2] = 0.3                                   # the plan's root pitch
    q0[3:] = 0.1
    seg = _segment(pm, q0, q0, 1.0, mode=("LF", "RF"), target=("LF", "RF"))
    hips = [hm.joint_names.index(j) for j in pm.joint_names if j.endswith("hip_pitch")]
    rest = [hm.joint_names.index(j) for j in pm.joint_names if not j.endswith("hip_pitch")]
    assert len(hips) == 2
    joints = np.full(len(hm.joint_names), 0.05)
    imu = _imu_reading(hm, Rotation.from_euler("y", 0.42).as_matrix(), joints)     # pitched 0.12 rad ahead

    def targets(gain, model, reading):
        ex = MulticontactExecutor([seg], pm.joint_names, hm.joint_names, ExecutorConfig(base_pitch_gain=gain),
                                  model=model)
        ex.step(_obs(hm, 0.0))
        obs = _obs(hm, 0.5, q=joints)
        if reading is not None:
            obs.inputs["imu"] = reading
        return ex.step(obs), ex

    open_loop, ex0 = targets(0.0, hm, imu)
    np.testing.assert_allclose(open_loop.positions[hips], 0.1)
    assert ex0.pitch_feedback_ticks == 0
    for gain in (0.5, 2.0):
        fb, ex = targets(gain, hm, imu)
        np.testing.assert_allclose(fb.positions[hips], 0.1 + gain * 0.12, atol=1e-9)
        np.testing.assert_allclose(fb.positions[rest], open_loop.positions[rest])
        np.testing.assert_allclose(fb.velocities, open_loop.velocities)
        assert ex.pitch_error_max == pytest.approx(0.12, abs=1e-9) and ex.pitch_feedback_ticks == 1
    # a robot pitched far off the plan (fallen): the offset stops at base_pitch_correction_max, and a
    # hip target never leaves the URDF's limits
    far = _imu_reading(hm, Rotation.from_euler("y", 1.8).as_matrix(), joints)     # 1.5 rad ahead
    fb, ex = targets(1.0, hm, far)
    np.testing.assert_allclose(fb.positions[hips], 0.1 + ExecutorConfig().base_pitch_correction_max, atol=1e-9)
    assert ex.pitch_error_max == pytest.approx(1.5, abs=1e-9)
    q_edge = q0.copy()
    q_edge[[pm.joint_names.index(j) + 3 for j in pm.joint_names if j.endswith("hip_pitch")]] = 0.7
    edge = MulticontactExecutor([_segment(pm, q_edge, q_edge, 1.0, mode=("LF", "RF"), target=("LF", "RF"))],
                                pm.joint_names, hm.joint_names, model=hm)
    edge.step(_obs(hm, 0.0))
    obs = _obs(hm, 0.5, q=joints)
    obs.inputs["imu"] = far
    upper = np.asarray(hm.limits.upper)[hips]
    assert np.all(upper < 0.7 + 0.3)                     # the offset target would pass the limit
    np.testing.assert_allclose(edge.step(obs).positions[hips], upper)
    with pytest.raises(ValueError):
        ExecutorConfig(base_pitch_correction_max=0.0)
    # no model, or no usable IMU reading: open loop (never a crash)
    for model, reading in ((None, imu), (hm, None), (hm, (np.full(4, np.nan), np.zeros(3)))):
        out, ex = targets(1.0, model, reading)
        np.testing.assert_allclose(out.positions, open_loop.positions)
        assert ex.pitch_feedback_ticks == 0
    with pytest.raises(ValueError):
        ExecutorConfig(base_pitch_gain=-1.0)
    with pytest.raises(ValueError):
        MulticontactExecutor([seg], pm.joint_names, hm.joint_names[::-1], model=hm)


def test_base_pitch_feedback_acts_on_the_stance_legs_hips_only(models):
    from scipy.spatial.transform import Rotation

    pm, hm = models
    q0 = np.zeros(pm.n)
    q0[3:] = 0.1
    swing = _segment(pm, q0, q0, 1.0, "add", "RF", ("LF",), ("LF", "RF"))     # the right foot in the air
    # the plan's joints tracked (a task-space swing, the default, drives both legs by the IK instead)
    ex = MulticontactExecutor([swing, swing], pm.joint_names, hm.joint_names, ExecutorConfig(swing_control="joints"),
                              model=hm)
    joints = np.full(len(hm.joint_names), 0.05)
    ex.step(_obs(hm, 0.0))
    obs = _obs(hm, 0.2, q=joints)
    obs.inputs["imu"] = _imu_reading(hm, Rotation.from_euler("y", 0.1).as_matrix(), joints)
    out = ex.step(obs)
    assert out.positions[hm.joint_names.index("l_hip_pitch")] == pytest.approx(0.2, abs=1e-9)   # 0.1 + 1 x 0.1
    assert out.positions[hm.joint_names.index("r_hip_pitch")] == pytest.approx(0.1, abs=1e-9)   # swinging: the plan


def test_task_space_swing_drives_both_legs_and_holds_them_when_the_imu_is_lost(models):
    """``swing_control`` "task" (the default): during a foot landing segment both legs come from the step
    controller's IK (not the plan's joints); an unusable IMU reading mid-swing holds the legs' last command instead
    of jumping to the plan's joints; the other joints track the plan either way."""
    pm, hm = models
    q0 = np.zeros(pm.n)
    for i, j in enumerate(pm.joint_names):
        q0[3 + i] = hm.standing_posture.get(j, 0.0)
    swing = _segment(pm, q0, q0, 0.5, "add", "RF", ("LF",), ("LF", "RF"))     # the right foot lands at 0.5 s
    stop = _segment(pm, q0, q0, 0.5, "", "", ("LF", "RF"), ("LF", "RF"))
    ex = MulticontactExecutor([swing, stop], pm.joint_names, hm.joint_names, model=hm)
    joints = hm.joint_vector(hm.standing_posture)
    legs = [hm.joint_index(f"{s}_{j}") for s in ("l", "r") for j in ("hip_pitch", "knee", "ankle_pitch")]

    def obs(t, imu=True):
        o = _obs(hm, t, left=True, right=False, q=joints)
        o = dataclasses.replace(o, state=dataclasses.replace(o.state, com=np.array([0.0, 0.0, 0.8])))
        if imu:
            o.inputs["imu"] = _imu_reading(hm, np.eye(3), joints)
        return o

    ex.step(obs(0.0))
    out = ex.step(obs(0.1))
    assert ex.task_swings and ex.task_swings[0]["foot"] == "RF"
    plan_q, _ = ex.sample(swing, 0.1)
    planned = np.array([plan_q[pm.joint_names.index(hm.joint_names[k])] for k in legs])
    assert np.abs(out.positions[legs] - planned).max() > 1e-3      # the legs are the IK's, not the plan's
    held = ex.step(obs(0.102, imu=False))
    np.testing.assert_array_equal(held.positions[legs], out.positions[legs])
    arm = hm.joint_index("l_elbow")
    assert held.positions[arm] == pytest.approx(plan_q[pm.joint_names.index("l_elbow")])
    # the IMU back: the IK again (the swing target moves on, so the command does)
    again = ex.step(obs(0.2))
    assert np.abs(again.positions[legs] - out.positions[legs]).max() > 1e-4


def test_task_space_swing_takes_a_posture_error_out_over_ticks_not_at_the_speed_limit(models):
    """The plan's posture and base pitch start off the measured ones (the take-over's projection to the two-foot
    mode: up to 0.04 rad; the 30 J step's base 0.03 rad ahead of the plan's). With per-tick gains of 1 on the
    posture and attitude tasks (session 26) the IK's first command drove the stance leg's joints at their speed
    limits (the robot left the ground for ~0.1 s at the lift-off); with the default gains the same error is taken
    out at a fraction of the limits. (The swing leg follows the swing sole's task, whose lift starts at once.)"""
    from scipy.spatial.transform import Rotation

    pm, hm = models
    q0 = np.zeros(pm.n)
    for i, j in enumerate(pm.joint_names):
        q0[3 + i] = hm.standing_posture.get(j, 0.0)
    swing = _segment(pm, q0, q0, 0.5, "add", "RF", ("LF",), ("LF", "RF"))
    stop = _segment(pm, q0, q0, 0.5, "", "", ("LF", "RF"), ("LF", "RF"))
    legs = [hm.joint_index(f"{s}_{j}") for s in ("l", "r") for j in ("hip_pitch", "knee", "ankle_pitch")]
    stance = legs[:3]               # the left leg: the right foot is the one that swings
    measured = hm.joint_vector(hm.standing_posture)
    measured[legs] += 0.04          # the measured legs 0.04 rad off the plan's
    limit = np.asarray(hm.limits.velocity)[stance]

    def first_command(**gains):
        ex = MulticontactExecutor([swing, stop], pm.joint_names, hm.joint_names, ExecutorConfig(**gains), model=hm)
        o = _obs(hm, 0.0, left=True, right=False, q=measured)
        o = dataclasses.replace(o, state=dataclasses.replace(o.state, com=np.array([0.0, 0.0, 0.8])))
        o.inputs["imu"] = _imu_reading(hm, Rotation.from_euler("y", 0.03).as_matrix(), measured)
        out = ex.step(o)
        assert ex.task_swings, "the swing starts at the take-over"
        return np.abs(out.velocities[stance]) / limit

    default = first_command()
    deadbeat = first_command(swing_attitude_gain=1.0, swing_posture_gain=1.0)
    assert deadbeat.max() > 0.9, deadbeat         # a stance joint at (0.95 of) its speed limit
    assert default.max() < 0.5 * deadbeat.max(), (default, deadbeat)
    with pytest.raises(ValueError, match="swing_posture_gain"):
        ExecutorConfig(swing_posture_gain=0.0)
    with pytest.raises(ValueError, match="swing_attitude_gain"):
        ExecutorConfig(swing_attitude_gain=float("nan"))


def test_lateral_roll_moves_the_com_sideways_towards_the_soles_segment():
    """``lateral_roll``: after a 0.5 m step (left sole behind at (0, 0.09), right ahead at (0.5, -0.09)) the
    segment between them is diagonal; a CoM 5 cm to the left of its middle, across it, gets a - roll in proportion
    to that offset's sideways part, bounded; the speed's part across the segment damps; a CoM past the front sole
    is held to that sole's centre; soles on top of each other give None."""
    from humfall_ros.control.standing import lateral_roll

    left, right = np.array([0.0, 0.09]), np.array([0.5, -0.09])
    n = np.array([0.18, 0.5]) / np.hypot(0.18, 0.5)       # the normal of (0.5, -0.18), to the left
    com = np.append((left + right) / 2 + 0.05 * n, 0.7)    # 5 cm off the segment's middle, across it
    err = 0.05 * n[1]                                      # its sideways part
    assert lateral_roll(com, np.zeros(3), left, right, 1.5, 0.2, 0.2) == pytest.approx(-1.5 * err)
    assert lateral_roll(com, np.zeros(3), left, right, 10.0, 0.2, 0.2) == pytest.approx(-0.2)
    v = np.array([0.3, 0.2, 0.0])
    want = -(1.5 * err + 0.2 * float(v[:2] @ n) * n[1])
    assert lateral_roll(com, v, left, right, 1.5, 0.2, 0.2) == pytest.approx(want)
    assert lateral_roll(np.array([0.7, -0.05, 0.7]), np.zeros(3), left, right, 1.0, 0.0, 0.2) == pytest.approx(-0.04)
    assert lateral_roll(com, v, left, left, 1.5, 0.2, 0.2) is None


def test_lateral_balance_rolls_the_legs_after_a_foot_landing_on_both_feet_only(models):
    """The executor applies ``lateral_roll`` to both ankle rolls (+d) and hip rolls (-d) in a feet-only segment
    after a foot landing, on the sensed configuration's soles: with the left leg forward and the robot rolled 0.1 rad
    (IMU), its CoM is off the soles' segment, and gets a - roll; before the landing, without an IMU reading, with a
    hand down, or with a zero gain: the rolls as held."""
    from scipy.spatial.transform import Rotation

    from humfall_ros.control.step_control import configuration_from_sensors
    from humfall_ros.control.standing import lateral_roll

    pm, hm = models
    q0 = np.zeros(pm.n)
    q0[3:] = 0.1
    release = _segment(pm, q0, q0, 0.1, "remove", "RF", ("LF", "RF"), ("LF",))
    landing = _segment(pm, q0, q0, 0.2, "add", "RF", ("LF",), ("LF", "RF"))
    rest = _segment(pm, q0, q0, 1.0, mode=("LF", "RF"), target=("LF", "RF"))
    hand = _segment(pm, q0, q0, 1.0, mode=("LF", "LH", "RF"), target=("LF", "LH", "RF"))
    joints = np.full(len(hm.joint_names), 0.05)
    joints[hm.joint_names.index("l_hip_pitch")], joints[hm.joint_names.index("r_hip_pitch")] = -0.3, 0.3
    rolled = _imu_reading(hm, Rotation.from_euler("x", -0.1).as_matrix(), joints)
    ankles = [hm.joint_names.index(f"{s}_ankle_roll") for s in "lr"]
    hips = [hm.joint_names.index(f"{s}_hip_roll") for s in "lr"]
    com, vel = np.array([0.05, 0.0, 0.75]), np.array([0.0, 0.05, 0.0])

    def command(cfg, t, reading=rolled, segs=(release, landing, rest)):
        ex = MulticontactExecutor(list(segs), pm.joint_names, hm.joint_names, cfg, model=hm)
        out = None
        for tt in np.arange(0.0, t + 1e-9, 0.002):   # the right foot loaded from 0.25 s: the landing ends then
            o = _obs(hm, tt, left=True, right=tt > 0.25, q=joints)
            o.state.com[:], o.state.com_velocity[:] = com, vel
            if reading is not None:
                o.inputs["imu"] = reading
            out = ex.step(o)
        return out, ex

    cfg = ExecutorConfig(swing_control="joints", lateral_gain=1.5, lateral_damping=0.2, lateral_max=0.2)
    held, ex0 = command(ExecutorConfig(swing_control="joints", lateral_gain=0.0), 0.5)
    out, ex = command(cfg, 0.5)
    assert ex.segment_index == 2 and ex0.lateral_ticks == 0
    q = configuration_from_sensors(hm, joints, rolled[0], com)
    hm.forward(q)
    left, right = (hm.sole_corners(s)[:, :2].mean(axis=0) for s in "lr")
    assert left[0] - right[0] > 0.3                     # the left sole ahead: the segment is diagonal
    d = lateral_roll(com, vel, left, right, 1.5, 0.2, 0.2)
    assert d < -0.01
    np.testing.assert_allclose(out.positions[ankles] - held.positions[ankles], d, atol=1e-9)
    np.testing.assert_allclose(out.positions[hips] - held.positions[hips], -d, atol=1e-9)
    others = [i for i in range(len(hm.joint_names)) if i not in ankles + hips]
    np.testing.assert_allclose(out.positions[others], held.positions[others])
    assert ex.lateral_ticks >= 1 and ex.lateral_offset_max == pytest.approx(abs(d))
    early, ex1 = command(cfg, 0.05)
    assert ex1.segment_index == 0 and ex1.lateral_ticks == 0
    blind, ex2 = command(cfg, 0.5, reading=None)
    np.testing.assert_allclose(blind.positions, held.positions)
    _, ex3 = command(cfg, 0.5, segs=(release, landing, hand))
    assert ex3.segment_index == 2 and ex3.lateral_ticks == 0


def _step_plan(pm, then_hand: bool = False) -> list[Segment]:
    """A protective step (the right foot released and landed again), its stop on both feet, and optionally a left
    hand landed after it."""
    q0 = np.zeros(pm.n)
    q1 = q0.copy()
    q1[3:] = 0.1
    segs = [_segment(pm, q0, q0, 0.05, "remove", "RF", ("LF", "RF"), ("LF",)),
            _segment(pm, q0, q1, 0.3, "add", "RF", ("LF",), ("LF", "RF"))]
    if then_hand:
        segs.append(_segment(pm, q1, q1, 0.3, "add", "LH", ("LF", "RF"), ("LF", "RF", "LH")))
        return segs + [_segment(pm, q1, q1, 0.4, mode=("LF", "RF", "LH"), target=("LF", "RF", "LH"))]
    return segs + [_segment(pm, q1, q1, 0.4, mode=("LF", "RF"), target=("LF", "RF"))]


@pytest.mark.parametrize("then_hand,on,takes_over", [(False, True, True), (False, False, False), (True, True, False)])
def test_the_stop_balance_replaces_the_stop_after_the_last_step_only(models, then_hand, on, takes_over):
    """``stop_balance``: from the touchdown that ends the plan's last foot landing the capture balance commands the
    robot (its targets, no velocity feed-forward), not the plan's stop; not when the option is off, nor in a plan
    that adds a hand after the step (that is tracked as planned)."""
    pm, hm = models
    ex = MulticontactExecutor(_step_plan(pm, then_hand), pm.joint_names, hm.joint_names,
                              ExecutorConfig(stop_balance=on), model=hm)
    q = np.zeros(len(hm.joint_names))
    for t in (0.0, 0.1, 0.2):
        ex.step(_obs(hm, t, left=True, right=False, q=q))
    assert ex.stop_balance is None
    cmd = ex.step(_obs(hm, 0.3, left=True, right=True, q=q))        # the right foot touches down
    assert ex.switches[-1][2] == "touchdown"
    assert (ex.stop_balance is not None) == takes_over
    if takes_over:
        assert ex.stop_balance_time == pytest.approx(0.3) and np.allclose(cmd.velocities, 0.0)
        later = ex.step(_obs(hm, 0.5, left=True, right=True, q=q))
        np.testing.assert_allclose(later.positions, ex.stop_balance.command(_obs(hm, 0.5, left=True, right=True,
                                                                                   q=q)))
    else:
        # the arms track the plan's next segment (the legs come from the landing blend of the task-space swing)
        arms = [i for i, j in enumerate(pm.joint_names) if "shoulder" in j or "elbow" in j]
        idx = [hm.joint_names.index(pm.joint_names[i]) for i in arms]
        np.testing.assert_allclose(cmd.positions[idx], MulticontactExecutor.sample(ex.segments[2], 0.0)[0][arms])


def test_the_run_matches_a_planned_contact_event_to_the_lasting_change_nearest_its_time():
    """``multicontact_run``: executed contact changes that last the debounce, and the one nearest the plan's time."""
    from humfall_ros.sim.multicontact_run import _lasting_changes, _matching_change
    m = np.array([0, 0, 1, 1, 0, 0, 0, 1, 1, 1, 1, 0, 1], bool)
    assert list(_lasting_changes(m, 0, 1)) == [2, 7, 12]          # no debounce: every change (one at the end)
    assert list(_lasting_changes(m, 0, 3)) == [7, 12]             # the 2-tick chatter at 2 is not a change
    assert list(_lasting_changes(m, 8, 3)) == [8, 12]             # true at the start counts
    assert list(_lasting_changes(m, 0, 5)) == [12]                # a change at the end lasts to the end
    assert len(_lasting_changes(np.zeros(4, bool), 0, 2)) == 0
    t = np.arange(len(m)) * 0.1
    assert _matching_change(m, 0, 1, t, 0.25) == 2 and _matching_change(m, 0, 1, t, 0.6) == 7
    assert _matching_change(m, 0, 1, t, 1.1) == 12 and _matching_change(m, 0, 3, t, 0.25) == 7
    assert _matching_change(np.zeros(4, bool), 0, 2, t, 0.1) is None
