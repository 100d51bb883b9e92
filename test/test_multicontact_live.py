"""A multi-contact plan made at the push's end from the robot's sensors (``multicontact.live``, the executor's
``plan_live``; session 43).

In process: the sensed 3-D state (IMU, encoders, the estimator's CoM and CoM velocity) against the simulator's, and
the plan made from it executed to rest. Over ROS (``multicontact_push_live``, its own ROS_DOMAIN_ID on localhost):
the executor node plans inside its take-over tick and the joint states equal the in-process loop's, bit for bit.
"""
import numpy as np
import pytest

from humfall_ros import launch, params, scenario
from humfall_ros.model.humanoid import load_model as load_humanoid
from humfall_ros.multicontact.planner import PROFILES, FallPlanner
from humfall_ros.nodes.multicontact_executor import make_controller
from humfall_ros.sim import multicontact_run as mr
from humfall_ros.sim.closed_loop import run_scenario
from humfall_ros.suite import locomotion_controller

from test_contract_graph import _rows


def test_a_plan_from_the_sensors_sees_the_true_state_and_executes_to_rest():
    """30 J forward (536 N): the sensed planar state is within 2 mm / 0.05 (m or rad)/s of the simulator's; the
    execution profile's library answers; the step is executed to rest on both feet, nothing else touching."""
    sc = scenario.load("multicontact_push", ["push.0.force=[536.0, 0.0, 0.0]"])
    planner = FallPlanner.from_params(**PROFILES["execution"])
    r = mr.execute(sc, planner=planner, cfg=mr.RunConfig(), plan_from="sensors")
    st = r["state_at_plan"]
    assert st["sensed_minus_truth_q_max"] < 0.002 and st["sensed_minus_truth_v_max"] < 0.05, st
    assert st["sensed_ke_planar_projected"] == pytest.approx(st["ke_planar_projected"], rel=0.01)
    assert r["plan"]["success"] and r["plan"]["source"] == "library", r["plan"]
    assert r["plan"]["contact_sequence"] == ["LF/RF", "RF", "LF/RF"]
    assert r["success"] and r["final_ke"] < 0.5 and r["final_mode_matches_plan"], r["executor_reason"]
    assert not r["other_links_touching"] and r["final_trunk_tilt_deg"] < 5.0


def test_plan_live_needs_a_take_over_time_and_excludes_a_plan_file():
    p = {**params.defaults("multicontact_executor"), "plan_live": True}
    hm = load_humanoid()
    with pytest.raises(ValueError, match="plan_live needs start_time"):
        make_controller(p, hm)
    with pytest.raises(ValueError, match="plan_file or plan_live"):
        make_controller({**p, "start_time": 0.6, "plan_file": "multicontact_push_30J"}, hm)


def test_the_executor_node_plans_live_and_matches_the_in_process_loop(in_ros_domain, tmp_path):
    """``humfall up multicontact_push_live`` (40 J): the node's plan from the sensors at 0.6 s, then its execution;
    the same as the in-process loop with the same controller, bit for bit, through the step's touchdown."""
    ov = ["duration=1.2"]
    status, r = launch.up("multicontact_push_live", None, ov, runs_dir=str(tmp_path / "runs"), quiet=True)
    assert status == 0, r
    sc = scenario.load("multicontact_push_live", ov)
    p = {**params.defaults("multicontact_executor"), **sc["controllers"][0]["params"]}
    hm = load_humanoid()
    ex = make_controller(p, hm)
    mine = run_scenario(sc, controllers=[locomotion_controller(sc, hm), ex], priorities={"multicontact": 40})
    info = ex.plan_source.info
    assert info["success"] and info["source"] == "library" and info["contact_sequence"] == ["LF/RF", "RF", "LF/RF"]
    ros = _rows(r, len(mine.joint_positions))
    assert np.array_equal(ros, mine.joint_positions)
    assert ex.task_swings and ex.switches[-1][2] == "touchdown"   # the step landed within the 1.2 s
    log = next((tmp_path / "runs").glob("*/logs/multicontact_executor_multicontact.log")).read_text()
    assert "plan from the sensors at 0.600 s: success=True source=library LF/RF -> RF -> LF/RF" in log, log[-1500:]


def test_a_sensed_state_that_cannot_be_used_gives_no_plan_and_says_why():
    """No IMU, or a NaN in the estimator's state: no plan (the executor then releases with the reason), no crash."""
    import types

    from humfall_ros.multicontact.live import SensedPlanSource

    hm = load_humanoid()
    src = SensedPlanSource(FallPlanner.from_params(), hm, profile="execution")
    n = len(hm.joint_names)
    state = types.SimpleNamespace(com=np.array([0.0, 0.0, 0.8]), com_velocity=np.array([np.nan, 0.0, 0.0]))
    imu = (np.array([0.0, 0.0, 0.0, 1.0]), np.zeros(3))
    obs = types.SimpleNamespace(state=state, inputs={"imu": imu}, joint_position=np.zeros(n),
                                joint_velocity=np.zeros(n), time=0.6)
    assert src(obs) is None and "non-finite" in src.info["reason"]
    obs.inputs = {}
    assert src(obs) is None and "no IMU" in src.info["reason"]
    with pytest.raises(ValueError, match="unknown planner_profile"):
        SensedPlanSource(FallPlanner.from_params(), hm, profile="bogus")
