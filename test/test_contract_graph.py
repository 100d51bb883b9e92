"""The controller contract over ROS, with real processes: hand-over, bumpless transfer and
identity with the in-process loop (humfall_ros.sim.closed_loop).

Each test runs in its own ROS_DOMAIN_ID on localhost (conftest.in_ros_domain).
"""
import json
import pathlib

import numpy as np
import pytest

from humfall_ros import launch, scenario
from humfall_ros.sim.closed_loop import ClosedLoop, run_scenario
from humfall_ros.suite import locomotion_controller

import takeover_controller as tc
from test_suite_graph import joint_states_from_bag

TAKEOVER = pathlib.Path(tc.__file__).resolve()


def takeover_overrides(take_over=0.3, release=0.8):
    return [f"controllers=[{{node: {TAKEOVER}, source: test, priority: 50, "
            f"params: {{source: test, take_over_time: {take_over}, release_time: {release}}}}}]"]


def bag_topic(bag, topic, field):
    from mcap_ros2.reader import read_ros2_messages

    return [(m.ros_msg.header.stamp.sec * 10**9 + m.ros_msg.header.stamp.nanosec, getattr(m.ros_msg, field))
            for m in read_ros2_messages(str(bag), topics=[topic])]


def in_process(sc, with_takeover):
    loop = ClosedLoop(sc)
    if with_takeover:
        c = sc["controllers"][0]
        test = tc.TakeoverController(loop.model, c["source"], c["params"]["take_over_time"],
                                     c["params"]["release_time"])
        loop.controllers = [locomotion_controller(sc, loop.model), test]
        from humfall_ros.control.mux import CommandMux, mux_order

        loop.mux = CommandMux(mux_order(["locomotion", "test"], {"test": 50}), loop.model.joint_names,
                              loop.mux.timeout)
    try:
        r = loop.run()
    finally:
        loop.close()
    return r


@pytest.fixture
def run_up(in_ros_domain, tmp_path):
    def run(name, *overrides):
        return launch.up(name, None, list(overrides), runs_dir=str(tmp_path / "runs"), quiet=True)
    return run


def _rows(r, n_ticks):
    # the bag's distinct ticks, in order (start-up retransmissions repeat tick 0)
    rows = joint_states_from_bag(r["bag"])
    return np.array([p for _, _, p in rows])[:n_ticks]


def test_standing_push_is_identical_in_process_and_over_ros(run_up):
    status, r = run_up("standing_push", "duration=1.2")
    assert status == 0
    sc = scenario.load("standing_push", ["duration=1.2"])
    mine = in_process(sc, with_takeover=False)
    ros = _rows(r, len(mine.joint_positions))
    assert ros.shape == mine.joint_positions.shape == (600, 22)
    assert np.array_equal(ros, mine.joint_positions)  # bit for bit


def test_a_controller_takes_over_releases_and_both_loops_agree(run_up):
    ov = takeover_overrides(0.3, 0.8)
    status, r = run_up("standing_quiet", "duration=1.4", *ov)
    assert status == 0, r
    assert r["metrics"]["fell"] is False
    # the active source over time, as scripted: locomotion, test from 0.3 s, locomotion again after 0.8 s
    active = bag_topic(r["bag"], "/mux/state", "active")
    by_time = {k: a for k, a in active}
    assert by_time[int(0.2e9)] == "locomotion"
    assert by_time[int(0.302e9)] == "test"  # the tick after the take-over tick
    assert by_time[int(0.79e9)] == "test"
    assert by_time[int(0.802e9)] == "locomotion"
    switches = [a for i, (_, a) in enumerate(active) if i == 0 or a != active[i - 1][1]]
    assert switches[-3:] == ["locomotion", "test", "locomotion"]
    sc = scenario.load("standing_quiet", ["duration=1.4", *ov])
    mine = in_process(sc, with_takeover=True)
    ticks = sorted(by_time)
    assert [by_time[k] for k in ticks[:len(mine.active_sources)]] == mine.active_sources
    ros = _rows(r, len(mine.joint_positions))
    assert np.array_equal(ros, mine.joint_positions)
    # bumpless: no joint jumps when control changes hands (both ways)
    q = mine.joint_positions
    step = np.abs(np.diff(q, axis=0)).max(axis=1)
    for t_switch in (0.3, 0.8):
        k = int(round(t_switch * 500))
        assert step[k - 2:k + 10].max() < 0.01, (t_switch, step[k - 2:k + 10].max())


def test_two_controllers_with_one_priority_are_refused_before_anything_starts(run_up, tmp_path):
    from humfall_ros.scenario import ScenarioError

    with pytest.raises(ScenarioError, match="priorit"):
        run_up("standing_quiet", f"controllers=[{{node: {TAKEOVER}, source: test, priority: 10}}]")
    assert not (tmp_path / "runs").exists()


def test_a_controller_that_goes_silent_stalls_the_run_with_its_name(run_up, tmp_path):
    # a lockstep source that answers up to t = 0.2 s and then never again: after stall_timeout the bridge
    # names it and the tick, writes the metrics and exits 3 (tick 0's wait is start_timeout's: start-up)
    ov = [f"controllers=[{{node: {TAKEOVER}, source: test, priority: 50, "
          f"params: {{take_over_time: -1.0, mute_time: 0.2}}}}]",
          "params.sim_bridge.stall_timeout=3.0"]
    status, r = run_up("standing_quiet", "duration=1.0", *ov)
    assert status != 0
    m = r["metrics"]
    assert m["stalled_source"] == "test" and m["stalled_at_s"] == pytest.approx(0.2)
    log = (pathlib.Path(r["bag"]).parent / "logs" / "sim_bridge.log").read_text()
    assert "no command from test" in log and "tick 100" in log and "stall_timeout" in log
    assert json.loads((pathlib.Path(r["bag"]).parent / "result.json").read_text())["node_exit_codes"]["sim_bridge"] == 3


def test_composed_mode_runs_the_same_graph_in_one_process(in_ros_domain, tmp_path):
    # --compose: estimator, locomotion and the test controller in one process, each its own node
    ov = takeover_overrides(0.3, 0.8)
    status, r = launch.up("standing_quiet", None, ["duration=1.4", *ov], runs_dir=str(tmp_path / "runs"),
                          quiet=True, compose=True)
    assert status == 0, r
    assert set(r["node_exit_codes"]) == {"recorder", "composed", "sim_bridge"}
    sc = scenario.load("standing_quiet", ["duration=1.4", *ov])
    mine = in_process(sc, with_takeover=True)
    ros = _rows(r, len(mine.joint_positions))
    assert np.array_equal(ros, mine.joint_positions)
    active = [a for _, a in bag_topic(r["bag"], "/mux/state", "active")]
    assert "test" in active and active[-1] == "locomotion"


def test_a_walk_is_identical_in_process_and_over_ros(run_up):
    # walking (locomotion with its walk schedule, IMU steering) and the e-stop node listening, as humfall up runs them
    ov = ["duration=4.0", "walk.steps=2"]
    status, r = run_up("walking", *ov)
    assert status == 0, r
    assert r["metrics"]["fell"] is False
    assert set(r["node_exit_codes"]) >= {"locomotion", "estop_planner"}
    res = run_scenario(scenario.load("walking", ov))
    ros = _rows(r, len(res.joint_positions))
    assert np.array_equal(ros, res.joint_positions)
    steps = {m for _, m in bag_topic(r["bag"], "/walking/state", "step_index")}
    assert max(steps) >= 2  # it did walk
