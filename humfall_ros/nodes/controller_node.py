"""A contract controller (humfall_ros.control.contract) as a lockstep command source on the graph.

Every controller node of the suite is one of these: it gathers the tick's
``centroidal_state``, ``joint_states`` and ``mux/state`` (plus any further
per-tick inputs, e.g. ``ftb/status``) in the shared tick gate, builds the same
:class:`Observation` the in-process loop builds, calls ``controller.step`` and
publishes ``joint_command/<source>`` stamped like the tick (an empty JointState
is a release). A retransmitted tick is answered with the last command; time going
back resets the controller. A controller that raises never kills the node: a
source that had taken over repeats its last targets (never leaves the robot
without a command), one that had not releases.
"""
from __future__ import annotations

import dataclasses
from types import SimpleNamespace
from typing import Any, Callable

import numpy as np
from humfall_interfaces.msg import CentroidalState, FallEvent, MuxState, ObstacleArray
from rclpy.node import Node
from sensor_msgs.msg import Imu, JointState

from humfall_ros.control.contract import CentroidalObservation, Controller, JointTargets, Observation, Obstacle
from humfall_ros.control.tick_gate import Action, TickGate
from humfall_ros.model.humanoid import HumanoidModel, load_model
from humfall_ros.nodes.common import (
    NO_PUB_EVENTS,
    QOS_LATCHED,
    QOS_TICK_WRITER,
    FirstAnswerHold,
    HotLoop,
    Params,
    encode,
    ros_stamp,
    stamp_key,
)


@dataclasses.dataclass
class Input:
    """A further input of a controller node.

    Attributes:
        name: key in ``observation.inputs``.
        msg_type, topic: what to subscribe to.
        convert: message -> the functional core's value.
        per_tick: the tick waits for it (its messages are stamped like the tick);
            otherwise the latest value is kept (latched events, commands).
        qos: subscription QoS (default: reliable per-tick, transient-local otherwise).
    """

    name: str
    msg_type: type
    topic: str
    convert: Callable[[Any], Any]
    per_tick: bool = False
    qos: Any = None


def centroidal_from_msg(msg: CentroidalState) -> CentroidalObservation:
    """The message's numbers, exactly (float64 all the way: the same as in process)."""
    def v(p):
        return np.array([p.x, p.y, p.z])

    poly = np.array([[p.x, p.y] for p in msg.support_polygon], dtype=float).reshape(-1, 2)
    return CentroidalObservation(
        com=v(msg.com), com_velocity=v(msg.com_velocity), cop=v(msg.cop), capture_point=v(msg.capture_point),
        angular_momentum=v(msg.angular_momentum), support_polygon=poly, feet_center=v(msg.feet_center),
        lean_angle=msg.lean_angle, lean_direction=msg.lean_direction, normal_force=msg.normal_force,
        left_contact=msg.left_contact, right_contact=msg.right_contact, cop_on_edge=msg.cop_on_edge,
        left_normal_force=msg.left_normal_force, right_normal_force=msg.right_normal_force, left_cop=v(msg.left_cop),
        right_cop=v(msg.right_cop), com_velocity_fused=v(msg.com_velocity_fused),
        capture_point_fused=v(msg.capture_point_fused))


def obstacles_from_msg(msg: ObstacleArray) -> list[Obstacle]:
    out = []
    for o in msg.obstacles:
        q = o.pose.orientation
        yaw = float(np.arctan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z)))
        p, s = o.pose.position, o.size
        out.append(Obstacle(o.name, (p.x, p.y, p.z), (s.x, s.y, s.z), yaw, o.is_target))
    return out


def imu_from_msg(msg: Imu) -> tuple[np.ndarray, np.ndarray]:
    """(orientation xyzw, gyro) as the in-process loop gives them."""
    o, g = msg.orientation, msg.angular_velocity
    return np.array([o.x, o.y, o.z, o.w]), np.array([g.x, g.y, g.z])


def fall_event_input(msg: FallEvent):
    """What a node's latched ``fall_event`` input holds: True for a fall event, None for a cleared one
    (the FTB's recovery), as ClosedLoop's latched None clears the input."""
    return None if msg.cleared else True


OBSTACLES = Input("obstacles", ObstacleArray, "obstacles", obstacles_from_msg)
FALL_EVENT = Input("fall_event", FallEvent, "fall_event", fall_event_input)
IMU = Input("imu", Imu, "imu", imu_from_msg, per_tick=True)  # for controllers that read the IMU each tick


