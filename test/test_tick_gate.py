"""The shared tick gate: compute once per complete tick, retransmit repeats, reset when time goes back."""
import pytest

from humfall_ros.control.tick_gate import Action, TickGate


def test_waits_for_every_input_of_a_stamp():
    g = TickGate({"state", "mux"}, trigger="state")
    assert g.offer("state", 10, "s10") is Action.WAIT
    assert g.poll() is None
    assert g.offer("mux", 12, "m12") is Action.WAIT  # another stamp: does not complete tick 10
    assert g.poll() is None
    g.offer("mux", 10, "m10")
    t = g.poll()
    assert t.stamp_ns == 10 and t.inputs == {"state": "s10", "mux": "m10"}
    assert g.poll() is None  # computed once


def test_repeated_trigger_is_a_retransmission_other_repeats_are_ignored():
    g = TickGate({"state", "mux"}, trigger="state")
    g.offer("state", 10, 1)
    g.offer("mux", 10, 1)
    g.poll()
    assert g.offer("state", 10, 1) is Action.RETRANSMIT
    assert g.offer("mux", 10, 1) is Action.WAIT
    assert g.poll() is None


def test_time_going_back_resets_and_keeps_the_new_input():
    g = TickGate({"state"})
    g.offer("state", 10, "a")
    g.poll()
    assert g.offer("state", 0, "b") is Action.RESET
    assert g.resets == 1
    t = g.poll()
    assert t.stamp_ns == 0 and t.inputs["state"] == "b"


def test_newest_complete_tick_wins_and_older_ones_are_dropped():
    g = TickGate({"state", "mux"})
    for k in (10, 12, 14):
        g.offer("state", k, k)
        g.offer("mux", k, k)
    g.offer("state", 16, 16)  # incomplete: stays pending
    t = g.poll()
    assert t.stamp_ns == 14 and g.dropped == 2
    g.offer("mux", 16, 16)
    assert g.poll().stamp_ns == 16


def test_bad_kinds_and_config_are_refused():
    with pytest.raises(ValueError):
        TickGate(set())
    with pytest.raises(ValueError):
        TickGate({"a"}, trigger="b")
    with pytest.raises(KeyError):
        TickGate({"a"}).offer("b", 0, None)


def test_gathering_says_when_a_trigger_waits_for_the_rest_of_its_tick():
    """What the hot loop asks before sleeping on the trigger topic alone (trigger-first waiting)."""
    g = TickGate({"centroidal_state", "joint_states", "mux"}, trigger="centroidal_state")
    assert not g.gathering()
    g.offer("joint_states", 10, 0)  # the tick's early inputs: keep sleeping on the trigger
    g.offer("mux", 10, 0)
    assert not g.gathering()
    g.offer("centroidal_state", 10, 0)
    assert not g.gathering()  # complete: poll takes it
    assert g.poll().stamp_ns == 10
    g.offer("centroidal_state", 12, 0)  # a trigger before its tick's joint_states (topics are not ordered)
    assert g.gathering() and not g.gathering("mux")
    g.offer("joint_states", 12, 0)
    assert g.gathering()
    g.offer("mux", 12, 0)
    assert not g.gathering() and g.poll().stamp_ns == 12
