"""LocomotionController: command checks, release on fall / e-stop, resume, and a kinematic walk."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from humfall_ros.control.contract import CentroidalObservation, Observation
from humfall_ros.model.humanoid import load_model
from humfall_ros.params import ParamError
from humfall_ros.walking.config import LocomotionConfig
from humfall_ros.walking.controller import LocomotionController, WalkingState


@pytest.fixture(scope="module")
def model():
    return load_model()


def observe(model, q, t, inputs=None, active="locomotion"):
    """An exact observation of configuration q (as if the joints tracked perfectly)."""
    model.forward(q)
    com = model.com(q)
    fc = 0.5 * (model.frame_position("l_foot") + model.frame_position("r_foot"))
    ground = np.array([com[0], com[1], 0.0])
    st = CentroidalObservation(com, np.zeros(3), ground, ground, np.zeros(3), np.zeros((0, 2)), fc, 0.0, 0.0,
                               model.weight, True, True, False)
    return Observation(round(t * 1e9), q[7:].copy(), np.zeros(model.njoints), st, active, inputs or {})


def test_config_from_params_refuses_unknown():
    assert LocomotionConfig.from_params() == LocomotionConfig()
    with pytest.raises(ParamError):
        LocomotionConfig.from_params({"no_such": 1.0})
    with pytest.raises(ParamError):
        LocomotionConfig.from_params({"double_support": 0.9})


def test_bad_commands(model):
    c = LocomotionController(model)
    assert "non-finite" in c.set_walk_command(float("nan"), 0.0)
    assert "non-finite" in c.set_walk_command(0.2, float("inf"))
    assert "backward" in c.set_walk_command(-0.1, 0.0)
    c.set_walk_command(5.0 / 3.6, math.radians(90))  # clamped first (the clamped walk may then be refused)
    assert any("clamped to 2.50 km/h" in m for m in c.messages)
    assert any("clamped to 20.0 deg/s" in m for m in c.messages)


def test_infeasible_walk_refused_with_reason(model):
    """Standing-height CoM with 2.5 km/h steps: the rear knee straightens; refused before the first step."""
    cfg = dataclasses.replace(LocomotionConfig(), com_height=0.74)
    c = LocomotionController(model, cfg)
    reason = c.set_walk_command(2.5 / 3.6, 0.0)
    assert reason is not None and "refused" in reason
    assert c.pending is None


def test_release_on_fall_and_estop_then_resume(model):
    c = LocomotionController(model)
    q = c.reference_configuration(c.standing_posture, 0.0, (0.0, 0.0))
    assert c.step(observe(model, q, 0.0)) is not None
    assert c.set_walk_command(1.0 / 3.6, 0.0, n_steps=2) is None
    out = c.step(observe(model, q, 0.002))
    assert c.pattern is not None and out.velocities is not None
    assert c.step(observe(model, q, 0.004, {"fall_event": True})) is None
    assert c.pattern is None and c.state.released
    assert "ignored" in c.set_walk_command(1.0 / 3.6, 0.0)
    assert c.step(observe(model, q, 0.006, {"estop": True})) is None
    # released inputs cleared: stands again from the measured posture (bumpless: the command is the posture)
    qm = q.copy()
    qm[7:] += 0.01
    out = c.step(observe(model, qm, 0.008, {}, active="estop"))
    assert out is not None
    assert np.max(np.abs(out.positions - qm[7:])) < 0.02


def test_kinematic_walk_finishes_and_reports_state(model):
    """With perfect tracking the controller walks 3 steps, the state follows the gait, and it stands after."""
    c = LocomotionController(model, dataclasses.replace(LocomotionConfig(), dcm_gain=0.0, cop_damping_gain=0.0))
    q = c.reference_configuration(c.standing_posture, 0.0, (0.0, 0.0))
    assert c.set_walk_command(1.0 / 3.6, 0.0, n_steps=3) is None
    t, supports, steps = 0.0, set(), []
    peak = np.zeros(model.njoints)
    for _ in range(5000):
        out = c.step(observe(model, q if c.q_ik is None else c.q_ik, t))
        t += c.dt
        supports.add(c.state.support)
        steps.append(c.state.step_index)
        if out.velocities is not None:
            peak = np.maximum(peak, np.abs(out.velocities))
        if c.pattern is None:
            break
    assert c.pattern is None and any("finished" in m for m in c.messages)
    assert supports == {"double", "single_left", "single_right"}
    assert max(steps) == 4
    assert np.all(peak <= c.cfg.velocity_fraction * model.limits.velocity + 1e-9)


def test_imu_heading_drift_steers_the_steps_not_yet_planned(model):
    """The IMU shows the robot yawed 3 deg right of the IK (e.g. a slipping stance foot): the pattern's steering
    target turns the coming steps left by the filtered drift; without an IMU input nothing is steered."""
    from scipy.spatial.transform import Rotation

    c = LocomotionController(model)
    q = c.reference_configuration(c.standing_posture, 0.0, (0.0, 0.0))
    assert c.set_walk_command(1.0 / 3.6, 0.0, n_steps=6) is None
    c.step(observe(model, q, 0.0))
    assert c.pattern is not None and c.pattern.steer_target == 0.0
    drift = math.radians(-3.0)
    t = 0.002
    for _ in range(int(2.0 / c.dt)):   # 5 filter time constants
        model.forward(c.q_ik)
        R_ik = model.frame_placement(model.imu_frame).rotation
        quat = (Rotation.from_euler("z", drift) * Rotation.from_matrix(R_ik)).as_quat()   # xyzw
        c.step(observe(model, c.q_ik, t, {"imu": (quat, np.zeros(3))}))
        t += c.dt
    assert c.pattern.steer_target == pytest.approx(-drift, abs=math.radians(0.1))
    # an unusable reading (NaN, zero quaternion) steers nothing that tick: the filter keeps its value
    before = c.drift_yaw
    for bad in (np.full(4, np.nan), np.zeros(4)):
        c.step(observe(model, c.q_ik, t, {"imu": (bad, np.zeros(3))}))
        t += c.dt
        assert c.drift_yaw == before and math.isfinite(c.pattern.steer_target)
    planned = c.pattern.steer_total
    assert 0.0 < planned <= -drift + 1e-9
    c2 = LocomotionController(model)
    assert c2.set_walk_command(1.0 / 3.6, 0.0, n_steps=6) is None
    c2.step(observe(model, q, 0.0))
    for k in range(50):
        c2.step(observe(model, c2.q_ik, 0.002 * (k + 1)))
    assert c2.pattern.steer_target == 0.0


def test_per_foot_measurements_reach_the_stabiliser_up_to_the_gate_speed(model):
    """Loops 4 (forces) and 5 of the stabiliser get the estimator's per-foot forces, CoPs and contacts in walks up to
    ``foot_force_max_speed_kmh``; faster walks get none (the CoP-based loop 4 of phase 5)."""
    from humfall_ros.walking.footsteps import WalkCommand

    c = LocomotionController(model)
    q = c.reference_configuration(c.standing_posture, 0.0, (0.0, 0.0))
    st = dataclasses.replace(observe(model, q, 0.0).state, left_normal_force=300.0, right_normal_force=260.0)
    gate = c.cfg.foot_force_max_speed_kmh
    c.command = WalkCommand((gate - 0.1) / 3.6, 0.0)
    got = c._foot_measurements(st)
    assert got["foot_forces"] == {"l": 300.0, "r": 260.0} and got["contacts"] == {"l": True, "r": True}
    c.command = WalkCommand((gate + 0.1) / 3.6, 0.0)
    assert c._foot_measurements(st) == {}


def _is_idle_default(state) -> bool:
    """The state is WalkingState's defaults but for its stamp and `released` (what the locomotion node caches)."""
    ref = dataclasses.replace(WalkingState(), stamp_ns=state.stamp_ns, released=state.released)
    for f in dataclasses.fields(WalkingState):
        a, b = getattr(state, f.name), getattr(ref, f.name)
        if isinstance(a, np.ndarray):
            if not np.array_equal(a, b, equal_nan=True):
                return False
        elif a != b:
            return False
    return True


