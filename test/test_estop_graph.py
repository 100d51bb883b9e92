"""The e-stop over ROS with real processes (`launch.up`): a standing stop identical to the in-process loop,
``estop/status`` every tick, and `humfall estop` (humfall_ros/nodes/estop_cli.py) triggering a running suite.

`humfall up` starts ``estop_planner`` when the scenario walks or schedules a trigger (``estop.time`` /
``estop.at``), and ``ClosedLoop(sc)`` runs the same suite in process; for a standing robot with no scheduled
trigger (``humfall estop`` from outside) the test adds the node to the launcher's plan (``_with_estop_node``).
Each test runs in its own ROS_DOMAIN_ID on localhost (conftest.in_ros_domain).
"""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from humfall_ros import launch, scenario
from humfall_ros.control.mux import DEFAULT_PRIORITIES, mux_order
from humfall_ros.sim.closed_loop import ClosedLoop

from test_contract_graph import bag_topic
from test_suite_graph import joint_states_from_bag

PUSH = "push=[{time: 0.5, force: [100.0, 0.0, 0.0], point: [0.0, 0.0, 0.2], link: chest, duration: 0.2}]"


def _with_estop_node(monkeypatch, params: dict) -> None:
    """Start estop_planner (source "estop", its built-in priority) in every launch.up of this test."""
    original = launch.plan_nodes

    def plan(sc, run_dir, record):
        nodes = original(sc, run_dir, record)
        if any(n.name == "estop_planner" for n in nodes):
            return nodes
        nodes.insert(-1, launch.NodeSpec("estop_planner", "humfall_ros.nodes.estop_planner", dict(params), "estop",
                                         DEFAULT_PRIORITIES["estop"]))
        sources = [n for n in nodes if n.source]
        order = mux_order([n.source for n in sources], {n.source: n.priority for n in sources})
        nodes[-1].params["command_sources"] = order
        nodes[-1].params["lockstep_sources"] = order
        return nodes

    monkeypatch.setattr(launch, "plan_nodes", plan)


@pytest.fixture
def run_up(in_ros_domain, tmp_path):
    def run(name, *overrides):
        return launch.up(name, None, list(overrides), runs_dir=str(tmp_path / "runs"), quiet=True)
    return run


def in_process(sc):
    """The suite ``humfall up`` starts for ``sc`` (locomotion + the e-stop fed walking/state), in process."""
    loop = ClosedLoop(sc)
    try:
        r = loop.run()
        (estop,) = [c for c in loop.controllers if c.source == "estop"]
        return r, estop
    finally:
        loop.close()


def test_a_standing_stop_over_ros_is_identical_to_the_in_process_loop(run_up, tmp_path):
    ov = ["duration=2.0", PUSH, "estop.time=0.7"]  # the launcher starts estop_planner for the scheduled trigger
    status, r = run_up("standing_quiet", *ov)
    assert status == 0, r
    assert r["metrics"]["fell"] is False
    sc = scenario.load("standing_quiet", ov)
    mine, ctl = in_process(sc)
    # the mux's source per tick: locomotion, then estop from the tick after the trigger's, to the end
    active = dict(bag_topic(r["bag"], "/mux/state", "active"))
    ticks = sorted(active)
    assert [active[k] for k in ticks[:len(mine.active_sources)]] == mine.active_sources
    assert active[int(0.698e9)] == "locomotion" and active[int(0.702e9)] == "estop"
    assert active[ticks[-1]] == "estop"
    rows = np.array([p for _, _, p in joint_states_from_bag(r["bag"])])[:len(mine.joint_positions)]
    assert rows.shape == mine.joint_positions.shape
    assert np.array_equal(rows, mine.joint_positions)  # bit for bit
    # estop/status every tick, stamped like the tick; the plan in it is the in-process plan
    states = dict(bag_topic(r["bag"], "/estop/status", "state"))
    assert set(ticks) <= set(states)
    assert states[int(0.698e9)] == "idle" and states[int(0.7e9)] == "stopping"
    assert states[ticks[-1]] == ctl.status.state
    n3 = dict(bag_topic(r["bag"], "/estop/status", "n_major"))[ticks[-1]][2]
    assert n3 == ctl.plan.major.n3
    feasible = dict(bag_topic(r["bag"], "/estop/status", "feasible"))[ticks[-1]]
    assert feasible is True and ctl.plan.feasible
    # Fig. 4/5/10-style plots from the bag: the stop's start and n3 as the node published them
    from humfall_ros.estop.plots import plot_run, run_from_bag

    run = run_from_bag(r["bag"], "standing stop over ROS")
    assert run.start == pytest.approx(0.7) and run.n3 == n3 and len(run.polygon) >= 4
    for path in plot_run(run, tmp_path):
        assert path.stat().st_size > 10_000
    # result.json's estop section from the bag
    from humfall_ros.estop.metrics import estop_result_from_bag

    sec = estop_result_from_bag(r["bag"], fell=r["metrics"]["fell"])
    assert sec["feasible"] is True and sec["fell"] is False and sec["n3_m"] == n3
    assert abs(sec["final_cog_major_m"] - n3) < 0.02 and abs(sec["final_cog_minor_m"]) < 0.01
    # (the margin is -inf: the in-process standing stop shows one tick without contact as a sole rocks back)
    assert not np.isnan(sec["min_cop_margin_m"]) and np.isfinite(sec["max_cop_minor_m"])
    print(f"standing stop over ROS: {len(ticks)} ticks identical; n3 {n3:.4f} m, end {ctl.plan.end_time:.2f} s, "
          f"final state {ctl.status.state}, wall {r['wall_time_s']:.1f} s")


