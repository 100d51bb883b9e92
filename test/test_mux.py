"""Joint command arbitration (twist_mux-like) and command validation."""
import numpy as np
import pytest

from humfall_ros.control.mux import CommandMux, JointCommand, validate_command

JOINTS = ["a", "b", "c"]


@pytest.fixture
def mux():
    return CommandMux(["safe_fall", "estop", "locomotion"], JOINTS, timeout=0.05)


def test_highest_priority_live_source_wins(mux):
    assert mux.active(0.0) is None
    mux.update("locomotion", JointCommand(1.0, JOINTS, [1, 1, 1]))
    assert mux.active(1.0) == "locomotion"
    mux.update("estop", JointCommand(1.0, ["b"], [2]))
    src, q, v = mux.targets(1.0, np.zeros(3), np.zeros(3))
    assert src == "estop" and q.tolist() == [0, 2, 0]  # a subset: the others keep their targets
    mux.update("safe_fall", JointCommand(1.0, JOINTS, [3, 3, 3], [0.1, 0.2, 0.3]))
    src, q, v = mux.targets(1.0, np.zeros(3), np.zeros(3))
    assert src == "safe_fall" and q.tolist() == [3, 3, 3] and v.tolist() == [0.1, 0.2, 0.3]


def test_release_and_timeout_hand_control_back(mux):
    mux.update("locomotion", JointCommand(1.0, JOINTS, [1, 1, 1]))
    mux.update("estop", JointCommand(1.0, JOINTS, [2, 2, 2]))
    assert mux.active(1.0) == "estop"
    mux.update("estop", JointCommand(1.002, [], []))  # release
    assert mux.active(1.002) == "locomotion"
    # a stale command is not live: 0.06 s > timeout
    assert mux.active(1.06) is None


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


def test_commands_from_the_future_are_not_live_and_clear_forgets(mux):
    mux.update("safe_fall", JointCommand(1e9, JOINTS, [1, 1, 1]))  # a stamp from before a reset
    mux.update("locomotion", JointCommand(0.5, JOINTS, [0, 0, 0]))
    assert mux.active(0.5) == "locomotion"
    mux.clear()
    assert mux.active(0.5) is None
