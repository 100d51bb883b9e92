"""A stored multi-contact plan executed on the 3-D robot in PyBullet (issue 14), in process.

The shipped 20, 40 and 60 J plans (config/multicontact_plans/multicontact_push_<KE>J.json, made by
``benchmarks/bench_multicontact_exec.py --save-plans config/multicontact_plans``) replayed after the
same push: the take-over state must be the one it was planned from (the simulation is deterministic;
if the world changed, regenerate the plans), and the robot must end at rest in the planned mode
(both hands: ``ExecutorConfig.both_hands``) with nothing else on the ground (issue 14's executed figure). The 20 J
plan needs the base pitch feedback, ``ExecutorConfig.base_pitch_gain``: open loop it ends with the head on the
ground on the 20 ms servos, docs/multicontact.md "Session 24"; the 10 J plan, which lifts a foot, does either way.
"""
import pytest

from humfall_ros import scenario
from humfall_ros.multicontact.executor import StoredPlan
from humfall_ros.nodes.multicontact_executor import plan_path
from humfall_ros.sim.multicontact_run import execute


@pytest.fixture(scope="module", params=[20, 40, 60])
def run60(request):
    plan = StoredPlan.load(plan_path(f"multicontact_push_{request.param}J"))
    force = plan.meta["push_force"]
    sc = scenario.load("multicontact_push", [f"push.0.force=[{force[0]}, {force[1]}, {force[2]}]"])
    sc["controllers"] = []
    return plan, execute(sc, segments=plan.segments, start_time=plan.take_over_time)


def test_the_stored_plan_starts_from_the_state_it_was_planned_from(run60):
    plan, r = run60
    assert r["take_over_time"] == pytest.approx(plan.take_over_time)
    assert r["plan"]["stored_state_error_q"] < 1e-6 and r["plan"]["stored_state_error_v"] < 1e-6
    # the push gives the stated energy
    assert r["state_at_plan"]["ke_planar"] == pytest.approx(plan.meta["target_ke"], rel=0.05)


def test_the_robot_ends_at_rest_in_the_planned_mode_with_nothing_else_on_the_ground(run60):
    plan, r = run60
    assert r["final_mode_matches_plan"], (r["final_mode"], r["planned_final_mode"])
    assert r["final_ke"] < 0.5
    assert r["other_links_touching"] == {}, r["other_links_touching"]
    for ev in r["contact_events"]:               # every planned landing happened, near its planned time
        assert ev["executed_time"] is not None, ev
        assert abs(ev["executed_time"] - ev["planned_time"]) < 0.2, ev
        assert abs(ev["executed_x"] - ev["planned_x"]) < 0.3, ev
    assert r["momentum_error_ns_max"] < 3.0      # no solver velocity clamp: momentum (nearly) conserved
    assert r["base_pitch_feedback_ticks"] > 0    # the feedback ran (on the IMU)


class _RecordingPlanner:
    """Records the request the run sends and answers "no plan" (the run then releases and only measures)."""

    def __init__(self):
        from humfall_ros.multicontact.model import load_model
        self.model = load_model()
        self.requests = []

    def plan(self, req):
        self.requests.append(req)
        return {"success": False, "reason": "recording only", "contact_sequence": [], "node_ke": [], "final_ke": None,
                "initial_ke": None, "nlp_count": 0, "landings": [], "segments": []}


def test_a_walking_push_is_planned_from_the_stance_foot_alone():
    """``execute(initial_mode="LF")`` (session 28): a push at the start of a right swing is planned from single
    support: the request names LF, and the state it carries has the left sole flat on the ground and the right foot
    free (above it); the standing default stays LF/RF."""
    import numpy as np

    from humfall_ros.multicontact import contacts as C
    from humfall_ros.multicontact.modes import Environment, parse_mode
    from humfall_ros.sim.multicontact_run import INITIAL_MODE

    assert INITIAL_MODE == "LF/RF"
    sc = scenario.load("walking_push", ["obstacles=[]", "push.0.force=[450.0, 0.0, 0.0]"])
    sc["controllers"] = []
    planner = _RecordingPlanner()
    r = execute(sc, planner=planner, initial_mode="LF", duration=7.3)
    (req,) = planner.requests
    assert req["initial_mode"] == "LF"
    assert r["plan"]["success"] is False and r["plan"]["reason"] == "recording only"
    q = np.asarray(req["q"])
    pm = planner.model
    for row in C.contact_rows(parse_mode("LF"), Environment()):
        if row.axis == "n":
            assert abs(pm.point(row.point, q)[1]) < 1e-6, row.point
    assert min(pm.point("RF_toe", q)[1], pm.point("RF_heel", q)[1]) > 0.005
    with pytest.raises(ValueError, match="unknown extremity"):
        execute(sc, planner=planner, initial_mode="LF/XX")


def test_a_20J_plan_without_one_foot_alone_is_planned_live_and_executes_at_rest():
    """Session 37: with ``single_foot_modes`` false the 20 J push (the paper's objective, the defaults otherwise)
    is planned from the measured 3-D state as a hand landing, not the foot lift the defaults plan (which falls: the
    planar plan has no lateral weight shift), and the robot ends at rest on the planned extremities with nothing
    else on the ground (the bench's success: the planned feet and hands touching, a foot may rest unloaded)."""
    from humfall_ros.multicontact.modes import one_foot_alone, parse_mode
    from humfall_ros.multicontact.planner import FallPlanner

    plan = StoredPlan.load(plan_path("multicontact_push_20J"))
    force = plan.meta["push_force"]
    sc = scenario.load("multicontact_push", [f"push.0.force=[{force[0]}, {force[1]}, {force[2]}]"])
    sc["controllers"] = []
    planner = FallPlanner.from_params(single_foot_modes=False)
    r = execute(sc, planner=planner)
    assert r["plan"]["success"], r["plan"]["reason"]
    seq = r["plan"]["contact_sequence"]
    assert not any(one_foot_alone(parse_mode(m)) for m in seq) and set(parse_mode(seq[-1])) & {"LH", "RH"}, seq
    assert r["success"], (r["final_mode_touching"], r["planned_final_mode"], r["final_ke"], r["other_links_touching"])
    assert r["final_ke"] < 0.5 and r["other_links_touching"] == {}
    hands = [ev for ev in r["contact_events"] if ev["extremity"] in ("LH", "RH")]
    assert hands and all(ev["executed_time"] is not None and abs(ev["executed_time"] - ev["planned_time"]) < 0.1
                         for ev in hands), hands
