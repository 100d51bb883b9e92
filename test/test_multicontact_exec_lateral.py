"""The executor's lateral balance (issue 14, session 39) on a step plan executed on the 3-D robot, in process.

``config/multicontact_plans/multicontact_push_40J_step.json`` is the paper objective's 40 J plan with the defaults of
session 39 (LF/RF -> LF -> LF/RF: the right foot steps 0.52 m forward in 0.26 s, then a self-motion stops the planar
model). A planar plan keeps the CoM between the feet; after the step that is outside the hull's diagonal side. With
the rolls held (``lateral_gain`` 0, every session before 39) the robot stops in x and topples sideways over that side
(traced: the CoM 5 cm off the soles' segment); with the lateral balance (the default) it ends at rest on both feet,
nothing else touching. Both runs track the plan's stop (``stop_balance`` off: the stop balance of session 41, the
default since, replaces the plan's stop after the touchdown, and with it the lateral balance of the plan's tracking).
"""
import pytest

from humfall_ros import scenario
from humfall_ros.multicontact.executor import StoredPlan
from humfall_ros.nodes.multicontact_executor import plan_path
from humfall_ros.sim.multicontact_run import RunConfig, execute


def _run(**run) -> dict:
    plan = StoredPlan.load(plan_path("multicontact_push_40J_step"))
    force = plan.meta["push_force"]
    sc = scenario.load("multicontact_push", [f"push.0.force=[{force[0]}, {force[1]}, {force[2]}]"])
    sc["controllers"] = []
    return execute(sc, segments=plan.segments, start_time=plan.take_over_time,
                   cfg=RunConfig.of(settle=2.5, stop_balance=False, **run))


@pytest.fixture(scope="module")
def runs():
    return {"lateral": _run(), "held": _run(lateral_gain=0.0)}


def test_the_stored_plan_is_a_step_ending_on_both_feet(runs):
    r = runs["lateral"]
    assert r["planned_final_mode"] == "LF/RF"
    assert [e["change"] for e in r["contact_events"]] == ["remove", "add"]
    assert r["plan"]["stored_state_error_q"] < 1e-6


def test_with_the_lateral_balance_the_step_plan_ends_at_rest_on_both_feet(runs):
    r = runs["lateral"]
    assert r["lateral_ticks"] > 500 and 0.0 < r["lateral_offset_max_rad"] <= RunConfig().executor.lateral_max + 1e-12
    assert r["final_mode"] == "LF/RF" and r["final_mode_matches_plan"]
    assert r["final_ke"] < 0.5 and not r["other_links_touching"]
    assert r["success"]


def test_with_the_rolls_held_it_falls(runs):
    r = runs["held"]
    assert r["lateral_ticks"] == 0
    assert not r["success"] and r["final_trunk_tilt_deg"] > 60.0