def joint_command(names=(), positions=(), velocities=None) -> SimpleNamespace:
    """A JointState's fields as a namespace, for ``encode`` (empty: a release)."""
    return SimpleNamespace(header=SimpleNamespace(stamp=None, frame_id=""), name=names, position=positions,
                           velocity=() if velocities is None else velocities, effort=())


class ControllerNode(Node):
    """Runs one contract controller as a lockstep source.

    Args:
        name: node name (its parameters: ``config/<name>.yaml``).
        make_controller: (declared parameter values, model) -> the controller.
        inputs: further inputs (per tick or latched).
    """

    def __init__(self, name: str, make_controller: Callable[[dict, HumanoidModel], Controller],
                 inputs: list[Input] | None = None, config_name: str | None = None,
                 declarations: dict | None = None):
        super().__init__(name)
        self.params = Params(self, config_name, declarations).declare_all()
        self.model = load_model()
        self.controller = make_controller(self.params, self.model)
        self.source = self.controller.source
        self.extra = list(inputs or [])
        self.pub = self.create_publisher(JointState, f"joint_command/{self.source}", QOS_TICK_WRITER,
                                         event_callbacks=NO_PUB_EVENTS)
        per_tick = [i for i in self.extra if i.per_tick]
        self.gate = TickGate({"centroidal_state", "joint_states", "mux", *(i.name for i in per_tick)},
                             trigger="centroidal_state")
        # the tick's last input is centroidal_state (the estimator answers the bridge's joint_states, mux/state
        # and imu): the loop sleeps on it and takes the others then
        self.hot_loop = HotLoop(self, on_batch=self._on_batch, gathering=self.gate.gathering)
        self.hot_loop.subscribe(CentroidalState, "centroidal_state", lambda m: self._offer("centroidal_state", m),
                                decoded=True, trigger=True)
        self.hot_loop.subscribe(JointState, "joint_states", lambda m: self._offer("joint_states", m), decoded=True)
        self.hot_loop.subscribe(MuxState, "mux/state", lambda m: self._offer("mux", m), decoded=True)
        for i in per_tick:
            self.hot_loop.subscribe(i.msg_type, i.topic, lambda m, i=i: self._offer(i.name, m), i.qos,
                                    decoded=True)
        self.latched: dict[str, Any] = {}
        for i in self.extra:
            if not i.per_tick:
                # taken by the hot loop as soon as they arrive, not by the executor's 50 ms service pass: the
                # FTB's cleared fall_event must reach locomotion within the safe-fall controller's hand-back
                # delay (10 ticks, ~15 ms of wall time on a quiet machine in lockstep); the executor's pass
                # gave a tick with no engaged source in a fresh-clone run
                self.hot_loop.subscribe(i.msg_type, i.topic, lambda m, i=i: self._on_latched(i, m),
                                        i.qos or QOS_LATCHED)
        self.last_cmd: SimpleNamespace | None = None  # the last command (a JointState's fields) ...
        self.last_cmd_data = b""  # ... and its bytes as published
        self.tick_outputs: list[tuple[Any, bytes]] = []  # (publisher, bytes) of the last tick, see publish_tick
        self.first_answer = FirstAnswerHold(self)  # so that the bag (the recorder) gets tick 0's command too
        self.engaged = False
        self.failures = 0
        self.get_logger().info(f"controller {type(self.controller).__name__} as source {self.source!r}; "
                               f"tick inputs {sorted(self.gate.required)}")

    # ------------------------------------------------------------ inputs
    def _on_latched(self, inp: Input, msg) -> None:
        try:
            self.latched[inp.name] = inp.convert(msg)
        except Exception as e:  # noqa: BLE001 - a bad message never kills the node
            self.get_logger().error(f"{inp.topic}: refused ({e})", throttle_duration_sec=1.0)

    def _offer(self, kind: str, msg) -> None:
        action = self.gate.offer(kind, stamp_key(msg.header.stamp), msg)
        if action is Action.RETRANSMIT:
            if not self.first_answer.ready([self.pub, *(pub for pub, _ in self.tick_outputs)]):
                return  # still held (see _on_batch)
            if self.last_cmd is not None:
                self.pub.publish(self.last_cmd_data)  # the bridge resent the tick: answer it again
            for pub, out in self.tick_outputs:  # and the tick's other outputs (a reader may have missed them)
                pub.publish(out)
            return
        if action is Action.RESET:
            self.get_logger().info(f"sim time went back to {stamp_key(msg.header.stamp) * 1e-9:.3f} s: "
                                   f"controller reset")
            self.controller.reset()
            self.last_cmd, self.engaged = None, False
        if not self.hot_loop.batching:  # callbacks from a plain executor: answer at once
            self._on_batch()

    def observation(self, stamp_ns: int, inputs: dict) -> Observation:
        js: JointState = inputs["joint_states"]
        if list(js.name) != self.model.joint_names:
            idx = {n: i for i, n in enumerate(js.name)}
            order = [idx[n] for n in self.model.joint_names]  # KeyError: a joint is missing
            q, v = np.array(js.position)[order], np.array(js.velocity)[order]
        else:
            q, v = np.array(js.position), np.array(js.velocity)
        extra = dict(self.latched)
        for i in self.extra:
            if i.per_tick:
                extra[i.name] = i.convert(inputs[i.name])
        mux = inputs["mux"]
        return Observation(stamp_ns, q, v, centroidal_from_msg(inputs["centroidal_state"]), mux.active, extra,
                           joint_targets=np.array(mux.targets, dtype=float) if len(mux.targets) else None)

    # ------------------------------------------------------------ the tick
    def _on_batch(self) -> None:
        tick = self.gate.poll()
        if tick is None:
            return
        self.tick_outputs = []
        stamp = ros_stamp(tick.inputs["centroidal_state"].header.stamp)
        stepped = None
        try:
            obs = self.observation(tick.stamp_ns, tick.inputs)
            targets = self.controller.step(obs)
            cmd = self._command(targets)
            stepped = (obs, targets)
        except Exception as e:  # noqa: BLE001 - never die on a bad tick; never leave a taken-over robot
            if not self.context.ok():
                return  # shutting down (a signal arrived mid-tick): nothing to answer, nothing failed
            self._failed(tick.stamp_ns, e)
            cmd = joint_command(self.last_cmd.name, self.last_cmd.position) \
                if self.engaged and self.last_cmd is not None else joint_command()
        cmd.header.stamp = stamp
        self.last_cmd_data = encode(self.pub, cmd)
        # first: in lockstep the bridge waits for it, not for the outputs below. The first answer waits for the
        # command's readers to match (the bridge resends the tick meanwhile; the resend publishes it)
        if self.first_answer.ready([self.pub]):
            self.pub.publish(self.last_cmd_data)
        self.last_cmd = cmd
        self.engaged = bool(cmd.name)
        if stepped is not None:
            try:
                self.after_step(*stepped)
            except Exception as e:  # noqa: BLE001
                if self.context.ok():
                    self._failed(tick.stamp_ns, e, "its per-tick outputs")

    def _failed(self, stamp_ns: int, e: Exception, what: str | None = None) -> None:
        self.failures += 1
        then = what and f"no {what} this tick"
        self.get_logger().error(f"tick {stamp_ns * 1e-9:.3f} s failed: {e!r}; "
                                + (then or ("repeating the last targets" if self.engaged else "releasing")),
                                throttle_duration_sec=1.0)

    def _command(self, targets: JointTargets | None) -> SimpleNamespace:
        if targets is None:
            return joint_command()
        q = np.asarray(targets.positions, float)
        if q.shape != (self.model.njoints,) or not np.all(np.isfinite(q)):
            raise ValueError(f"controller returned bad positions (shape {q.shape})")
        v = None if targets.velocities is None else np.asarray(targets.velocities, float)
        return joint_command(self.model.joint_names, q, v)

    def publish_tick(self, pub, msg) -> None:
        """Publish a per-tick output of this tick (walking/state, estop/status): sent again with the command
        when the tick is retransmitted, since a reader that matched late (start-up) would otherwise wait for it
        for ever in lockstep. Held with the first command (see FirstAnswerHold)."""
        data = encode(pub, msg)
        self.tick_outputs.append((pub, data))
        if self.first_answer.released:
            pub.publish(data)

    def after_step(self, observation: Observation, targets: JointTargets | None) -> None:
        """Hook for subclasses: publish the controller's own per-tick state (e.g. walking/state) with
        :meth:`publish_tick`."""
