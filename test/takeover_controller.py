"""A test-only controller: takes over at a given time, moves the arms, releases later.

Used by the controller-contract tests (hand-over, bumpless transfer, in-process vs
ROS identity) and as an idle stand-in per-tick controller in the headroom benchmark
(``take_over_time`` < 0: never takes over, answers every tick with a release).

Run as a node: ``python test/takeover_controller.py --ros-args -p source:=test ...``
(a scenario names it as ``controllers: [{node: test/takeover_controller.py, source: test,
priority: 50, params: {...}}]``).
"""
from __future__ import annotations

import numpy as np

from humfall_ros.control.contract import JointTargets, Observation
from humfall_ros.params import Declaration

DECLARATIONS = {d.name: d for d in (
    Declaration("source", "string", "test", "mux source name (joint_command/<source>)"),
    Declaration("take_over_time", "double", 1.0, "sim time to take over (s); < 0: never", (-1.0, 3600.0)),
    Declaration("release_time", "double", 2.0, "sim time to release (s)", (0.0, 3600.0)),
    Declaration("arm_offset", "double", 0.4, "shoulder pitch offset reached while in control (rad)", (-1.5, 1.5)),
    Declaration("ramp_time", "double", 0.3, "time to reach the offset (s)", (0.01, 10.0)),
    Declaration("mute_time", "double", -1.0, "node only: from this sim time on, publish no answer at all "
                "(a hung source, for the stall test) (s); < 0: never", (-1.0, 3600.0)),
)}


class TakeoverController:
    """Releases until ``take_over_time``; then holds the measured posture of that tick and raises
    the arms by ``arm_offset`` over ``ramp_time``; releases from ``release_time`` on."""

    def __init__(self, model, source: str = "test", take_over_time: float = 1.0, release_time: float = 2.0,
                 arm_offset: float = 0.4, ramp_time: float = 0.3):
        self.source = source
        self.take_over_time, self.release_time = take_over_time, release_time
        self.arm_offset, self.ramp_time = arm_offset, ramp_time
        self.arms = [model.joint_index(f"{s}_shoulder_pitch") for s in ("l", "r")]
        self.reset()

    def reset(self) -> None:
        self.start: np.ndarray | None = None
        self.start_time = 0.0

    def step(self, obs: Observation) -> JointTargets | None:
        t = obs.time
        if self.take_over_time < 0 or t < self.take_over_time - 1e-9 or t >= self.release_time - 1e-9:
            self.start = None
            return None
        if self.start is None:  # bumpless: start from where the joints are
            self.start = np.asarray(obs.joint_position, float).copy()
            self.start_time = t
        q = self.start.copy()
        q[self.arms] += self.arm_offset * min(1.0, (t - self.start_time) / self.ramp_time)
        return JointTargets(q)


def make_controller(p: dict, model) -> TakeoverController:
    return TakeoverController(model, p["source"], p["take_over_time"], p["release_time"], p["arm_offset"],
                              p["ramp_time"])


def make_node(name: str):
    from sensor_msgs.msg import JointState

    from humfall_ros.nodes.common import stamp_key
    from humfall_ros.nodes.controller_node import ControllerNode
    from humfall_ros.recording import cdr

    node = ControllerNode(name, make_controller, declarations=DECLARATIONS)
    mute_ns = int(round(node.params["mute_time"] * 1e9))
    if mute_ns >= 0:  # a hung source: the answers of every tick from mute_time on are never sent
        publish, decode = node.pub.publish, cdr.decoder(JointState)  # the node publishes commands encoded

        def muted(data: bytes) -> None:
            if stamp_key(decode(data).header.stamp) < mute_ns:
                publish(data)

        node.pub.publish = muted
    return node


def main(args=None) -> int:
    import sys

    from humfall_ros.nodes.common import run_node

    # the node name follows the source, so several stand-ins can run side by side
    argv = sys.argv if args is None else args
    source = next((a.split(":=", 1)[1] for a in argv if a.startswith("source:=")), "test")
    return run_node(lambda: make_node(f"takeover_{source}"), args)


if __name__ == "__main__":
    raise SystemExit(main())
