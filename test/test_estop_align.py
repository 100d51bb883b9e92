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
