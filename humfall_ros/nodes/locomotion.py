"""locomotion: the balance and walking controller's node (issue 10), lockstep source ``joint_command/locomotion``.

The controller is :class:`humfall_ros.walking.controller.LocomotionController` (it stands, walks,
releases on a fall event or an e-stop; all the logic); this file only converts messages, run by
:class:`humfall_ros.nodes.controller_node.ControllerNode` like every controller of the suite.

Parameters: config/locomotion.yaml. ``scenario`` (a scenario name or file, default empty): the
node follows that scenario's ``walk:`` section (its walk schedule, ``walk.step_period`` and
``walk.double_support``) and control rate, exactly as an in-process user of
``walking.controller.from_scenario(sc, model)`` does.

Inputs besides the tick's:

* ``cmd_walk`` (``geometry_msgs/Twist``, reliable, latest value kept): ``linear.x`` forward speed
  [m/s], ``angular.z`` yaw rate [rad/s]; starts a walk, changes its speed or turn, zero ends it with
  a planned stop. A non-finite command is refused and logged; clamps and refusals of the
  controller (speed, turn rate, kinematics, while released) are logged too;
* ``fall_event`` (``humfall_interfaces/FallEvent``, latched): release; a ``cleared`` one (the FTB
  recovered) ends the release: standing resumes where the feet are once the safe-fall controller lets go;
* the e-stop is not an input: walking gives way when ``mux/state`` shows another source drives;

Output besides the command: ``walking/state`` (``humfall_interfaces/WalkingState``) every tick,
stamped like the tick.
"""
from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
from geometry_msgs.msg import Twist
from humfall_interfaces.msg import Footstep as FootstepMsg
from humfall_interfaces.msg import WalkingState as WalkingStateMsg

from humfall_ros import params as params_mod
from humfall_ros.control.contract import JointTargets, Observation
from humfall_ros.nodes.common import NO_PUB_EVENTS, QOS_RELIABLE, QOS_TICK_WRITER, run_node, xyz
from humfall_ros.nodes.controller_node import FALL_EVENT, IMU, ControllerNode, Input
from humfall_ros.walking.controller import LocomotionController, WalkingState, from_scenario
from humfall_ros.walking.footsteps import WalkCommand
from humfall_ros.walking.scenario import walking_config


def make_controller(p: dict, model) -> LocomotionController:
    """The node's controller: ``from_scenario`` of the ``scenario`` parameter's file, else the declared
    parameters at the bridge's default control rate, standing until a ``cmd_walk``."""
    if p.get("scenario"):
        from humfall_ros import scenario as scenario_mod

        return from_scenario(scenario_mod.load(p["scenario"]), model, p)
    rate = float(params_mod.defaults("sim_bridge")["control_rate"])
    cfg = walking_config({"walk": {"step_period": p["step_period"], "double_support": p["double_support"]}}, p)
    return LocomotionController(model, cfg, 1.0 / rate)


def walk_command_from_twist(msg: Twist) -> WalkCommand:
    """``cmd_walk`` -> :class:`WalkCommand`; ValueError (logged by the node) when not finite."""
    v, w = float(msg.linear.x), float(msg.angular.z)
    if not (math.isfinite(v) and math.isfinite(w)):
        raise ValueError(f"non-finite walk command (linear.x {v!r}, angular.z {w!r})")
    ignored = [n for n, x in (("linear.y", msg.linear.y), ("linear.z", msg.linear.z),
                              ("angular.x", msg.angular.x), ("angular.y", msg.angular.y)) if x != 0.0]
    if ignored:
        raise ValueError(f"only linear.x and angular.z are walkable; {', '.join(ignored)} given")
    return WalkCommand(v, w)


def _pose(foot) -> SimpleNamespace:
    x, y, z, yaw = foot
    return SimpleNamespace(position=xyz((x, y, z)),
                           orientation=SimpleNamespace(x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2)))


def walking_state_to_msg(s: WalkingState) -> SimpleNamespace:
    """The controller's :class:`WalkingState` as a WalkingState message's fields (a namespace for
    ``publish_encoded``; building the rosidl message with its ten nested points and poses was ~0.1 ms a
    tick while walking). The stamp is set by the caller."""
    steps = []
    for side, x, y, yaw, *rest in s.next_footsteps:
        index, stop = (int(rest[0]), bool(rest[1])) if rest else (0, False)
        steps.append(SimpleNamespace(side=FootstepMsg.LEFT if side == "l" else FootstepMsg.RIGHT,
                                     position=xyz((x, y)), yaw=float(yaw),
                                     index=index, stop=stop))
    return SimpleNamespace(
        header=SimpleNamespace(stamp=SimpleNamespace(sec=0, nanosec=0), frame_id=""),
        walking=bool(s.walking), released=bool(s.released), support=str(s.support),
        phase_fraction=float(s.phase_fraction), step_index=int(s.step_index),
        com_ref=xyz(s.com_ref), com_velocity_ref=xyz(s.com_velocity_ref),
        zmp_ref=xyz(s.zmp_ref), capture_point_ref=xyz(s.capture_point_ref),
        multibody_zmp=xyz(np.asarray(s.multibody_zmp, float)),
        left_foot=_pose(s.left_foot), right_foot=_pose(s.right_foot),
        next_footsteps=steps, speed=float(s.speed), yaw_rate=float(s.yaw_rate))


def node_inputs() -> list[Input]:
    # the IMU per tick, as every in-process observation has it (heading steering); no estop/status: its
    # arrival is not tied to the tick, and walking gives way to the e-stop through mux/state already
    return [Input("cmd_walk", Twist, "cmd_walk", walk_command_from_twist, qos=QOS_RELIABLE),
            FALL_EVENT, IMU]


class Locomotion(ControllerNode):
    def __init__(self):
        super().__init__("locomotion", make_controller, node_inputs())
        self.state_pub = self.create_publisher(WalkingStateMsg, "walking/state", QOS_TICK_WRITER,
                                               event_callbacks=NO_PUB_EVENTS)
        self._logged = 0
        self._idle_msgs: dict[bool, WalkingStateMsg] = {}

    def after_step(self, observation: Observation, targets: JointTargets | None) -> None:
        state = self.controller.state
        if state.walking:
            msg = walking_state_to_msg(state)
        else:
            # standing or released: the state is WalkingState's defaults but for `released` (tested), so its
            # message is built once; building it each tick was a quarter of the node's CPU while standing
            msg = self._idle_msgs.get(state.released)
            if msg is None:
                msg = self._idle_msgs[state.released] = walking_state_to_msg(state)
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(observation.stamp_ns), 1_000_000_000)
        self.publish_tick(self.state_pub, msg)
        log = self.controller.messages
        for line in log[self._logged:]:
            (self.get_logger().warning if ("refused" in line or "clamped" in line or "ignored" in line)
             else self.get_logger().info)(line)
        self._logged = len(log)


def main(args=None) -> int:
    return run_node(Locomotion, args)


if __name__ == "__main__":
    raise SystemExit(main())
