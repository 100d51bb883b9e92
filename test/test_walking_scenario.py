"""The scenario's walk: schedule, gait-phase times against the controller's own WalkingState in a
ClosedLoop run, the node's controller and message conversions, and lockstep repeatability."""
from __future__ import annotations

import math

import numpy as np
import pytest

from humfall_ros import scenario
from humfall_ros.model.humanoid import load_model
from humfall_ros.sim.closed_loop import ClosedLoop
from humfall_ros.walking.controller import WalkingState, from_scenario
from humfall_ros.walking.scenario import PHASES, WalkScenarioError, phase_time, walk_schedule, walking_config


def walk_sc(*sets):
    return scenario.load("walking", list(sets))


def test_walk_schedule_from_the_scenario():
    sc = walk_sc("walk.speed_kmh=1.8", "walk.steps=7", "walk.turn_rate_deg_s=10", "walk.start_time=0.3")
    [(t, cmd)] = walk_schedule(sc)
    assert t == pytest.approx(0.3)
    assert cmd.speed == pytest.approx(0.5) and cmd.yaw_rate == pytest.approx(math.radians(10)) and cmd.n_steps == 7
    assert walk_schedule(walk_sc("walk.steps=0")) == []
    with pytest.raises(WalkScenarioError, match="direction"):
        walk_schedule(walk_sc("walk.direction_deg=90"))


def test_walking_config_takes_the_walk_timing_and_refuses_a_contradiction():
    cfg = walking_config(walk_sc("walk.step_period=0.7", "walk.double_support=0.12"))
    assert cfg.step_period == pytest.approx(0.7) and cfg.double_support == pytest.approx(0.12)
    with pytest.raises(WalkScenarioError, match="contradicts"):
        walking_config(walk_sc("walk.step_period=0.7", "params.locomotion.step_period=0.8"))


def test_phase_time_matches_the_controllers_walking_state():
    """Every gait event of a 1-step walk (step 0 and the stop step 1) at the stamp phase_time gives."""
    sc = walk_sc("walk.steps=1", "walk.start_time=0.2")
    model = load_model()
    ctl = from_scenario(sc, model)
    events = {(k, p): phase_time(sc, {"step": k, "phase": p}, model) for k in (0, 1) for p in PHASES}
    end = max(events.values()) + 0.01
    loop = ClosedLoop(sc, controllers=[ctl])
    states: dict[int, WalkingState] = {}
    try:
        while loop.world.time < end:
            obs = loop.step()
            states[round(obs.time * 500)] = ctl.state
    finally:
        loop.close()
    for (k, p), t in events.items():
        i = round(t * 500)
        now, before = states[i], states[i - 1]
        assert now.walking, (k, p)
        if p.startswith("ss") and p != "ss_end":
            assert now.support == ("single_left" if k % 2 == 0 else "single_right"), (k, p)  # right swings first
            assert now.step_index == k + 1
        else:
            assert now.support == "double", (k, p)
        if p in ("ds_start", "ss_start", "ss_end"):
            assert now.phase_fraction == 0.0 and (before.support != now.support or k == 0 and p == "ds_start"), (k, p)
        else:  # the first tick at half of the phase
            assert now.phase_fraction >= 0.5 > before.phase_fraction, (k, p)
    assert events[(1, "ds_start")] == pytest.approx(events[(0, "ss_end")])
    with pytest.raises(WalkScenarioError):
        phase_time(sc, {"step": 2, "phase": "ss_start"})


def test_two_lockstep_walks_are_identical():
    sc = walk_sc("walk.steps=1", "walk.start_time=0.1")
    runs = []
    for _ in range(2):
        loop = ClosedLoop(sc, controllers=[from_scenario(sc, load_model())])
        try:
            runs.append(loop.run(2.4).joint_positions)
        finally:
            loop.close()
    assert runs[0].shape[0] == 1200
    np.testing.assert_array_equal(runs[0], runs[1])
    assert np.max(np.abs(runs[0][-1] - runs[0][0])) > 0.05  # it did move (the walk started)


def test_node_builds_the_in_process_controller_and_converts_messages():
    pytest.importorskip("humfall_interfaces.msg")
    from geometry_msgs.msg import Twist

    from humfall_ros import params as params_mod
    from humfall_ros.nodes.estop_planner import walking_state_from_msg
    from humfall_ros.nodes.locomotion import make_controller, walk_command_from_twist, walking_state_to_msg

    model = load_model()
    p = params_mod.defaults("locomotion")
    p["scenario"] = "walking"
    node_ctl, ref = make_controller(p, model), from_scenario(walk_sc(), model)
    assert node_ctl.cfg == ref.cfg and node_ctl.dt == ref.dt and node_ctl.schedule == ref.schedule
    p["scenario"] = ""
    assert make_controller(p, model).schedule == []

    t = Twist()
    t.linear.x, t.angular.z = 0.3, 0.1
    cmd = walk_command_from_twist(t)
    assert (cmd.speed, cmd.yaw_rate) == (0.3, 0.1)
    t.linear.x = float("nan")
    with pytest.raises(ValueError, match="non-finite"):
        walk_command_from_twist(t)

    s = WalkingState(stamp_ns=5, walking=True, support="single_left", phase_fraction=0.25, step_index=3,
                     com_ref=np.array([0.1, 0.02, 0.7]), com_velocity_ref=np.array([0.3, 0.0, 0.0]),
                     zmp_ref=np.array([0.12, 0.09, 0.0]), left_foot=(0.1, 0.09, 0.0, 0.2),
                     right_foot=(0.0, -0.09, 0.03, -0.1), next_footsteps=[("r", 0.3, -0.09, 0.0, 4, False)])
    from humfall_interfaces.msg import WalkingState as WalkingStateMsg

    from humfall_ros.recording import cdr

    # what the e-stop node reads: the bytes the node publishes, decoded
    back = walking_state_from_msg(cdr.decoder(WalkingStateMsg)(cdr.encoder(WalkingStateMsg)(walking_state_to_msg(s))))
    assert back.support == "single_left" and back.step_index == 3 and back.phase_fraction == 0.25
    np.testing.assert_allclose(back.com_ref, s.com_ref)
    np.testing.assert_allclose(back.left_foot, s.left_foot, atol=1e-12)
    np.testing.assert_allclose(back.right_foot, s.right_foot, atol=1e-12)
