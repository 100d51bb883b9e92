"""Joint command arbitration (twist_mux-like, with take-over) and command validation."""
import numpy as np
import pytest

from humfall_ros.control.mux import CommandMux, JointCommand, validate_command

JOINTS = ["a", "b", "c"]


@pytest.fixture
def mux():
    return CommandMux(["safe_fall", "estop", "locomotion"], JOINTS, timeout=0.05)


def test_highest_priority_engaged_source_wins(mux):
    assert mux.active(0.0) is None
    assert mux.update("locomotion", JointCommand(1.0, JOINTS, [1, 1, 1]), now=1.0) is None
    assert mux.active(1.0) == "locomotion"
    mux.update("estop", JointCommand(1.0, ["b"], [2]), now=1.0)
    d, q, v = mux.targets(1.0, np.zeros(3), np.zeros(3))
    assert d.source == "estop" and q.tolist() == [0, 2, 0]  # a subset: the others keep their targets
    mux.update("safe_fall", JointCommand(1.0, JOINTS, [3, 3, 3], [0.1, 0.2, 0.3]), now=1.0)
    d, q, v = mux.targets(1.0, np.zeros(3), np.zeros(3))
    assert d.source == "safe_fall" and q.tolist() == [3, 3, 3] and v.tolist() == [0.1, 0.2, 0.3]


def test_only_a_release_hands_control_back(mux):
    mux.update("locomotion", JointCommand(1.0, JOINTS, [1, 1, 1]), now=1.0)
    mux.update("estop", JointCommand(1.0, JOINTS, [2, 2, 2]), now=1.0)
    assert mux.active(1.0) == "estop"
    # the e-stop goes silent: 0.06 s > timeout, but it took over, so the robot holds its targets
    mux.update("locomotion", JointCommand(1.06, JOINTS, [1, 1, 1]), now=1.06)
    d, q, _ = mux.targets(1.06, np.full(3, 7.0), np.zeros(3))
    assert d.source == "estop" and d.holding and q.tolist() == [7, 7, 7]
    assert mux.active(1.06) is None
    mux.update("estop", JointCommand(1.06, [], []), now=1.06)  # explicit release
    assert mux.active(1.06) == "locomotion"
    assert not mux.engaged["estop"]


def test_future_stamps_and_conflicting_answers_are_refused(mux):
    why = mux.update("locomotion", JointCommand(2.0, JOINTS, [1, 1, 1]), now=1.0)
    assert "has not happened" in why and mux.active(1.0) is None
    assert mux.update("locomotion", JointCommand(1.0, JOINTS, [1, 1, 1]), now=1.0) is None
    assert mux.update("locomotion", JointCommand(1.0, JOINTS, [1, 1, 1]), now=1.0) is None  # duplicate: fine
    why = mux.update("locomotion", JointCommand(1.0, JOINTS, [9, 9, 9]), now=1.0)
    assert "different answer" in why
    _, q, _ = mux.targets(1.0, np.zeros(3), np.zeros(3))
    assert q.tolist() == [1, 1, 1]  # the first answer stands
    assert "older" in mux.update("locomotion", JointCommand(0.5, JOINTS, [0, 0, 0]), now=1.0)
    assert "unknown source" in mux.update("nobody", JointCommand(1.0, JOINTS, [0, 0, 0]), now=1.0)


@pytest.mark.parametrize("names, pos, vel, why", [
    (["a", "x"], [0, 0], [], "unknown joints"),
    (["a"], [0, 1], [], "1 names but 2 positions"),
    (["a", "b"], [0, 1], [1], "2 names but 1 velocities"),
    (["a", "a"], [0, 1], [], "duplicate"),
    (["a"], [float("nan")], [], "non-finite"),
    (["a"], [0.0], [float("inf")], "non-finite"),
])
def test_bad_commands_are_refused(names, pos, vel, why):
    assert why in validate_command(names, pos, vel, {n: i for i, n in enumerate(JOINTS)})


def test_good_command_passes():
    assert validate_command(["c", "a"], [0.1, 0.2], [], set(JOINTS)) is None
    with pytest.raises(ValueError):
        CommandMux(["a", "a"], JOINTS, 0.05)


def test_clear_forgets_engagement(mux):
    mux.update("safe_fall", JointCommand(0.5, JOINTS, [1, 1, 1]), now=0.5)
    assert mux.active(0.5) == "safe_fall"
    mux.clear()
    assert mux.active(0.5) is None and not any(mux.engaged.values())
