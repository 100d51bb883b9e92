"""The safe fall's shell without a graph: message converters (exact round trips), the FTB as a ClosedLoop
monitor (latched event), the fall controller acting on the tick's ftb/status, the safe-fall metrics."""
import math

import numpy as np
import pytest

from humfall_ros.control.contract import CentroidalObservation, Observation
from humfall_ros.fall import ftb as core
from humfall_ros.fall.controller import fall_event_of
from humfall_ros.sim.metrics import FallMetrics


def _state(com=(0.05, 0.0, 0.75), vel=(0.0, 0.0, 0.0)):
    poly = np.array([[0.145, -0.16], [0.145, 0.16], [-0.095, 0.16], [-0.095, -0.16]])
    return CentroidalObservation(np.array(com, float), np.array(vel, float), np.array([0.14, 0.0, 0.0]),
                                 np.array([0.05, 0.0, 0.0]) + np.array(vel) * math.sqrt(0.75 / 9.81),
                                 np.zeros(3), poly, np.zeros(3), 0.05, 0.0, 570.0, True, True, False)


def _obs(t, state):
    return Observation(int(round(t * 1e9)), np.zeros(0), np.zeros(0), state)


def _event(t=0.6):
    z = np.array([0.1, 0.2, 0.0])
    return core.FallEvent(int(t * 1e9), "ftb", "why", z, z + 0.1, True, z, z * 2, 0.3, 0.81, 0.26, 1.001, 0.001,
                          0.12, np.array([0.05, 0.0, 0.75]), np.array([0.6, -0.1, 0.0]),
                          np.array([[0.145, 0.02], [0.145, -0.16]]), False)


def test_monitor_latches_the_event_from_the_trigger_on():
    mon = core.FtbMonitor(core.FtbConfig(debounce_ms=4.0))
    assert mon.name == "ftb/status" and mon.latched == {}
    st = mon.step(_obs(0.0, _state()))
    assert st.fall_event is None and mon.latched == {}
    fast = _state(com=(0.12, 0.0, 0.75), vel=(0.9, 0.0, 0.0))  # well past the crest of the toe edge
    events = []
    for k in range(1, 8):
        st = mon.step(_obs(0.002 * k, fast))
        events.append(st.event)
    fired = [e for e in events if e is not None]
    assert len(fired) == 1                                  # once, on the edge
    assert st.fall_event is fired[0] and mon.latched == {"fall_event": fired[0]}   # carried on every later tick
    mon.reset()
    assert mon.latched == {"fall_event": None} and mon.state is core.FtbState.BALANCED   # reset clears it
    assert core.FtbMonitor().latched == {}                  # nothing to clear before any event


def _fire(mon, t0=0.0):
    fast = _state(com=(0.12, 0.0, 0.75), vel=(0.9, 0.0, 0.0))  # well past the crest of the toe edge
    st = None
    for k in range(1, 8):
        st = mon.step(_obs(t0 + 0.002 * k, fast))
    assert st.state is core.FtbState.FALLING and st.fall_event is not None
    return st.fall_event, t0 + 0.014


def test_recovery_clears_the_event_once_and_a_new_trigger_is_a_new_event():
    mon = core.FtbMonitor(core.FtbConfig(debounce_ms=4.0, recover_s=0.1))
    mon.step(_obs(0.0, _state()))
    ev, t = _fire(mon)
    assert mon.latched == {"fall_event": ev}
    cleared = []
    for k in range(1, 100):
        st = mon.step(_obs(t + 0.002 * k, _state()))   # still, upright, inside the boundary
        if st.cleared is not None:
            cleared.append((k, st))
    assert len(cleared) == 1                              # once, on the edge
    k, st = cleared[0]
    assert st.cleared is ev and st.state is core.FtbState.BALANCED and st.fall_event is None
    assert "recovered" in st.reason and k * 0.002 >= 0.1 - 1e-9    # after recover_s
    assert mon.latched == {"fall_event": None}            # the loop drops the latched input
    ev2, _ = _fire(mon, t + 0.2)
    assert ev2 is not ev and mon.latched == {"fall_event": ev2}


