"""Return home, step 3 (paper 3 §V; humfall_ros/estop/align.py): the feet aligned by one step after the stop.

The plan (no simulator): the rear foot steps beside the other at the standard step width, the CoG moves over the
stance sole first (double support) and back to the middle, walking's preview control and swing trajectory,
bumpless start. In process (ClosedLoop, benchmarks/estop_trials.py): after a walking stop the feet end side by
side and the robot stands."""
from __future__ import annotations

import math
import pathlib
import sys

import numpy as np
import pinocchio as pin
import pytest

from humfall_ros.estop.align import AlignSettings, plan_alignment, side_by_side_offsets
from humfall_ros.model.humanoid import load_model
from humfall_ros.walking.footsteps import step_width

M = load_model()
DT = 0.002
ZMP_OFFSET = 0.02          # sole frame -> sole centre along the foot [m] (synthetic)


def _sole(x, y, yaw=0.0):
    c, s = math.cos(yaw), math.sin(yaw)
    return pin.SE3(np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]), np.array([x, y, 0.0]))


def _feet(front_side="l", stride=0.25, yaw=0.0):
    """Feet of a stop: ``front_side`` ``stride`` ahead along ``yaw``, lateral 0.18 m; sole centres ZMP_OFFSET ahead."""
    h, n = np.array([math.cos(yaw), math.sin(yaw)]), np.array([-math.sin(yaw), math.cos(yaw)])
    left = (stride if front_side == "l" else 0.0) * h + 0.09 * n
    right = (stride if front_side == "r" else 0.0) * h - 0.09 * n
    soles = {"l": _sole(*left, yaw), "r": _sole(*right, yaw)}
    centers = {s: soles[s].translation + soles[s].rotation @ np.array([ZMP_OFFSET, 0.0, 0.0]) for s in "lr"}
    return soles, centers


@pytest.mark.parametrize("front,yaw", [("l", 0.0), ("r", 0.4)])
def test_the_rear_foot_steps_beside_the_other_at_the_step_width(front, yaw):
    soles, centers = _feet(front, 0.25, yaw)
    com = np.array([*(0.5 * (centers["l"] + centers["r"]))[:2], 0.6])
    p = plan_alignment(M, soles, centers, com, DT)
    rear = "r" if front == "l" else "l"
    assert p.swing == rear and p.stance == front
    assert p.offset_before == pytest.approx(-0.25, abs=1e-9)
    assert p.width == pytest.approx(step_width(M))
    end = {p.stance: soles[p.stance], p.swing: p.sample(p.duration).swing}
    along, lateral = side_by_side_offsets(end, yaw, p.width, p.stance)
    assert abs(along) < 1e-9 and abs(lateral) < 1e-9
    assert np.allclose(end[p.swing].rotation, soles[p.stance].rotation)


