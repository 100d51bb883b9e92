"""A predicted capture given up at the touchdown (``capture_abandon``, ours, the default since session 42).

``standing_push`` at 1.4x: the decision (on the fall event's tick, the push still on) predicts a capture, but the
step lands with the measured capture point ~2.6 cm outside both soles' hull, beyond any balance. Given up, inertia
shaping starts at the touchdown, as after a predicted fall, instead of the capture balance: alpha2 124 deg against
108 deg with the balance, 100 deg stepping alone (docs/safe_fall.md "Session 42"). At 1.0x the capture point is
inside at the touchdown: the balance starts and the robot is captured as before.

Since session 43 a capture is also given up when the capture point is inside by less than
``capture_abandon_margin_m`` (0.02 m: the ankle balance needs 2-3.5 cm, session 39). At 1.42x the step lands with it
0.8 cm inside: the balance failed there and the robot fell onto the target; given up, it falls clear of it. At 1.3x
it lands 3.1 cm inside and is captured by the balance, as before.
"""
import pytest

from humfall_ros import scenario
from humfall_ros.sim import fall_runs as runs


def _push(scale: float, *overrides: str):
    """The scenario's push scaled (as ``benchmarks/fall_closed_loop.py push SCALE``)."""
    f = [round(x * scale, 4) for x in scenario.load("standing_push")["push"][0]["force"]]
    return runs.run(scenario.load("standing_push", [f"push.0.force={f}", *overrides]), "stepping_inertia")


@pytest.fixture(scope="module")
def given_up():
    return _push(1.4)


@pytest.fixture(scope="module")
def balanced():
    return _push(1.4, "params.safe_fall_controller.capture_abandon=false")


def test_a_capture_point_outside_the_soles_at_the_touchdown_gives_the_capture_up(given_up, balanced):
    m = given_up.metrics
    assert m["predicted_captured"] and not m["captured"] and m["fell"]
    notes = [r for r in given_up.reasons if "given up" in r]
    assert len(notes) == 1 and "inside the soles" in notes[0]
    # the touchdown's margin, as the note gives it, is negative: the capture point is outside
    assert float(notes[0].split("capture point ")[1].split(" m")[0]) < 0.0
    assert not any("given up" in r for r in balanced.reasons)
    # the same decision and step; after the touchdown shaping instead of the balance turns the fall further away
    assert m["decision_case"] == balanced.metrics["decision_case"]
    assert m["min_target_distance_m"] >= 0.05
    assert m["avoidance_angle_p2_deg"] > balanced.metrics["avoidance_angle_p2_deg"] + 5.0


def test_a_capture_point_inside_keeps_the_balance_and_the_robot_is_captured():
    r = _push(1.0)
    assert r.metrics["captured"] and not r.metrics["fell"]
    assert not any("given up" in x for x in r.reasons)


def test_a_capture_point_barely_inside_is_given_up_too_and_the_target_stays_clear():
    r = _push(1.42)
    m = r.metrics
    notes = [x for x in r.reasons if "given up" in x]
    assert m["predicted_captured"] and m["fell"] and len(notes) == 1
    assert 0.0 < float(notes[0].split("capture point ")[1].split(" m")[0]) < 0.02   # inside, but shallow
    assert m["min_target_distance_m"] >= 0.05
    balanced = _push(1.42, "params.safe_fall_controller.capture_abandon_margin_m=0.0")   # session 42's rule
    assert not any("given up" in x for x in balanced.reasons)
    assert balanced.metrics["min_target_distance_m"] < 0.05 < m["min_target_distance_m"]
    assert m["avoidance_angle_p2_deg"] > balanced.metrics["avoidance_angle_p2_deg"] + 45.0


def test_a_capture_point_deep_enough_keeps_the_balance_at_1_3x():
    r = _push(1.3)
    assert r.metrics["captured"] and not r.metrics["fell"]
    assert not any("given up" in x for x in r.reasons)
