"""estop_planner: the emergency stop's node (paper 3; issue 12). A lockstep command source ``joint_command/estop``.

The controller is :class:`humfall_ros.estop.controller.EstopController` (all the logic; this file only converts
messages), run by :class:`humfall_ros.nodes.controller_node.ControllerNode` like every controller of the suite.

Inputs:

* ``estop`` (``std_msgs/msg/Empty``, reliable, transient-local): every message is a trigger
  (:class:`TopicEvent` with a new count; ``humfall estop`` publishes it, as
  ``ros2 topic pub --once --qos-durability transient_local /estop std_msgs/msg/Empty`` would);
* ``estop/release`` (``std_msgs/msg/Empty``, reliable, transient-local): a release, granted once the robot
  holds still at its final posture (refused and logged otherwise);
* ``fall_event`` (``humfall_interfaces/FallEvent``, latched): "falling", the e-stop yields; a ``cleared`` one
  (the FTB's recovery) means no fall event, as in the in-process loop (:func:`fall_event_input`);
* ``walking/state`` (``humfall_interfaces/WalkingState``, per tick, stamped like the tick) when that message
  type exists and the parameter ``walking_state_input`` is true (the default: the locomotion node must then
  publish it every tick, or the lockstep run stalls on this node): the pattern state the stop is planned from
  and the gait phase of a scheduled trigger. Without it the node stops a standing robot.

A scheduled trigger (parameters ``trigger_time`` or ``trigger_step`` + ``trigger_phase``; the launcher
passes the scenario's ``estop.time`` / ``estop.at``) acts on exactly that tick, so lockstep runs repeat.

Output: ``estop/status`` (``humfall_interfaces/EstopStatus``) every tick, stamped like the tick; log lines of
the controller (transitions, refusals, bad input) go to the node's log.
"""
from __future__ import annotations

import itertools
import math

import numpy as np
from geometry_msgs.msg import Point, Vector3
from humfall_interfaces.msg import EstopStatus as EstopStatusMsg
from std_msgs.msg import Empty

from humfall_ros.control.contract import JointTargets, Observation
from humfall_ros.estop.config import EstopConfig
from humfall_ros.estop.controller import EstopController, EstopStatus, TopicEvent
from humfall_ros.nodes.common import NO_PUB_EVENTS, QOS_LATCHED, QOS_TICK_WRITER, run_node
from humfall_ros.nodes.controller_node import FALL_EVENT, IMU, ControllerNode, Input

try:  # the walking engineer's message; until it exists the node stops a standing robot
    from humfall_interfaces.msg import WalkingState as WalkingStateMsg
except ImportError:  # pragma: no cover - depends on the interface build
    WalkingStateMsg = None


def make_controller(p: dict, model) -> EstopController:
    return EstopController(model, EstopConfig.from_params(p))


def event_converter():
    """A message -> :class:`TopicEvent` converter numbering the messages 1, 2, ..."""
    counter = itertools.count(1)
    return lambda _msg: TopicEvent(next(counter))


def _xyz(v) -> np.ndarray:
    if hasattr(v, "x") and hasattr(v, "z"):
        return np.array([v.x, v.y, v.z], float)
    return np.asarray(v, float).reshape(3)


def _sole(v) -> tuple:
    """A sole pose (x, y, z, yaw) from a humfall_interfaces Footstep (position + yaw), a geometry_msgs Pose
    or Pose2D, or a float array."""
    if hasattr(v, "position") and hasattr(v, "yaw"):
        return (v.position.x, v.position.y, v.position.z, float(v.yaw))
    if hasattr(v, "position") and hasattr(v, "orientation"):
        q = v.orientation
        yaw = math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z))
        return (v.position.x, v.position.y, v.position.z, yaw)
    if hasattr(v, "theta"):
        return (v.x, v.y, 0.0, v.theta)
    a = [float(x) for x in v]
    return tuple(a) if len(a) == 4 else (a[0], a[1], 0.0, a[2])


def _support(msg) -> str:
    """The support phase name ("double", "single_left", "single_right") from a string or an enumerated field."""
    v = msg.support
    if isinstance(v, str):
        return v
    for name in ("DOUBLE", "SINGLE_LEFT", "SINGLE_RIGHT"):
        if getattr(type(msg), name, None) == v:
            return name.lower()
    raise ValueError(f"walking/state: unknown support {v!r}")