def test_recovery_from_fallen_by_timeout_but_not_lying_or_moving():
    import dataclasses

    cfg = core.FtbConfig(debounce_ms=4.0, recover_s=0.1, falling_timeout_s=0.1)
    rocking = dataclasses.replace(_state(), lean_angle=math.radians(12.0))   # above recover_lean_deg
    for final, recovers in ((_state(), True), (_state(com=(0.05, 0.0, 0.3)), False),
                            (_state(vel=(0.0, 0.2, 0.0)), False)):
        mon = core.FtbMonitor(cfg)
        mon.step(_obs(0.0, _state()))
        _, t = _fire(mon)
        for k in range(1, 80):
            st = mon.step(_obs(t + 0.002 * k, rocking))
        assert st.state is core.FtbState.FALLEN and st.fall_event is not None   # the timeout
        t += 0.16
        for k in range(1, 100):
            st = mon.step(_obs(t + 0.002 * k, final))
        assert (st.state is core.FtbState.BALANCED) is recovers
        assert (st.fall_event is None) is recovers
    # recover_from_fallen off: fallen stays fallen
    mon = core.FtbMonitor(dataclasses.replace(cfg, recover_from_fallen=False))
    mon.step(_obs(0.0, _state()))
    _, t = _fire(mon)
    for k in range(1, 200):
        st = mon.step(_obs(t + 0.002 * k, rocking if k < 80 else _state()))
    assert st.state is core.FtbState.FALLEN


def test_cleared_fall_event_message_reads_as_no_event():
    pytest.importorskip("humfall_interfaces")
    from humfall_ros.nodes.controller_node import fall_event_input
    from humfall_ros.nodes.ftb_monitor import cleared_msg, event_to_msg

    ev = _event()
    assert fall_event_input(event_to_msg(ev)) is True
    m = cleared_msg(ev, int(4.5e9), "recovered")
    assert m.cleared and fall_event_input(m) is None
    assert m.header.stamp.sec == 4 and m.header.stamp.nanosec == 500_000_000 and m.reason == "recovered"
    assert not event_to_msg(ev, m).cleared                 # a reused message is a fall event again
    # every controller node that reads fall_event reads a cleared one as "no event" (the e-stop read any
    # message as "falling": over ROS it would yield after a hand-back, in process it would not)
    from humfall_ros.nodes import estop_planner, locomotion
    for mod in (estop_planner, locomotion):
        fe = [i for i in mod.node_inputs() if i.name == "fall_event"]
        assert len(fe) == 1, mod.__name__
        cleared = cleared_msg(ev, int(4.5e9), "recovered")
        assert fe[0].convert(event_to_msg(ev)) is True and fe[0].convert(cleared) is None, mod.__name__


def test_controller_acts_on_the_status_of_the_tick_not_on_the_latched_topic():
    ev = _event()
    st = core.FtbStatus(ev.stamp_ns, core.FtbState.FALLING, "ftb", core.FtbFeatures(), 0.0, "", None, ev)
    obs = _obs(0.7, _state())
    obs.inputs = {"ftb/status": st, "fall_event": _event(0.3)}
    assert fall_event_of(obs) is ev
    obs.inputs = {"ftb/status": core.FtbStatus(0, core.FtbState.BALANCED, "ftb", core.FtbFeatures(), 0.0),
                  "fall_event": _event(0.3)}
    assert fall_event_of(obs) is None   # a latched event the status does not carry is not acted on
    obs.inputs = {"fall_event": ev}
    assert fall_event_of(obs) is ev     # no status at all: the latched input


def test_messages_round_trip_exactly():
    pytest.importorskip("humfall_interfaces.msg")
    from humfall_interfaces.msg import FtbStatus

    from humfall_ros.nodes.ftb_monitor import event_from_msg, event_to_msg, status_from_msg, status_to_msg

    ev = _event()
    back = event_from_msg(event_to_msg(ev))
    for f in ("stamp_ns", "trigger_mode", "reason", "leading_corner", "fall_direction", "control_duration",
              "energy_ratio", "walking"):
        assert getattr(back, f) == getattr(ev, f)
    for f in ("leading_edge_start", "cop", "reference_point", "com", "com_velocity", "support_polygon"):
        assert np.array_equal(getattr(back, f), getattr(ev, f))
    feats = core.features_of(_state(com=(0.12, 0.0, 0.75), vel=(0.9, 0.0, 0.0)))
    st = core.FtbStatus(ev.stamp_ns, core.FtbState.FALLING, "ftb", feats, 0.25, "r", ev, ev)
    msg = status_to_msg(st, FtbStatus())
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(ev.stamp_ns, 10**9)
    b = status_from_msg(msg)
    assert b.state is core.FtbState.FALLING and b.event is not None and b.fall_event.stamp_ns == ev.stamp_ns
    assert b.features.energy_ratio == feats.energy_ratio and np.array_equal(b.features.edge_normal, feats.edge_normal)
    # inf control duration (never falls, by the model) survives
    ev.control_duration = math.inf
    assert event_from_msg(event_to_msg(ev)).control_duration == math.inf