def test_humfall_estop_triggers_a_running_suite(run_up, monkeypatch, in_ros_domain):
    _with_estop_node(monkeypatch, {"walking_state_input": False})
    cli = subprocess.Popen([sys.executable, "-m", "humfall_ros.nodes.estop_cli", "--timeout", "60"],
                           env=in_ros_domain, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        status, r = run_up("standing_quiet", "duration=2.5")
        out, _ = cli.communicate(timeout=30)
    finally:
        if cli.poll() is None:
            cli.kill()
    assert cli.returncode == 0, out
    assert "delivered on /estop to" in out
    assert status == 0, r
    assert r["metrics"]["fell"] is False
    states = bag_topic(r["bag"], "/estop/status", "state")
    triggered = [k for k, s in states if s != "idle"]
    assert triggered, "the trigger never reached the node"
    active = dict(bag_topic(r["bag"], "/mux/state", "active"))
    last = max(active)
    assert active[last] == "estop"          # taken over, never handed back without a release
    assert dict(states)[last] in ("stopping", "stopped", "holding")


def test_the_cli_says_when_nobody_listens(in_ros_domain):
    p = subprocess.run([sys.executable, "-m", "humfall_ros.nodes.estop_cli", "--release", "--timeout", "0.5"],
                       env=in_ros_domain, capture_output=True, text=True, timeout=60)
    assert p.returncode == 1
    assert "no subscriber on /estop/release from estop_planner" in p.stderr


def test_the_status_message_carries_every_status_field_and_walking_state_converts():
    from humfall_interfaces.msg import WalkingState as WalkingStateMsg

    from humfall_ros.estop.controller import EstopStatus
    from humfall_ros.nodes.estop_planner import status_to_msg, walking_state_from_msg

    s = EstopStatus(state="stopping", active=True, n_major=(0.0, -0.1, 0.1), gains_minor=(1.0, 2.0, 3.0),
                    final_com=(0.1, 0.2, 0.7), frame_origin=(0.3, 0.4), major_axis=(0.0, 1.0), feasible=True,
                    com_ref=(1.0, 2.0, 3.0), reason="x", feet_frame_origin=(0.5, 0.6), feet_major_axis=(0.6, 0.8),
                    feet_support_polygon=((0.0, 0.0), (0.1, 0.0), (0.1, 0.2)), feet_yaw_off_pattern=0.2)
    m = status_to_msg(s)
    assert (m.feet_frame_origin.y, m.feet_major_axis.x, m.feet_yaw_off_pattern) == (0.6, 0.6, 0.2)
    assert [(p.x, p.y) for p in m.feet_support_polygon] == [(0.0, 0.0), (0.1, 0.0), (0.1, 0.2)]
    assert m.state == "stopping" and m.active and m.feasible and m.reason == "x"
    assert list(m.n_major) == [0.0, -0.1, 0.1] and list(m.gains_minor) == [1.0, 2.0, 3.0]
    assert (m.final_com.x, m.final_com.y, m.final_com.z) == (0.1, 0.2, 0.7)
    assert (m.frame_origin.x, m.major_axis.y, m.com_ref.z) == (0.3, 1.0, 3.0)
    assert np.isnan(m.omega_c) and np.isnan(m.zmp_ref.x)
    msg_fields = set(m.get_fields_and_field_types()) - {"header"}
    import dataclasses

    assert msg_fields == {f.name for f in dataclasses.fields(EstopStatus)} - {"stamp_ns"}
    w = WalkingStateMsg(walking=True, support=WalkingStateMsg.SINGLE_LEFT, phase_fraction=0.25, step_index=4)
    w.com_ref.x, w.com_velocity_ref.x, w.zmp_ref.y = 0.5, 0.3, -0.09
    w.left_foot.position.x = 0.4
    if hasattr(w.left_foot, "yaw"):        # humfall_interfaces/Footstep
        w.left_foot.yaw = 0.2
    else:                                  # geometry_msgs/Pose
        w.left_foot.orientation.z, w.left_foot.orientation.w = np.sin(0.1), np.cos(0.1)
    ws = walking_state_from_msg(w)
    assert ws.walking and ws.support == "single_left" and ws.step_index == 4 and ws.com_ref[0] == 0.5
    assert ws.left_foot[0] == 0.4 and ws.left_foot[3] == pytest.approx(0.2) and ws.zmp_ref[1] == -0.09
