"""A protective-step plan executed on the 3-D robot (issue 14), in process: the task-space swing.

``config/multicontact_plans/multicontact_push_30J.json`` is the paper objective's 30 J plan (LF/RF -> LF -> LF/RF:
the right foot steps 0.6 m forward in 0.44 s). Tracked joint by joint (``swing_control`` "joints") the swing foot
never leaves the ground on the 3-D robot (the planar plan has no lateral weight transfer; docs/multicontact.md
"Session 24"); with ``swing_control`` "task" the legs follow paper 1's step controller (``control.step_control``) and
the step happens where and when the plan puts it, and with ``swing_attitude_weight`` the base keeps the plan's
pitch through the swing. The robot still falls after the step (the plan's stop is not
reproduced in 3-D, "Session 26"), which is why these tests judge the step, not the end.
"""
import pytest

from humfall_ros import scenario
from humfall_ros.multicontact.executor import StoredPlan
from humfall_ros.nodes.multicontact_executor import plan_path
from humfall_ros.sim.multicontact_run import RunConfig, execute


def _run(**run) -> tuple[StoredPlan, dict]:
    plan = StoredPlan.load(plan_path("multicontact_push_30J"))
    force = plan.meta["push_force"]
    sc = scenario.load("multicontact_push", [f"push.0.force=[{force[0]}, {force[1]}, {force[2]}]"])
    sc["controllers"] = []
    return plan, execute(sc, segments=plan.segments, start_time=plan.take_over_time,
                         cfg=RunConfig.of(settle=0.5, **run))


@pytest.fixture(scope="module")
def runs():
    return {"joints": _run(swing_control="joints"), "task": _run(swing_control="task"),
            "task_no_attitude": _run(swing_control="task", swing_attitude_weight=0.0),
            "task_deadbeat": _run(swing_control="task", swing_attitude_gain=1.0, swing_posture_gain=1.0)}


def _landing(r: dict) -> dict:
    (ev,) = [e for e in r["contact_events"] if e["change"] == "add"]
    return ev


def test_the_stored_step_plan_is_a_step_from_its_own_state(runs):
    plan, r = runs["task"]
    assert [s["change"] for s in r["plan"]["segments"]] == ["remove", "add", ""]
    assert r["plan"]["stored_state_error_q"] < 1e-6 and r["plan"]["stored_state_error_v"] < 1e-6
    assert r["state_at_plan"]["ke_planar"] == pytest.approx(plan.meta["target_ke"], rel=0.05)


def test_the_task_space_swing_lifts_the_foot_and_lands_it_where_and_when_planned(runs):
    _, r = runs["task"]
    ev = _landing(r)
    assert ev["swing_clearance_m"] > 0.05, ev                     # lifted (the swing's apex is 0.1 m)
    assert abs(ev["executed_time"] - ev["planned_time"]) < 0.06, ev
    assert abs(ev["executed_x"] - ev["planned_x"]) < 0.1, ev       # a 0.6 m step
    assert ev["sole_x_error_m"] == pytest.approx(ev["executed_sole_x"] - ev["planned_x"])
    assert abs(ev["sole_x_error_m"]) < 0.08, ev                   # the sole's centre, as the plan's position
    assert r["switches"][-1]["why"] == "touchdown"
    s = r["series"]                                                # per tick, for the plots: the same swing
    assert len(s["base_pitch"]) == len(s["t"]) == len(s["foot_height"]["RF"])
    in_swing = [h for t, h in zip(s["t"], s["foot_height"]["RF"]) if 0.0 < t <= ev["executed_time"] + 1e-9]
    assert max(in_swing) == pytest.approx(ev["swing_clearance_m"])
    assert 0 < s["plan"]["t"][-1] <= r["plan"]["duration"] and max(s["plan"]["foot_height"]["RF"]) < 0.05
    # the CoM, capture point and toes beside the plan's: both start from the take-over's state, and the right toe
    # ends where the step put it
    assert len(s["com_x"]) == len(s["capture_point_x"]) == len(s["toe_x"]["RF"]) == len(s["t"])
    k0 = next(k for k, t in enumerate(s["t"]) if t >= 0.0)
    assert abs(s["capture_point_x"][k0] - s["plan"]["capture_point_x"][0]) < 0.03
    assert abs(s["com_x"][k0] - s["plan"]["com_x"][0]) < 0.01
    assert s["toe_x"]["RF"][-1] > s["toe_x"]["RF"][k0] + 0.5 and s["plan"]["toe_x"]["RF"][-1] > 0.7
    (swing,) = r["task_swings"]
    assert swing["foot"] == "RF" and swing["duration"] == pytest.approx(ev["planned_time"], abs=0.003)


def test_the_attitude_task_keeps_the_base_on_the_plans_pitch_through_the_swing(runs):
    """The stance leg's hip / ankle strategy (``swing_attitude_weight``): without it the base runs ahead."""
    with_task = runs["task"][1]["task_swings"][0]["pitch_error_max"]
    without = runs["task_no_attitude"][1]["task_swings"][0]["pitch_error_max"]
    assert with_task < 0.06 and without > 2 * with_task, (with_task, without)


def test_tracking_the_joints_drags_the_swing_foot(runs):
    """The reason for the task-space swing: joint tracking leaves the swing foot on the ground."""
    _, r = runs["joints"]
    ev = _landing(r)
    assert ev["swing_clearance_m"] < 0.01, ev
    # back on the ground well before the plan's landing, and far short of it (the report matches the plan's landing
    # to the lasting touchdown nearest its time since session 41; until then it took the first change, a chatter
    # before 0.1 s: the dragged foot left the ground at 0.19 s and touched again at 0.31 s, 0.56 m short)
    assert ev["executed_time"] < ev["planned_time"] - 0.1 and ev["executed_x"] < ev["planned_x"] - 0.3, ev
    # the swing it made is less than 60 % of the planned one (0.11 s of 0.25 s)
    (rel,) = [e for e in r["contact_events"] if e["change"] == "remove"]
    assert ev["executed_time"] - rel["executed_time"] < 0.6 * (ev["planned_time"] - rel["planned_time"]), (rel, ev)


def test_the_stance_foot_stays_loaded_through_the_swing(runs):
    """With per-tick gains of 1 on the IK's posture and attitude tasks (session 26) the first swing tick drove the
    stance leg at its speed limits and the robot left the ground for ~0.1 s at the lift-off (the estimator's
    stance contact flag off); the defaults keep the stance foot on the ground through the swing."""
    default = runs["task"][1]["task_swings"][0]["stance_unloaded_s"]
    deadbeat = runs["task_deadbeat"][1]["task_swings"][0]["stance_unloaded_s"]
    assert default < 0.01 and deadbeat > 0.05, (default, deadbeat)