def _metrics_after_a_step_right_decision() -> FallMetrics:
    """Metrics with a target 1.2 m ahead, P at the origin, a fall event at 0.6 s and a step_right decision."""
    m = FallMetrics([1.2, 0.0])
    m.set_reference_cop([0.0, 0.0, 0.0])
    m.note_fall_event(0.6)
    m.note_decision({"stamp_ns": int(0.6e9), "case": "step_right", "swing_side": "r", "landing": [0.3, -0.1, 0.2],
                     "alpha2": math.radians(90.0), "captured": False, "touchdown_time": 0.45})
    return m


def test_metrics_alpha2_at_the_measured_p2_and_prediction():
    m = _metrics_after_a_step_right_decision()
    poses = {"l": (0.0, 0.1, 0.0, 0.0), "r": (0.0, -0.1, 0.0, 0.0)}
    t = 0.0
    for k in range(1000):
        t = 0.002 * k
        down = {"l": True, "r": not (0.61 <= t < 1.04)}
        poses["r"] = (0.31, -0.1, 0.21, 1.0) if t >= 1.04 else poses["r"]
        cop = [0.3, -0.3, 0.0] if t >= 1.04 else [0.14, 0.0, 0.0]
        m.update_feet(t, cop, down, poses)
        m.update_feet(t, [9.0, 9.0, 0.0], down, poses)   # a repeated tick is ignored
        fell = t > 1.5
        m.update(t, [0.3, -1.0, 0.3] if fell else [0.1, 0, 0.75], 1.2 if fell else 0.1, 0.8, 0.5, fell and t > 1.6)
    r = m.result()
    assert r["fall_event_time_s"] == 0.6 and r["lead_time_s"] == pytest.approx(r["landing_time_s"] - 0.6)
    assert r["measured_p2"] == pytest.approx([0.3, -0.3])
    # at P2 = (0.3, -0.3): landing CoM straight along -y is 90 deg... from P2 -> T = (0.9, 0.3)
    u, v = np.array([0.0, -0.7]), np.array([0.9, 0.3])
    assert r["avoidance_angle_p2_deg"] == pytest.approx(math.degrees(math.acos(u @ v / 0.7 / np.hypot(*v))))
    p = r["prediction"]
    assert p["touchdown_error_s"] == pytest.approx(1.04 - 1.05, abs=1e-9)
    assert p["landing_error_m"] == pytest.approx(0.01) and p["landing_yaw_error_deg"] == pytest.approx(0.573, abs=1e-3)
    assert r["predicted_avoidance_deg"] == pytest.approx(90.0) and r["captured"] is False


def test_metrics_a_step_that_ends_leaning_on_the_target_is_no_capture():
    """``captured``: the step was taken and the robot did not fall, without the target's help: the same run
    with the robot touching the target on the way (distance 0) is not a capture; 3 cm away it is."""
    out = {}
    for dist in (0.03, 0.0):
        m = _metrics_after_a_step_right_decision()
        poses = {"l": (0.0, 0.1, 0.0, 0.0), "r": (0.0, -0.1, 0.0, 0.0)}
        for k in range(1000):
            t = 0.002 * k
            down = {"l": True, "r": not (0.61 <= t < 1.04)}
            poses["r"] = (0.31, -0.1, 0.21, 1.0) if t >= 1.04 else poses["r"]
            m.update_feet(t, [0.14, 0.0, 0.0], down, poses)
            m.update(t, [0.1, 0.0, 0.75], 0.1, 0.8, 0.5 if t < 1.5 else dist, False)
        out[dist] = m.result()
    assert out[0.03]["captured"] is True and out[0.03]["min_target_distance_m"] == pytest.approx(0.03)
    assert out[0.0]["captured"] is False and not out[0.0]["fell"]


