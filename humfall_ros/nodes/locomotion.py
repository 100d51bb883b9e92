"""locomotion: the balance and walking controller's node (standing now; walking lands with its issue).

A lockstep command source (``joint_command/locomotion``) under the controller
contract: see humfall_ros/nodes/controller_node.py for the tick handling and
humfall_ros/control/standing.py for the controller.
"""
from __future__ import annotations

from humfall_ros.control.standing import StandingController
from humfall_ros.nodes.common import run_node
from humfall_ros.nodes.controller_node import ControllerNode


def make_controller(p: dict, model) -> StandingController:
    return StandingController(model, model.standing_posture, p["ankle_kp"], p["ankle_kd"], p["ankle_max_offset"],
                              p["resume_time"])


class Locomotion(ControllerNode):
    def __init__(self):
        super().__init__("locomotion", make_controller)


def main(args=None) -> int:
    return run_node(Locomotion, args)


if __name__ == "__main__":
    raise SystemExit(main())