def test_cog_over_the_stance_sole_before_lift_off_and_back_in_the_middle_bumpless():
    soles, centers = _feet("l", 0.25)
    com = np.array([0.1, 0.02, 0.6])
    p = plan_alignment(M, soles, centers, com, DT)
    s0 = p.sample(0.0)
    np.testing.assert_allclose(s0.com, com, atol=1e-12)                 # bumpless: from the rest point, at rest
    np.testing.assert_allclose(s0.com_velocity, 0.0, atol=1e-12)
    t = np.arange(0.0, p.duration + 0.1, DT)
    S = [p.sample(x) for x in t]
    com_t = np.array([s.com for s in S])
    assert np.max(np.linalg.norm(np.diff(com_t, axis=0), axis=1)) < 0.002          # continuous CoG (< 1 m/s)
    single = np.array([s.support == "single_l" for s in S])
    assert single.any() and not any(s.support == "single_r" for s in S)
    # the preview's cart-table ZMP sits on the stance sole centre through the single support (within 5 mm)
    zmp_ss = np.array([s.zmp[:2] for s, k in zip(S, single) if k])
    assert np.max(np.linalg.norm(zmp_ss - centers["l"][:2], axis=1)) < 0.005
    lift = int(np.argmax(single))
    assert np.linalg.norm(S[lift].com[:2] - centers["l"][:2]) < 0.01             # the CoG is over the stance sole
    # the swing sole: still until lift-off, apex at mid-swing, zero velocity at both ends, on the ground after
    sw = np.array([s.swing.translation for s in S])
    st = AlignSettings()
    assert np.max(np.abs(sw[:lift, :2] - soles["r"].translation[:2])) < 1e-12       # still on the ground ...
    assert 0.0 <= np.min(sw[:lift, 2]) and np.max(sw[:lift, 2]) <= st.unload_height + 1e-9   # ... unloading
    assert sw[lift - 1, 2] == pytest.approx(st.unload_height, abs=1e-6)
    assert st.apex <= np.max(sw[:, 2]) <= st.apex + st.unload_height
    touch = lift + int(np.sum(single))
    assert np.linalg.norm(S[lift].swing_velocity) < 1e-9 and np.linalg.norm(S[touch - 1].swing_velocity) < 0.01
    assert sw[-1][2] == pytest.approx(0.0, abs=1e-12)
    # the end: the CoG in the middle of the aligned soles, at rest
    mid = 0.5 * (centers["l"][:2] + (sw[-1][:2] + np.array([ZMP_OFFSET, 0.0])))
    assert np.linalg.norm(S[-1].com[:2] - mid) < 0.002 and S[-1].done
    np.testing.assert_allclose(S[-1].com_velocity, 0.0)
    assert np.linalg.norm(S[-60].com_velocity) < 0.005               # at rest before the end too (0.12 s earlier)


def test_aligned_feet_are_not_stepped_and_bad_input_is_refused():
    soles, centers = _feet("l", 0.005)
    assert plan_alignment(M, soles, centers, np.array([0.0, 0.0, 0.6]), DT) is None
    soles, centers = _feet("l", 0.2)
    with pytest.raises(ValueError):
        plan_alignment(M, soles, centers, np.array([np.nan, 0.0, 0.6]), DT)
    with pytest.raises(ValueError):
        plan_alignment(M, soles, centers, np.array([0.0, 0.0, 0.05]), DT)


def test_after_a_walking_stop_the_feet_end_side_by_side_and_the_robot_stands():
    """walking_estop at 1.0 km/h, the stop after the first swing, then the upper body home and the feet step:
    the rear foot ends within 1 cm of side by side (along the heading and across, at the step width), yaw within
    2 deg, the robot stands on both feet (no fall) with the CoG back between them, the e-stop holding."""
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "benchmarks"))
    import estop_trials

    tr = estop_trials.run_trial(1.0, "ds_start", step=1)
    m = tr.metrics
    assert m["fell"] is False and m["state"] == "holding", tr.messages[-5:]
    assert abs(m["align_offset_before_m"]) > 0.1                     # a real step: the feet were a stride apart
    assert abs(m["align_final_offset_along_m"]) < 0.01
    assert abs(m["align_final_lateral_error_m"]) < 0.01
    assert abs(m["align_final_yaw_diff_deg"]) < 2.0
    assert m["align_stands"] and m["align_both_feet_in_contact_end"]
    assert m["align_final_cog_from_feet_mid_m"] < 0.03
    # the mux never handed the robot back to walking, and the stop's own figures end where the step starts
    assert (tr.trace["active"][tr.trace["t"] >= m["trigger_time_s"]] == "estop").all()
    assert abs(m["final_cog_vs_n3_m"]) <= 0.02