def walking_state_from_msg(msg):
    """``humfall_interfaces/WalkingState`` -> ``humfall_ros.walking.controller.WalkingState`` (the fields the
    e-stop reads: walking, support, phase_fraction, step_index, com_ref, com_velocity_ref, zmp_ref,
    left_foot, right_foot)."""
    from humfall_ros.walking.controller import WalkingState

    return WalkingState(
        stamp_ns=msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec, walking=bool(msg.walking),
        released=bool(getattr(msg, "released", False)), support=_support(msg),
        phase_fraction=float(msg.phase_fraction), step_index=int(msg.step_index), com_ref=_xyz(msg.com_ref),
        com_velocity_ref=_xyz(msg.com_velocity_ref), zmp_ref=_xyz(msg.zmp_ref), left_foot=_sole(msg.left_foot),
        right_foot=_sole(msg.right_foot))


def status_to_msg(s: EstopStatus) -> EstopStatusMsg:
    """The :class:`EstopStatus` dataclass as the message (stamp set by the caller)."""
    m = EstopStatusMsg()
    for name in ("state", "active", "phase_at_trigger", "step_at_trigger", "phase_fraction_at_trigger",
                 "trigger_time", "start_time", "omega_c", "alpha", "beta", "omega_f", "max_zmp_minor",
                 "max_zmp_major", "max_lipm_zmp_minor", "max_lipm_zmp_major", "n3_lower_bound", "min_zmp_margin",
                 "predicted_stop_time", "crouch", "crouch_height", "feasible", "fallback", "reason",
                 "feet_yaw_off_pattern", "align_start_time", "align_end_time", "align_swing", "align_offset"):
        v = getattr(s, name)
        setattr(m, name, type(getattr(m, name))(v))
    for name in ("gains_minor", "gains_major", "poles_minor_re", "poles_minor_im", "n_major", "n_minor_re",
                 "n_minor_im"):
        setattr(m, name, np.asarray(getattr(s, name), float))
    m.final_com = Point(x=float(s.final_com[0]), y=float(s.final_com[1]), z=float(s.final_com[2]))
    m.frame_origin = Point(x=float(s.frame_origin[0]), y=float(s.frame_origin[1]), z=0.0)
    m.major_axis = Vector3(x=float(s.major_axis[0]), y=float(s.major_axis[1]), z=0.0)
    m.feet_frame_origin = Point(x=float(s.feet_frame_origin[0]), y=float(s.feet_frame_origin[1]), z=0.0)
    m.feet_major_axis = Vector3(x=float(s.feet_major_axis[0]), y=float(s.feet_major_axis[1]), z=0.0)
    m.feet_support_polygon = [Point(x=float(p[0]), y=float(p[1]), z=0.0) for p in s.feet_support_polygon]
    m.com_ref = Point(x=float(s.com_ref[0]), y=float(s.com_ref[1]), z=float(s.com_ref[2]))
    m.com_velocity_ref = Vector3(x=float(s.com_velocity_ref[0]), y=float(s.com_velocity_ref[1]),
                                 z=float(s.com_velocity_ref[2]))
    m.zmp_ref = Point(x=float(s.zmp_ref[0]), y=float(s.zmp_ref[1]), z=float(s.zmp_ref[2]))
    return m


def node_inputs() -> list[Input]:
    """The node's inputs: the events, and the IMU per tick (the stop's ankle strategy turns the measured CoG by the
    robot's yaw off its kinematic model, as every in-process observation allows); walking/state is added per tick
    by :class:`EstopPlannerNode` when asked."""
    return [Input("estop", Empty, "estop", event_converter(), qos=QOS_LATCHED),
            Input("estop_release", Empty, "estop/release", event_converter(), qos=QOS_LATCHED),
            FALL_EVENT, IMU]


WALKING_STATE = Input("walking/state", WalkingStateMsg, "walking/state", walking_state_from_msg, per_tick=True) \
    if WalkingStateMsg is not None else None


class EstopPlannerNode(ControllerNode):
    def __init__(self):
        inputs = node_inputs()

        def make(p: dict, model) -> EstopController:
            # the declared parameters are known only here: walking/state joins the inputs before the node reads them
            if p["walking_state_input"] and WALKING_STATE is not None:
                inputs.append(WALKING_STATE)
            return make_controller(p, model)

        super().__init__("estop_planner", make, inputs)
        self.status_pub = self.create_publisher(EstopStatusMsg, "estop/status", QOS_TICK_WRITER,
                                                event_callbacks=NO_PUB_EVENTS)
        self._logged = 0
        per_tick = any(i.name == "walking/state" for i in self.extra)
        self.get_logger().info("walking/state: " + ("per tick" if per_tick else "not read (standing robots only)"))

    def after_step(self, observation: Observation, targets: JointTargets | None) -> None:
        c: EstopController = self.controller
        for line in c.messages[self._logged:]:
            self.get_logger().info(line)
        self._logged = len(c.messages)
        msg = status_to_msg(c.status)
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(observation.stamp_ns), 1_000_000_000)
        self.publish_tick(self.status_pub, msg)


def main(args=None) -> int:
    return run_node(EstopPlannerNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