def test_a_state_that_is_not_walking_carries_only_released(model):
    """locomotion builds walking/state's message once for a non-walking state: standing, released (fall event,
    e-stop) and standing again after a walk must all be the defaults, or the node would publish stale content."""
    c = LocomotionController(model, dataclasses.replace(LocomotionConfig(), dcm_gain=0.0, cop_damping_gain=0.0))
    q = c.reference_configuration(c.standing_posture, 0.0, (0.0, 0.0))
    c.step(observe(model, q, 0.0))
    assert not c.state.walking and _is_idle_default(c.state)
    assert c.set_walk_command(1.0 / 3.6, 0.0, n_steps=1) is None
    t, seen_walking = 0.002, False
    for _ in range(4000):
        c.step(observe(model, q if c.q_ik is None else c.q_ik, t))
        t += c.dt
        seen_walking |= c.state.walking
        if seen_walking and not c.state.walking:
            break
    assert seen_walking and not c.state.walking and _is_idle_default(c.state)   # stands again after the walk
    assert not _is_idle_default(dataclasses.replace(c.state, speed=0.1))        # the check can fail
    c.step(observe(model, q, t, {"fall_event": True}))
    assert c.state.released and not c.state.walking and _is_idle_default(c.state)
    c.step(observe(model, q, t + c.dt, {"estop": True}))
    assert c.state.released and _is_idle_default(c.state)
