"""The multicontact executor as a contract controller, on synthetic observations (no simulator)."""
from __future__ import annotations

import numpy as np
import pytest

from humfall_ros.control.contract import CentroidalObservation, Controller, Observation, stamp_ns_of
from humfall_ros.model.humanoid import load_model as load_humanoid
from humfall_ros.multicontact.collocation import Segment
from humfall_ros.multicontact.executor import MulticontactExecutor
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
    ex = MulticontactExecutor([landing, settle], pm.joint_names, hm.joint_names)
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
