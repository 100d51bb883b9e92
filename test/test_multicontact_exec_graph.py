"""The multicontact executor node over ROS (``humfall up multicontact_push``): it takes over at the
plan file's take-over time and gives the joint states of the in-process loop, bit for bit.

Its own ROS_DOMAIN_ID on localhost (conftest.in_ros_domain). The plan is a small synthetic one
(a two-foot self-motion raising the arms), so the test does not depend on the planner.
"""
import numpy as np

from humfall_ros import launch, params, scenario
from humfall_ros.model.humanoid import load_model as load_humanoid
from humfall_ros.multicontact.collocation import Segment
from humfall_ros.multicontact.executor import StoredPlan
from humfall_ros.multicontact.model import load_model as load_planar
from humfall_ros.nodes.multicontact_executor import make_controller, plan_path
from humfall_ros.sim.closed_loop import run_scenario
from humfall_ros.suite import locomotion_controller

from test_contract_graph import _rows, bag_topic

TAKE_OVER = 0.6


def synthetic_plan(path):
    pm, hm = load_planar(), load_humanoid()
    q0 = np.zeros(pm.n)
    for i, j in enumerate(pm.joint_names):
        q0[3 + i] = hm.standing_posture.get(j, 0.0)
    q1 = q0.copy()
    for j in ("l_shoulder_pitch", "r_shoulder_pitch"):
        q1[3 + pm.joint_names.index(j)] -= 0.6
    N, T = 5, 0.4
    t = np.linspace(0, T, N)
    s = (1 - np.cos(np.pi * t / T)) / 2
    q = q0 + np.outer(s, q1 - q0)
    v = np.outer(np.pi / (2 * T) * np.sin(np.pi * t / T), q1 - q0)
    seg = Segment(kind="self_motion", mode=("LF", "RF"), target_mode=("LF", "RF"), change="", extremity="",
                  time=t, q=q, v=v, a=np.zeros_like(q), u=np.zeros((N, pm.m)), lam=np.zeros((N, 0)), rows=[],
                  ke=np.zeros(N), success=True, status="synthetic", iterations=0, nlp_time=0.0, seed_duration=T,
                  attempts=1, max_violation=0.0)
    StoredPlan([seg], TAKE_OVER, {"synthetic": True}).save(path)


def test_the_executor_node_takes_over_at_the_plan_time_and_matches_the_in_process_loop(in_ros_domain, tmp_path):
    plan = tmp_path / "plan.json"
    synthetic_plan(plan)
    ov = ["duration=1.2", "push.0.force=[100.0, 0.0, 0.0]", f"controllers.0.params.plan_file={plan}"]
    status, r = launch.up("multicontact_push", None, ov, runs_dir=str(tmp_path / "runs"), quiet=True)
    assert status == 0, r
    assert "multicontact_executor_multicontact" in r["node_exit_codes"]
    active = dict(bag_topic(r["bag"], "/mux/state", "active"))
    assert active[int(0.598e9)] == "locomotion"
    assert active[int(0.602e9)] == "multicontact"          # the tick after the take-over tick
    assert active[int(1.19e9)] == "multicontact"            # never released
    sc = scenario.load("multicontact_push", ov)
    p = {**params.defaults("multicontact_executor"), "plan_file": str(plan)}
    hm = load_humanoid()
    mine = run_scenario(sc, controllers=[locomotion_controller(sc, hm), make_controller(p, hm)],
                        priorities={"multicontact": 40})
    ros = _rows(r, len(mine.joint_positions))
    assert np.array_equal(ros, mine.joint_positions)
    # and the arms did follow the plan (raised by ~0.6 rad over 0.4 s)
    hm = load_humanoid()
    k = hm.joint_names.index("l_shoulder_pitch")
    assert mine.joint_positions[-1, k] - mine.joint_positions[int(TAKE_OVER * 500), k] < -0.4


def test_a_protective_step_over_ros_matches_the_in_process_loop(in_ros_domain, tmp_path):
    """The shipped 30 J step plan (``multicontact_push_30J.json``) with the task-space swing (the default): the
    swing's IK reads the IMU and the estimator's CoM from the node's inputs; over ROS the joint states equal the
    in-process loop's bit for bit through the swing, and the swing foot lands near its planned time."""
    stored = StoredPlan.load(plan_path("multicontact_push_30J"))
    f = stored.meta["push_force"]
    ov = ["duration=1.2", f"push.0.force=[{f[0]}, {f[1]}, {f[2]}]",
          "controllers.0.params.plan_file=multicontact_push_30J"]
    status, r = launch.up("multicontact_push", None, ov, runs_dir=str(tmp_path / "runs"), quiet=True)
    assert status == 0, r
    sc = scenario.load("multicontact_push", ov)
    p = {**params.defaults("multicontact_executor"), "plan_file": "multicontact_push_30J"}
    assert p["swing_control"] == "task"
    hm = load_humanoid()
    ex = make_controller(p, hm)
    mine = run_scenario(sc, controllers=[locomotion_controller(sc, hm), ex], priorities={"multicontact": 40})
    ros = _rows(r, len(mine.joint_positions))
    assert np.array_equal(ros, mine.joint_positions)
    assert ex.task_swings and ex.task_swings[0]["foot"] == "RF"
    # the landing segment ended on the right foot's touchdown near its planned end (0.437 s): the foot was in the
    # air until then (tracked joint by joint it stays loaded and the switch comes at the window's first tick, 0.288 s)
    seg, when, why = ex.switches[-1]
    assert why == "touchdown" and when > sum(float(s.time[-1]) for s in stored.segments[:2]) - 0.05, ex.switches


def test_a_60J_step_stopped_by_the_stop_balance_over_ros_matches_the_in_process_loop(in_ros_domain, tmp_path):
    """The shipped 60 J plan made with ``step_capture_margin`` 0.25 (one step) over ROS to its end: after the step's
    touchdown the executor's stop balance (the default) stops the robot and brings the CoM back over both feet. The
    joint states equal the in-process loop's bit for bit through the whole run, the balance and its shift started,
    and nothing but the feet touched the ground: the robot ends standing."""
    name = "multicontact_push_60J_step_margin25"
    stored = StoredPlan.load(plan_path(name))
    f = stored.meta["push_force"]
    ov = ["duration=5.6", f"push.0.force=[{f[0]}, {f[1]}, {f[2]}]", f"controllers.0.params.plan_file={name}"]
    status, r = launch.up("multicontact_push", None, ov, runs_dir=str(tmp_path / "runs"), quiet=True)
    assert status == 0, r
    sc = scenario.load("multicontact_push", ov)
    p = {**params.defaults("multicontact_executor"), "plan_file": name}
    assert p["stop_balance"]
    hm = load_humanoid()
    ex = make_controller(p, hm)
    mine = run_scenario(sc, controllers=[locomotion_controller(sc, hm), ex], priorities={"multicontact": 40})
    ros = _rows(r, len(mine.joint_positions))
    assert np.array_equal(ros, mine.joint_positions)
    assert ex.stop_balance is not None and ex.stop_shift is not None
    assert ex.stop_shift_time > ex.stop_balance_time + 1.0
    for m in (mine.metrics, r["metrics"]):
        assert m["landing_time_s"] is None                  # no link but the feet ever touched
        # standing at the end, in the lunge the 0.7 m step leaves (measured 0.59 m; 0.74 m standing quiet; a fallen
        # robot's CoM is below 0.35 m)
        assert m["landing_com"][2] > 0.5