def test_the_controller_steps_after_home_refuses_a_release_while_stepping_then_holds_the_feet_side_by_side():
    """EstopController on synthetic observations (CoG at rest): stopped -> (home) aligning -> holding; the IK's
    feet end side by side at the step width; a release while aligning is refused; with align_feet off: holding."""
    import dataclasses as dc

    from humfall_ros.control.contract import CentroidalObservation, Observation, stamp_ns_of
    from humfall_ros.estop.config import EstopConfig
    from humfall_ros.estop.controller import EstopController, EstopState
    from humfall_ros.sim.world import STANDING_POSTURE

    @dc.dataclass
    class Pattern:
        walking: bool = True
        support: str = "double"
        phase_fraction: float = 0.0
        step_index: int = 5
        com_ref: np.ndarray = dc.field(default_factory=lambda: np.array([0.06, -0.02, 0.742]))
        com_velocity_ref: np.ndarray = dc.field(default_factory=lambda: np.array([0.1, 0.02, 0.0]))
        zmp_ref: np.ndarray = dc.field(default_factory=lambda: np.array([0.0, -0.09, 0.0]))
        left_foot: tuple = (0.15, 0.09, 0.0, 0.0)
        right_foot: tuple = (0.0, -0.09, 0.0, 0.0)

    # joints with the feet a stride apart (as a walking stop leaves them): the IK onto the pattern's feet
    from humfall_ros.estop.controller import feet_from_soles
    from humfall_ros.estop.posture import configuration_from_feet
    from humfall_ros.model.ik import ComTask, FrameTask, PostureTask, WholeBodyIK

    pat = Pattern()
    feet = feet_from_soles(M, {"l": pat.left_foot, "r": pat.right_foot})
    q = configuration_from_feet(M, M.joint_vector(STANDING_POSTURE), feet, "r")
    ik = WholeBodyIK(M)
    for _ in range(300):
        q = ik.solve(q, [*(FrameTask(M.foot_link[x], pin.SE3(feet[x].rotation, feet[x].position), hard=True)
                           for x in "lr"), ComTask(np.array([0.075, 0.0, 0.72]), weight=100.0),
                         PostureTask(q[7:].copy(), weight=1e-3)], 0.01).q
    stride_joints = q[7:].copy()

    def obs(t, **inputs):
        joints = stride_joints.copy()
        st = CentroidalObservation(
            com=np.array([0.06, -0.02, 0.742]), com_velocity=np.zeros(3), cop=np.array([0.02, -0.09, 0.0]),
            capture_point=np.zeros(3), angular_momentum=np.zeros(3), support_polygon=np.zeros((0, 2)),
            feet_center=np.array([0.075, 0.0, 0.105]), lean_angle=0.0, lean_direction=0.0, normal_force=569.0,
            left_contact=True, right_contact=True, cop_on_edge=False)
        return Observation(stamp_ns_of(t), joints, np.zeros_like(joints), st, "locomotion", dict(inputs))

    off = EstopController(M, EstopConfig.defaults(trigger_time=0.0, home_duration=0.1, align_feet=False), DT)
    ctl = EstopController(M, EstopConfig.defaults(trigger_time=0.0, home_duration=0.1), DT)
    seen, refused, k = [], False, 0
    while ctl.state != EstopState.HOLDING or off.state != EstopState.HOLDING:
        o = obs(k * DT, **{"walking/state": Pattern()})
        off.step(o)
        if ctl.state == EstopState.ALIGNING and not refused:
            o.inputs["estop_release"] = True
            refused = True
        assert ctl.step(o) is not None
        seen.append(ctl.state)
        k += 1
        assert k * DT < 12.0, ctl.messages[-3:]
    assert EstopState.ALIGNING in seen, ctl.messages
    assert seen.index(EstopState.ALIGNING) > seen.index(EstopState.STOPPED)
    assert any("release refused: aligning" in m for m in ctl.messages)
    assert EstopState.ALIGNING not in {off.state} and off.align is None
    s = ctl.status
    assert s.align_swing == "r" and s.align_offset == pytest.approx(-0.15, abs=0.01)
    assert s.align_end_time - s.align_start_time == pytest.approx(ctl.align.duration, abs=2 * DT)
    d = M.model.createData()
    pin.framesForwardKinematics(M.model, d, ctl.q_ik)
    soles = {x: d.oMf[M.frame_ids[M.sole_frame[x]]] for x in "lr"}
    along, lateral = side_by_side_offsets(soles, 0.0, ctl.align.width, "l")
    assert abs(along) < 2e-3 and abs(lateral) < 2e-3
    assert abs(soles["r"].translation[2] - soles["l"].translation[2]) < 1e-3
