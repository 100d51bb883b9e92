"""The safe fall over ROS, with real processes: ftb_monitor + safe_fall_controller in the launched suite.

``humfall up standing_push --controller stepping_inertia``: the FTB fires, the fall controller
takes over through the mux, publishes its decision, steps and does not touch the target; the
joint states are bit-identical to the in-process run (``sim.fall_runs`` on ``ClosedLoop``).
Each test runs in its own ROS_DOMAIN_ID on localhost (conftest.in_ros_domain).
"""
import math

import numpy as np
import pytest

from humfall_ros import launch, scenario
from humfall_ros.sim import fall_runs as runs

from test_suite_graph import joint_states_from_bag

DURATION = 2.6  # s: trigger 0.60 s, touchdown 0.85 s, hand-back 2.37 s (2.42 s with the CoM velocity filter)


def bag_messages(bag, topic):
    from mcap_ros2.reader import read_ros2_messages

    return [m.ros_msg for m in read_ros2_messages(str(bag), topics=[topic])]


@pytest.fixture
def run_up(in_ros_domain, tmp_path):
    def run(name, controller, *overrides):
        return launch.up(name, controller, list(overrides), runs_dir=str(tmp_path / "runs"), quiet=True)
    return run


def test_stepping_inertia_standing_push_over_ros_equals_in_process(run_up):
    ov = [f"duration={DURATION}"]
    status, r = run_up("standing_push", "stepping_inertia", *ov)
    assert status == 0, r
    bag = r["bag"]
    # the FTB: a status every tick, the event latched once
    events = bag_messages(bag, "/fall_event")
    # the event, latched once, then its clearing: the step captures the push and the FTB sees the recovery
    assert [e.cleared for e in events] == [False, True] and "recovered" in events[1].reason
    ev = events[0]
    assert ev.trigger_mode == "ftb" and math.isfinite(ev.control_duration) and len(ev.support_polygon) >= 2
    statuses = bag_messages(bag, "/ftb/status")
    stamps = sorted({s.header.stamp.sec * 10**9 + s.header.stamp.nanosec for s in statuses})
    assert len(stamps) >= int(DURATION * 500) - 2
    assert sum(s.event_tick for s in statuses) >= 1
    # the decision, once
    decisions = bag_messages(bag, "/safe_fall/decision")
    assert len(decisions) == 1
    d = decisions[0]
    assert d.step_case in ("step_left", "step_right") and d.cell_count >= 2000
    # the mux: safe_fall drives from the tick after the trigger on
    active = [(m.header.stamp.sec * 10**9 + m.header.stamp.nanosec, m.active) for m in bag_messages(bag, "/mux/state")]
    t_ev = ev.header.stamp.sec * 10**9 + ev.header.stamp.nanosec
    # after the clearing, safe_fall hands back to locomotion once, for good, within the run
    t_clear = events[1].header.stamp.sec * 10**9 + events[1].header.stamp.nanosec
    assert all(a == "safe_fall" for k, a in active if t_ev < k <= t_clear)
    assert all(a == "locomotion" for k, a in active if 0 < k <= t_ev)
    after = [a for k, a in sorted(active) if k > t_clear]
    k_hb = after.index("locomotion")
    assert set(after[:k_hb]) <= {"safe_fall"} and set(after[k_hb:]) == {"locomotion"}
    # identical to the in-process loop
    sc = scenario.load("standing_push", ov + ["controller=stepping_inertia"])
    mine = runs.run(sc, stop_after_landing_s=None)
    ros = np.array([p for _, _, p in joint_states_from_bag(bag)])[:len(mine.joint_positions)]
    assert ros.shape == mine.joint_positions.shape
    assert np.array_equal(ros, mine.joint_positions)
    assert mine.decision.case == d.step_case
    assert np.array_equal(np.asarray(mine.decision.landing), np.asarray(d.landing))
    assert mine.fall_event.stamp_ns == t_ev
    # the target is not touched (ground truth, the bridge's metrics)
    assert r["metrics"]["min_target_distance_m"] >= 0.05


HANDBACK_DURATION = 3.5  # s: trigger 0.60 s, touchdown 0.85 s, FTB recovered 2.35 s, hand-back 2.37 s (balance_kd 0.1)


def test_captured_push_handed_back_to_locomotion_over_ros_equals_in_process(run_up):
    """standing_push with stepping: captured; the FTB's recovery publishes a cleared fall_event, the safe-fall
    controller releases and locomotion stands where the feet are, on the same tick as in process."""
    ov = [f"duration={HANDBACK_DURATION}"]
    status, r = run_up("standing_push", "stepping", *ov)
    assert status == 0, r
    bag = r["bag"]
    events = bag_messages(bag, "/fall_event")
    assert [e.cleared for e in events] == [False, True]       # the event, then its clearing (latched)
    t_ev = events[0].header.stamp.sec * 10**9 + events[0].header.stamp.nanosec
    t_clear = events[1].header.stamp.sec * 10**9 + events[1].header.stamp.nanosec
    assert t_clear > t_ev and "recovered" in events[1].reason
    active = sorted((m.header.stamp.sec * 10**9 + m.header.stamp.nanosec, m.active)
                    for m in bag_messages(bag, "/mux/state"))
    active = [(k, a) for k, a in active if k > 0]   # the first tick: "none" (nothing commanded yet)
    switches = [(k, a) for (k0, a0), (k, a) in zip(active, active[1:]) if a != a0]
    assert active[0][1] == "locomotion" and [a for _, a in switches] == ["safe_fall", "locomotion"]
    t_hb = switches[1][0]
    assert t_hb > t_clear
    sc = scenario.load("standing_push", ov + ["controller=stepping"])
    mine = runs.run(sc, stop_after_landing_s=None)
    ros = np.array([p for _, _, p in joint_states_from_bag(bag)])[:len(mine.joint_positions)]
    assert ros.shape == mine.joint_positions.shape
    assert np.array_equal(ros, mine.joint_positions)
    k_hb = next(k for k in range(1, len(mine.active_sources)) if mine.active_sources[k - 1] == "safe_fall"
                and mine.active_sources[k] == "locomotion")
    assert round(k_hb * 2e6) == t_hb                            # the same hand-back tick (500 Hz)
    assert not r["metrics"]["fell"]


WALKING_DURATION = 8.0  # s: the push at 7.1 s in a right swing, the fall event 7.18 s, the decision after the push


def test_a_walking_take_over_decided_after_the_push_over_ros_equals_in_process(run_up):
    """walking_push with stepping: the take-over of a walking robot waits while the push residual reads the push
    (the default since session 23, from the estimator's capture points of the last ticks), then steps; over ROS the
    wait ends on the same tick and the joint states are bit-identical to the in-process loop."""
    ov = [f"duration={WALKING_DURATION}"]
    status, r = run_up("walking_push", "stepping", *ov)
    assert status == 0, r
    bag = r["bag"]
    decisions = bag_messages(bag, "/safe_fall/decision")
    assert decisions and decisions[0].step_case in ("step_left", "step_right")
    sc = scenario.load("walking_push", ov + ["controller=stepping"])
    mine = runs.run(sc, stop_after_landing_s=None)
    assert any("decision deferred" in x for x in mine.reasons)
    ros = np.array([p for _, _, p in joint_states_from_bag(bag)])[:len(mine.joint_positions)]
    assert ros.shape == mine.joint_positions.shape
    assert np.array_equal(ros, mine.joint_positions)
    assert mine.decision.case == decisions[-1].step_case      # the last one published: after the swing's re-plans
    assert np.array_equal(np.asarray(mine.decision.landing), np.asarray(decisions[-1].landing))