def test_metrics_with_lazy_poses_and_cop_equal_the_eager_ones_and_compute_them_rarely():
    """The bridge passes the feet's poses and the CoP as functions (foot_state(world, lazy=True)): the same
    result, and the functions are called on the touchdown tick and in the CoP window only."""
    eager, lazy = _metrics_after_a_step_right_decision(), _metrics_after_a_step_right_decision()
    calls = {"poses": 0, "cop": 0}
    for k in range(1000):
        t = 0.002 * k
        down = {"l": True, "r": not (0.61 <= t < 1.04)}
        poses = {"l": (0.0, 0.1, 0.0, 0.0), "r": (0.31, -0.1, 0.21, 1.0) if t >= 1.04 else (0.0, -0.1, 0.0, 0.0)}
        cop = [0.3, -0.3, 0.0] if t >= 1.04 else [0.14, 0.0, 0.0]

        def poses_fn(poses=poses):
            calls["poses"] += 1
            return poses

        def cop_fn(cop=cop):
            calls["cop"] += 1
            return cop

        eager.update_feet(t, cop, down, poses)
        lazy.update_feet(t, cop_fn, down, poses_fn)
        for m in (eager, lazy):
            m.update(t, [0.1, 0, 0.75], 0.1, 0.8, 0.5, False)
    assert lazy.result() == eager.result() and lazy.result()["measured_p2"] == pytest.approx([0.3, -0.3])
    assert calls["poses"] == 1  # the right foot's one touchdown (the left never lifts)
    window = lazy._touchdown_log["r"][-1][3]  # the CoPs of P2, 0.05-0.15 s after that touchdown
    assert len(window) > 40 and calls["cop"] == len(window)  # once a tick, in that window only


def test_metrics_take_the_step_after_the_fall_event_not_a_walking_step_before_it():
    # walking: the right foot steps at 0.2-0.6 s (a walk step, CoP there (0.15, 0)); the FTB fires at 1.0 s; the
    # protective step lands at 1.3 s with the CoP at (0.6, -0.2): P2 and the prediction are that step's,
    # whenever the event became known (the bridge learns it over the graph, after the ticks it stamps)
    def run(event_known_at: float) -> dict:
        m = FallMetrics([2.0, 0.0])
        m.set_reference_cop([0.0, 0.0, 0.0])
        for k in range(1000):
            t = 0.002 * k
            if t >= event_known_at:
                m.note_fall_event(1.0)
            down = {"l": True, "r": not (0.2 <= t < 0.6 or 1.05 <= t < 1.3)}
            cop = [0.6, -0.2, 0.0] if t >= 1.3 else [0.15, 0.0, 0.0]
            m.update_feet(t, cop, down, {"l": (0, 0.1, 0, 0), "r": (0.6 if t >= 1.3 else 0.1, -0.1, 0, 0)})
            fell = t > 1.6
            m.update(t, [1.0, -1.0, 0.3] if fell else [0.1, 0, 0.75], 1.2 if fell else 0.1, 0.8, 1.0, fell and t > 1.7)
        return m.result()

    early, late = run(1.0), run(1.5)
    assert early["measured_p2"] == pytest.approx([0.6, -0.2]) and early == late
    no_event = FallMetrics([2.0, 0.0])
    for k in range(500):
        t = 0.002 * k
        no_event.update_feet(t, [0.15, 0.0, 0.0], {"l": True, "r": not (0.2 <= t < 0.6)}, {"l": (0, 0.1, 0, 0),
                                                                                         "r": (0.1, -0.1, 0, 0)})
    assert no_event.touchdowns["r"][0] == pytest.approx(0.6)  # without an event: the first after a lift-off


def test_metrics_p2_of_a_step_that_bounces_is_taken_after_it_lands_again():
    """The step's sole lands, bounces off before P2's window (0.05-0.15 s after touchdown) and lands again
    within BOUNCE_S: P2 is the CoP after the second landing, the touchdown stays the first one (seen in the
    sweep at 30 deg: no alpha2 at all before)."""
    from humfall_ros.sim.metrics import BOUNCE_S

    m = _metrics_after_a_step_right_decision()
    poses = {"l": (0.0, 0.1, 0.0, 0.0), "r": (0.31, -0.1, 0.21, 1.0)}
    second = 1.04 + BOUNCE_S / 2
    for k in range(1000):
        t = 0.002 * k
        down = {"l": True, "r": not (0.61 <= t < 1.04 or 1.07 <= t < second)}
        cop = [0.3, -0.3, 0.0] if t >= second else [0.14, 0.0, 0.0]
        m.update_feet(t, cop, down, poses)
        fell = t > 1.6
        m.update(t, [0.3, -1.0, 0.3] if fell else [0.1, 0, 0.75], 1.2 if fell else 0.1, 0.8, 0.5, fell and t > 1.7)
    r = m.result()
    assert r["measured_p2"] == pytest.approx([0.3, -0.3]) and r["avoidance_angle_p2_deg"] is not None
    assert r["prediction"]["touchdown_time_s"] == pytest.approx(1.04)
