"""The executor's stop balance (issue 14, session 41) on step plans executed on the 3-D robot, in process.

After a plan's last foot landing the executor no longer tracks the plan's stop: from the touchdown the safe fall's
capture balance (``fall.capture_balance``: a settle posture over the point of the soles' segment nearest the capture
point, the ankle and hip strategies, the lateral balance) stops the robot, and once it has stopped a second settle
posture moves the CoM to the soles' middle, so that the rear foot comes down. Two stored plans for the
``multicontact_push`` scenario, paper objective:

* ``multicontact_push_30J_step.json``: 30 J (536 N), the defaults, one step. Tracking the plan's stop, the robot
  topples forward over the front foot (``test_multicontact_exec_margin.py``).
* ``multicontact_push_60J_step_margin25.json``: 60 J (727 N), ``step_capture_margin`` 0.25, one step (a 0.7 m
  step landing with ~100 J). Tracking the plan's stop, the robot turns over the front foot onto an arm.

Measured with ``benchmarks/bench_multicontact_exec.py --objective paper [--set step_capture_margin=0.25]``: with the
stop balance every step plan of the defaults from 20 to 50 J (every 5 J) and every one with the margin 0.25 from 20
to 60 J ends at rest on both feet, upright (docs/multicontact.md "Session 41").
"""
import pytest

from humfall_ros import scenario
from humfall_ros.multicontact.executor import StoredPlan
from humfall_ros.nodes.multicontact_executor import plan_path
from humfall_ros.sim.multicontact_run import RunConfig, execute

PLANS = {30: "multicontact_push_30J_step", 60: "multicontact_push_60J_step_margin25"}


def _run(ke: int, **run) -> dict:
    plan = StoredPlan.load(plan_path(PLANS[ke]))
    force = plan.meta["push_force"]
    sc = scenario.load("multicontact_push", [f"push.0.force=[{force[0]}, {force[1]}, {force[2]}]"])
    sc["controllers"] = []
    return execute(sc, segments=plan.segments, start_time=plan.take_over_time, cfg=RunConfig.of(**run))


@pytest.fixture(scope="module")
def runs():
    return {(ke, on): _run(ke, stop_balance=on, **({} if on else {"settle": 2.0})) for ke in PLANS
            for on in (True, False)}


def test_the_plans_are_one_step_each_from_their_own_state(runs):
    for ke in PLANS:
        r = runs[(ke, True)]
        assert r["planned_final_mode"] == "LF/RF" and r["plan"]["stored_state_error_q"] < 1e-6
        assert [(e["extremity"], e["change"]) for e in r["contact_events"]] == [("RF", "remove"), ("RF", "add")]
    assert StoredPlan.load(plan_path(PLANS[60])).meta["planner_overrides"] == {"step_capture_margin": 0.25}


@pytest.mark.parametrize("ke", sorted(PLANS))
def test_with_the_stop_balance_the_robot_ends_upright_at_rest_on_both_feet(runs, ke):
    r = runs[(ke, True)]
    sb = r["stop_balance"]
    # it took over at the step's touchdown, and shifted the CoM back once the robot had stopped
    (touchdown,) = [s["plan_time"] for s in r["switches"] if s["why"] == "touchdown"]
    assert sb is not None and sb["plan_time_s"] == pytest.approx(touchdown)
    assert sb["shift_plan_time_s"] is not None and sb["shift_plan_time_s"] > sb["plan_time_s"] + 1.0
    assert r["final_mode"] == "LF/RF" and r["final_mode_matches_plan"]
    assert r["final_ke"] < 0.5 and not r["other_links_touching"] and r["final_trunk_tilt_deg"] < 5.0
    assert all(abs(r["final_limb_height_m"][f]) < 0.005 for f in ("LF", "RF")), r["final_limb_height_m"]
    assert r["success"]


@pytest.mark.parametrize("ke", sorted(PLANS))
def test_tracking_the_plans_stop_instead_the_robot_falls_over_the_front_foot(runs, ke):
    r = runs[(ke, False)]
    assert r["stop_balance"] is None
    assert not r["success"] and r["final_trunk_tilt_deg"] > 60.0 and r["other_links_touching"]


@pytest.mark.parametrize("name", ["multicontact_push_20J_step_margin25", "multicontact_push_40J_step_margin25"])
def test_the_shipped_plans_for_the_3d_robot_end_upright_at_rest(name):
    """The plans made for execution (paper objective, ``planner.FOR_EXECUTION``; session 42), the 40 J one the
    scenario's default: one step each, at rest on both feet with nothing else touching."""
    from humfall_ros.multicontact.planner import FOR_EXECUTION

    plan = StoredPlan.load(plan_path(name))
    assert plan.meta["objective"] == "paper" and plan.meta["planner_overrides"] == FOR_EXECUTION
    force = plan.meta["push_force"]
    sc = scenario.load("multicontact_push", [f"push.0.force=[{force[0]}, {force[1]}, {force[2]}]"])
    sc["controllers"] = []
    r = execute(sc, segments=plan.segments, start_time=plan.take_over_time, cfg=RunConfig())
    assert [(e["extremity"], e["change"]) for e in r["contact_events"]] == [("RF", "remove"), ("RF", "add")]
    assert r["stop_balance"] is not None and r["final_mode"] == "LF/RF" and r["final_ke"] < 0.5
    assert not r["other_links_touching"] and r["final_trunk_tilt_deg"] < 5.0 and r["success"]


def test_the_scenario_executes_a_plan_made_for_the_3d_robot_by_default():
    sc = scenario.load("multicontact_push")
    (c,) = sc["controllers"]
    plan = StoredPlan.load(plan_path(c["params"]["plan_file"]))
    assert plan.meta["objective"] == "paper" and plan.meta["push_force"][0] == sc["push"][0]["force"][0]
