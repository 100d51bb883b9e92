"""sim_bridge: the PyBullet world on the ROS graph.

Publishes /clock and the sensors each control tick, takes joint commands from
several controllers through a priority mux (like twist_mux), applies pushes and
obstacles, and reports ground-truth run metrics at the end.

Lockstep (default): after publishing the sensors stamped t_k, the bridge waits
until every source in ``lockstep_sources`` has sent its command stamped t_k
(a JointState with no names means "I release control this tick"), then steps.
A source silent for ``stall_timeout`` (the first tick: ``start_timeout``, which
covers every source's start-up) ends the run as stalled, named in the metrics.
Results then depend only on the commands, never on CPU load. If nothing moves
for ``retransmit_period`` wall seconds (start-up discovery), the tick's sensors
are sent again; downstream nodes answer a repeated stamp with their last output.
Free-run: steps at ``real_time_factor`` x real time with the freshest commands,
once the lockstep sources have answered the first tick (or ``start_timeout`` passed).
"""
from __future__ import annotations

import json
import math
import sys
import time
import types

import numpy as np
import rclpy
import rclpy.executors
from builtin_interfaces.msg import Time as TimeMsg
from geometry_msgs.msg import TransformStamped, WrenchStamped
from humfall_interfaces.msg import FallEvent, MuxState, Obstacle, ObstacleArray, SafeFallDecision
from humfall_interfaces.srv import Push, SetObstacles
from nav_msgs.msg import Odometry
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.node import Node
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import Imu, JointState
from std_msgs.msg import Float64, String
from std_srvs.srv import Trigger
from tf2_msgs.msg import TFMessage

from humfall_ros import scenario as scenario_mod
from humfall_ros.control.mux import CommandMux, JointCommand, MuxDecision, validate_command
from humfall_ros.recording import cdr
from humfall_ros.nodes.common import (
    NO_PUB_EVENTS,
    QOS_CLOCK,
    QOS_LATCHED,
    QOS_RELIABLE,
    QOS_TICK_WRITER,
    KeptWaitSet,
    Params,
    profiled,
    publish_encoded,
    shutting_down,
    stamp_key,
    wait_acknowledged,
)
from humfall_ros.sim.ground_truth import GroundTruth
from humfall_ros.sim.sensors import SensorNoise, Sensors
from humfall_ros.sim.world import STANDING_POSTURE, Box, SimWorld, validate_push

SIDE_TOPIC = {"l": "left_foot/wrench", "r": "right_foot/wrench"}


def stamp_of(t: float) -> TimeMsg:
    ns = int(round(t * 1e9))
    return TimeMsg(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def seconds(stamp: TimeMsg) -> float:
    return stamp.sec + stamp.nanosec * 1e-9


def _names(values) -> list[str]:
    """A string-array parameter; [''] stands for the empty list ROS cannot type."""
    return [v for v in values if v]


class SimBridge(Node):
    def __init__(self):
        super().__init__("sim_bridge")
        P = Params(self)
        self.physics_rate = P.declare("physics_rate")
        self.control_rate = P.declare("control_rate")
        self.lockstep = P.declare("lockstep")
        self.rtf_target = P.declare("real_time_factor")
        self.sources = _names(P.declare("command_sources"))
        self.lockstep_sources = _names(P.declare("lockstep_sources"))
        self.command_timeout = P.declare("command_timeout")
        self.retransmit_period = P.declare("retransmit_period")
        self.stall_timeout = P.declare("stall_timeout")
        self.start_timeout = P.declare("start_timeout")
        self.end_time = P.declare("end_time")
        self.wait_for_nodes = _names(P.declare("wait_for_nodes"))
        self.wait_timeout = P.declare("wait_timeout")
        self.ack_timeout = P.declare("ack_timeout")
        self.metrics_file = P.declare("metrics_file")
        self.scenario_name = P.declare("scenario")
        # SimWorld's own settings (friction, contact threshold), from the parameters or the scenario's sim section
        world_kw = {k: P.declare(k) for k in ("friction", "contact_breaking_threshold", "servo_time_constant")}
        tf_rate = P.declare("tf_rate")
        gt_rate = P.declare("ground_truth_rate")
        self.service_period = 1.0 / P.declare("service_rate")
        noise = {f: P.declare(f"noise_{f}")
                 for f, what in (("joint_position", "joint positions, rad"), ("joint_velocity", "joint velocities, "
                                 "rad/s"), ("imu_orientation", "the IMU attitude, rad"), ("gyro", "the gyro, rad/s"),
                                 ("accelerometer", "the accelerometer, m/s^2"), ("force", "ankle forces, N"),
                                 ("torque", "ankle torques, N m"))}
        noise_seed = P.declare("noise_seed")
        unknown = set(self.lockstep_sources) - set(self.sources)
        if unknown:
            raise ValueError(f"lockstep_sources {sorted(unknown)} are not command_sources")

        self.scenario = scenario_mod.load(self.scenario_name) if self.scenario_name else scenario_mod.validate({})
        if self.scenario_name:
            # the scenario's sim section and duration rule, unless a parameter was given explicitly
            sim = self.scenario["sim"]
            for param, attr, value in (("physics_rate", "physics_rate", float(sim["physics_rate"])),
                                       ("control_rate", "control_rate", float(sim["control_rate"])),
                                       ("lockstep", "lockstep", bool(sim["lockstep"])),
                                       ("real_time_factor", "rtf_target", float(sim["real_time_factor"])),
                                       ("friction", None, float(sim["friction"])),
                                       ("contact_breaking_threshold", None, float(sim["contact_breaking_threshold"])),
                                       ("servo_time_constant", None, float(sim["servo_time_constant"])),
                                       ("end_time", "end_time", float(self.scenario["duration"]))):
                if param in P.overridden:
                    if P.values[param] != value:
                        self.get_logger().info(f"parameter {param}={P.values[param]!r} overrides the scenario's "
                                               f"{'duration' if param == 'end_time' else 'sim.' + param}={value!r}")
                    continue
                if attr is None:
                    world_kw[param] = value
                else:
                    setattr(self, attr, value)
        posture = None
        if self.scenario["robot"]["initial_posture"]:
            posture = {**STANDING_POSTURE, **self.scenario["robot"]["initial_posture"]}
        self.world = SimWorld(self.physics_rate, self.control_rate, initial_posture=posture, **world_kw)
        self.model = self.world.model
        self.sensors = Sensors(self.world, SensorNoise(**noise, seed=noise_seed))
        self.joint_index = {n: i for i, n in enumerate(self.model.joint_names)}
        self._apply_scenario()

        self.pub_clock = self.create_publisher(Clock, "/clock", QOS_CLOCK, event_callbacks=NO_PUB_EVENTS)
        self.pub_js = self.create_publisher(JointState, "joint_states", QOS_TICK_WRITER, event_callbacks=NO_PUB_EVENTS)
        self.pub_imu = self.create_publisher(Imu, "imu", QOS_TICK_WRITER, event_callbacks=NO_PUB_EVENTS)
        self.pub_wrench = {s: self.create_publisher(WrenchStamped, t, QOS_TICK_WRITER, event_callbacks=NO_PUB_EVENTS)
                           for s, t in SIDE_TOPIC.items()}
        self.pub_odom = self.create_publisher(Odometry, "ground_truth/odom", QOS_TICK_WRITER,
                                              event_callbacks=NO_PUB_EVENTS)
        self.pub_active = self.create_publisher(String, "active_controller", QOS_LATCHED)
        self.pub_mux = self.create_publisher(MuxState, "mux/state", QOS_TICK_WRITER, event_callbacks=NO_PUB_EVENTS)
        self.pub_rtf = self.create_publisher(Float64, "sim/real_time_factor", QOS_TICK_WRITER)
        self.pub_obstacles = self.create_publisher(ObstacleArray, "obstacles", QOS_LATCHED)
        self.pub_result = self.create_publisher(String, "sim/result", QOS_LATCHED)
        # the robot for RViz / Foxglove: URDF text, fixed joints once, moving joints at tf_rate
        self.pub_description = self.create_publisher(String, "/robot_description", QOS_LATCHED)
        self.pub_tf_static = self.create_publisher(TFMessage, "/tf_static", QOS_LATCHED)
        self.pub_tf = self.create_publisher(TFMessage, "/tf", QOS_TICK_WRITER, event_callbacks=NO_PUB_EVENTS)
        self.tf_every = max(1, int(round(self.control_rate / tf_rate))) if tf_rate > 0 else 0
        self.odom_every = max(1, int(round(self.control_rate / gt_rate)))
        self._tick_msgs()
        with open(self.model.urdf_path) as f:
            self.pub_description.publish(String(data=f.read()))

        self._published: dict = {}  # publisher -> messages sent
        self.mux = CommandMux(self.sources, self.model.joint_names, self.command_timeout)
        self.answered: set[str] = set()
        self.rejected_commands = 0
        self.holding_ticks = 0
        self.stalled: tuple[str, float] | None = None  # (sources, sim time) of a lockstep stall
        self.decision = MuxDecision(None)
        self.uncontrolled_ticks = 0
        # Commands arrive every tick: they get a node of their own with nothing else on it,
        # so the hot loop waits on 3 subscriptions instead of every service, parameter
        # service and QoS event of the bridge (rclpy builds the wait set each spin).
        self.command_node = rclpy.create_node("sim_bridge_commands", start_parameter_services=False,
                                              enable_rosout=False)
        no_events = SubscriptionEventCallbacks(use_default_callbacks=False)
        # raw: taken as bytes and decoded by recording/cdr.py (rclpy building a 31-name JointState is ~3x dearer);
        # the direct take and the executor's path (when that is unusable) both go through _on_command_bytes
        self._decode_command = cdr.decoder(JointState)
        self.command_subs = {s: self.command_node.create_subscription(
            JointState, f"joint_command/{s}", lambda data, s=s: self._on_command_bytes(s, data), QOS_RELIABLE,
            event_callbacks=no_events, raw=True) for s in self.sources}
        self._can_take = True
        self._command_wait: KeptWaitSet | None = None   # _wait_commands
        # the fall controller's event and decision, for the run metrics (alpha2, lead time, prediction)
        self.create_subscription(FallEvent, "fall_event", self._on_fall_event, QOS_LATCHED)
        self.create_subscription(SafeFallDecision, "safe_fall/decision", self._on_decision, QOS_LATCHED)
        self.create_service(Push, "sim/push", self._on_push)
        self.create_service(Trigger, "sim/reset", self._on_reset)
        self.create_service(SetObstacles, "sim/set_obstacles", self._on_set_obstacles)
        self.active_source = ""
        self.done = False
        self._publish_active("none")
        self._publish_obstacles()
        self._publish_tf(static=True)

    def _tick_msgs(self) -> None:
        """Per-tick messages built once and refilled each tick, as namespaces (``cdr.blank``) encoded by
        ``publish_encoded``: constructing ~8 rosidl messages per tick cost the bridge about a tenth of its
        CPU, and rclpy's conversion of a refilled message at publish as much again."""
        self._js = cdr.blank(JointState)
        self._js.name = list(self.model.joint_names)
        self._imu = cdr.blank(Imu)
        self._imu.header.frame_id = "imu_link"
        self._wrench = {}
        for side in self.pub_wrench:
            m = cdr.blank(WrenchStamped)
            m.header.frame_id = self.model.foot_link[side]
            self._wrench[side] = m
        self._odom = cdr.blank(Odometry)
        self._odom.header.frame_id, self._odom.child_frame_id = "odom", "waist"
        self._tf_msgs: dict[bool, TFMessage] = {}
        self._mux_msg = cdr.blank(MuxState)
        self._clock = cdr.blank(Clock)

    # ------------------------------------------------------------ scenario
    def _apply_scenario(self) -> None:
        self.truth = GroundTruth(self.world, self.scenario)

    # ------------------------------------------------------------ callbacks
    def _on_command_bytes(self, source: str, data: bytes) -> None:
        """A command's serialized bytes: decoded, or counted as rejected and dropped when malformed."""
        try:
            msg = self._decode_command(data)
        except Exception as e:  # noqa: BLE001 - struct.error, ValueError: malformed bytes
            self.rejected_commands += 1
            self.get_logger().warning(f"joint_command/{source}: undecodable message dropped ({e})",
                                      throttle_duration_sec=1.0)
            return
        self._on_command(source, msg)

    def _on_command(self, source: str, msg) -> None:
        """A command (a JointState decoded by recording/cdr.py: a read-only namespace with its fields)."""
        reason = validate_command(msg.name, msg.position, msg.velocity, self.joint_index)
        if reason:
            self.rejected_commands += 1
            self.get_logger().warning(f"joint_command/{source} refused: {reason}",
                                      throttle_duration_sec=1.0)
            msg = types.SimpleNamespace(header=msg.header, name=[], position=[], velocity=[])  # a release this tick
        why = self.mux.update(source, JointCommand(seconds(msg.header.stamp), list(msg.name), list(msg.position),
                                                   list(msg.velocity)), now=self.world.time)
        if why:
            # from the future, or a second different answer to a tick: refused, the tick still waits
            self.rejected_commands += 1
            self.get_logger().warning(f"joint_command/{source} refused: {why}", throttle_duration_sec=1.0)
            return
        if stamp_key(msg.header.stamp) == self.tick_key:
            self.answered.add(source)

    def _on_fall_event(self, msg) -> None:
        if msg.cleared:
            return  # the recovery's stamp, not a trigger (a bridge that joins late sees only this one)
        self.truth.metrics.note_fall_event(seconds(msg.header.stamp))

    def _on_decision(self, msg) -> None:
        try:
            self.truth.metrics.note_decision({
                "stamp_ns": stamp_key(msg.header.stamp), "case": msg.step_case, "swing_side": msg.swing_side,
                "landing": list(msg.landing), "alpha2": msg.alpha2, "captured": msg.captured,
                "touchdown_time": msg.touchdown_time, "step_index": msg.step_index})
        except Exception as e:  # noqa: BLE001 - a bad message never stops the bridge
            self.get_logger().warning(f"safe_fall/decision not usable for the metrics: {e}")

    def _wait_commands(self, command_executor, timeout: float) -> None:
        """Wait up to ``timeout`` [s] for a command (then ``take_commands`` takes it).

        A wait set on the command subscriptions alone, kept between ticks (``KeptWaitSet``, as the other nodes'
        hot loops): the executor's ``spin_once`` built its wait set on every call, inside the lockstep round
        trip. If rclpy's internals are not what this expects, the executor path."""
        if self._can_take:
            try:
                if self._command_wait is None:
                    self._command_wait = KeptWaitSet(self.command_subs.values(), self.command_node.context)
                self._command_wait.wait(int(timeout * 1e9))
                return
            except (AttributeError, TypeError, ImportError) as e:  # rclpy internals changed
                self.get_logger().warning(f"command wait set unusable ({e}); spinning the executor")
                self._can_take = False
        command_executor.spin_once(timeout_sec=timeout)

    def take_commands(self) -> None:
        """Take queued commands without a wait (cheap when they are already here).

        Uses the subscription handle's take_message, as rclpy's executor does; if
        that internal API changes, the executor path alone still works.
        """
        if not self._can_take:
            return
        try:
            for s, sub in self.command_subs.items():
                while True:
                    with sub.handle:
                        taken = sub.handle.take_message(JointState, True)
                    if taken is None:
                        break
                    self._on_command_bytes(s, taken[0])
        except Exception as e:  # noqa: BLE001
            self._can_take = False
            self.get_logger().warning(f"direct take disabled ({e}); using the executor only")

    def _on_push(self, req: Push.Request, resp: Push.Response) -> Push.Response:
        force = [req.force.x, req.force.y, req.force.z]
        point = [req.point.x, req.point.y, req.point.z]
        link = req.link or "chest"
        reason = validate_push(force, point, req.duration)
        if reason is None and link not in self.world.link_ids:
            reason = f"unknown link {link!r} (links: {', '.join(sorted(self.world.link_ids))})"
        if reason:
            resp.success, resp.message = False, reason
            self.get_logger().warning(f"sim/push refused: {reason}")
            return resp
        self.world.add_push(force, point, req.duration, link)
        self.truth.metrics.set_reference_cop(self.world.ground_truth_cop())
        resp.success, resp.message = True, f"pushing {link} with {np.round(force, 1).tolist()} N for {req.duration} s"
        self.get_logger().info(resp.message)
        return resp

    def _on_reset(self, req, resp):
        self.world.reset()
        self.sensors.reset()
        self.mux.clear()
        self.answered = set()
        self._apply_scenario()
        self._publish_obstacles()
        resp.success, resp.message = True, "world reset"
        return resp

    def _on_set_obstacles(self, req: SetObstacles.Request, resp: SetObstacles.Response):
        boxes = []
        for i, o in enumerate(req.obstacles):
            vals = [o.pose.position.x, o.pose.position.y, o.pose.position.z, o.size.x, o.size.y, o.size.z]
            if not all(math.isfinite(v) for v in vals) or min(vals[3:]) <= 0 or max(vals[3:]) > 50:
                resp.success, resp.message = False, f"obstacle {i} ({o.name!r}): sizes must be finite, in (0, 50] m"
                return resp
            q = o.pose.orientation
            if not all(math.isfinite(c) for c in (q.x, q.y, q.z, q.w)):
                resp.success, resp.message = False, f"obstacle {i} ({o.name!r}): orientation must be finite"
                return resp
            yaw = math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z)) if q.w or q.z else 0.0
            boxes.append(Box(o.name or f"box{i}", tuple(vals[:3]), tuple(vals[3:]), yaw, o.is_target))
        if len({b.name for b in boxes}) != len(boxes):
            resp.success, resp.message = False, "obstacle names must be unique"
            return resp
        self.world.set_obstacles(boxes)
        self.truth.set_target(boxes)
        self._publish_obstacles()
        resp.success, resp.message = True, f"{len(boxes)} obstacles set"
        return resp

    # ------------------------------------------------------------ publishing
    def _publish_active(self, name: str) -> None:
        if name != self.active_source:
            self.active_source = name
            self.pub_active.publish(String(data=name))

    def _publish_obstacles(self) -> None:
        msg = ObstacleArray()
        msg.header.frame_id = "odom"
        msg.header.stamp = stamp_of(self.world.time)
        for b in self.world.obstacles:
            o = Obstacle(name=b.name, is_target=b.is_target)
            o.pose.position.x, o.pose.position.y, o.pose.position.z = b.position
            o.pose.orientation.z, o.pose.orientation.w = math.sin(b.yaw / 2), math.cos(b.yaw / 2)
            o.size.x, o.size.y, o.size.z = b.size
            msg.obstacles.append(o)
        self.pub_obstacles.publish(msg)

    def _pub(self, pub, msg) -> None:
        publish_encoded(pub, msg)
        self._published[pub] = self._published.get(pub, 0) + 1  # topic names resolved at the end

    @property
    def published(self) -> dict[str, int]:
        """Messages published per topic, for the recorder's no-loss check."""
        return {pub.topic_name: n for pub, n in self._published.items()}

    def _publish_tf(self, static: bool = False) -> None:
        """Ground-truth link poses as TF: odom -> waist and parent -> child per URDF joint."""
        w = self.world
        q = w.pinocchio_configuration()
        self.model.forward(q)
        st = stamp_of(w.time)
        links = self.model.link_transforms(fixed=static)
        if not static:
            links = [("odom", self.model.root_link, q[:3], q[3:7]), *links]
        msg = self._tf_msgs.get(static)
        if msg is None:  # the frames never change: build the transforms once, refill the numbers
            msg = self._tf_msgs[static] = TFMessage(transforms=[
                TransformStamped(child_frame_id=child) for _, child, _, _ in links])
            for t, (parent, _, _, _) in zip(msg.transforms, links):
                t.header.frame_id = parent
        for t, (_, _, p, quat) in zip(msg.transforms, links):
            t.header.stamp = st
            tr, r = t.transform.translation, t.transform.rotation
            tr.x, tr.y, tr.z = float(p[0]), float(p[1]), float(p[2])
            r.x, r.y, r.z, r.w = float(quat[0]), float(quat[1]), float(quat[2]), float(quat[3])
        self._pub(self.pub_tf_static if static else self.pub_tf, msg)

    def publish_sensors(self) -> None:
        w = self.world
        st = stamp_of(w.time)
        # the estimator's inputs first (joint states, IMU, wrenches): in lockstep its answer starts the
        # controllers' tick, so what only they and the recorder read (mux/state, /clock) goes after
        r = self.sensors.read()
        js = self._js
        js.header.stamp = st
        js.position, js.velocity, js.effort = r.joint_position, r.joint_velocity, r.joint_effort
        self._pub(self.pub_js, js)
        orn, gyro, acc = r.imu_orientation, r.gyro, r.accelerometer
        imu = self._imu
        imu.header.stamp = st
        o, g, a = imu.orientation, imu.angular_velocity, imu.linear_acceleration
        o.x, o.y, o.z, o.w = orn
        g.x, g.y, g.z = gyro
        a.x, a.y, a.z = acc
        self._pub(self.pub_imu, imu)
        for side, pub in self.pub_wrench.items():
            f, t = r.wrenches[side]
            m = self._wrench[side]
            m.header.stamp = st
            m.wrench.force.x, m.wrench.force.y, m.wrench.force.z = f
            m.wrench.torque.x, m.wrench.torque.y, m.wrench.torque.z = t
            self._pub(pub, m)
        mux = self._mux_msg
        mux.header.stamp = st
        mux.active, mux.holding = self.decision.source or "none", self.decision.holding
        mux.engaged = [s for s in self.mux.sources if self.mux.engaged[s]]
        mux.targets = w.targets
        self._pub(self.pub_mux, mux)
        self._clock.clock = st
        self._pub(self.pub_clock, self._clock)
        tick = w.step_count // w.substeps
        if tick % self.odom_every == 0:
            pos, orn_b, lin, ang = w.base_state()
            od = self._odom
            od.header.stamp = st
            p = od.pose.pose
            p.position.x, p.position.y, p.position.z = pos
            p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w = orn_b
            # REP 105 puts the odom twist in the child frame; we keep it in the world frame
            # (frame_id) because that is what the estimator comparison needs; documented.
            tw = od.twist.twist
            tw.linear.x, tw.linear.y, tw.linear.z = lin
            tw.angular.x, tw.angular.y, tw.angular.z = ang
            self._pub(self.pub_odom, od)
        if self.tf_every and tick % self.tf_every == 0:
            self._publish_tf()

    # ------------------------------------------------------------ stepping
    @property
    def tick_key(self) -> int:
        return int(round(self.world.time * 1e9))

    def _mux(self) -> None:
        w = self.world
        d, q, v = self.mux.targets(w.time, w.targets, w.target_velocities)
        self.decision = d
        self._publish_active(d.source or "none")
        if d.source is not None and not d.holding:
            w.set_joint_targets(q, v)
        else:
            self.uncontrolled_ticks += 1  # e.g. free-run with controllers that cannot keep up
            if d.holding:
                self.holding_ticks += 1
                self.get_logger().warning(f"t={w.time:.3f}: {d.source} took over and is silent: holding its "
                                          "last targets (never handing back to a lower source)",
                                          throttle_duration_sec=1.0)

    def result(self) -> dict:
        r = self.truth.metrics.result()
        r.update(sim_duration_s=round(self.world.time, 6), rejected_commands=self.rejected_commands,
                 stalled_ticks=self.stalled_ticks, uncontrolled_ticks=self.uncontrolled_ticks,
                 holding_ticks=self.holding_ticks,
                 stalled_source=self.stalled[0] if self.stalled else None,
                 stalled_at_s=round(self.stalled[1], 6) if self.stalled else None,
                 ticks=int(round(self.world.time * self.control_rate)), published=dict(self.published))
        return r

    def wait_for_subscribers(self, executor) -> None:
        """Hold time at zero until the listed nodes listen to every per-tick topic (so the bag starts at t=0)."""
        deadline = time.monotonic() + self.wait_timeout
        per_tick = [self.pub_clock, self.pub_js, self.pub_imu, *self.pub_wrench.values(), self.pub_odom]
        # the lockstep sources' commands even before their writers show: a controller still importing when we
        # look would otherwise not be waited for, and the recorder (which subscribes to what is published)
        # missed its tick-0 command (a CI run)
        commands = {self.command_subs[s].topic_name for s in self.lockstep_sources if s in self.command_subs}
        while rclpy.ok() and self.wait_for_nodes:
            missing = set()
            # every topic someone publishes now (ours and the controllers'), e.g. for the recorder
            for topic in {t for t, _ in self.get_topic_names_and_types()} | commands:
                if topic not in commands and not self.get_publishers_info_by_topic(topic):
                    continue
                present = {i.node_name for i in self.get_subscriptions_info_by_topic(topic)}
                missing |= {f"{n} on {topic}" for n in self.wait_for_nodes if n not in present}
            for pub in per_tick:
                if pub.get_subscription_count() < self.count_subscribers(pub.topic_name):
                    missing.add(f"matching on {pub.topic_name}")  # discovered, data path not up yet
            if not missing:
                return
            if time.monotonic() > deadline:
                self.get_logger().warning(f"starting without {sorted(missing)}: not subscribed after "
                                          f"{self.wait_timeout} s")
                return
            executor.spin_once(timeout_sec=0.05)

    def run(self, executor, command_executor) -> None:
        """The main loop (instead of executor.spin: the bridge owns time).

        ``command_executor`` spins the command node every tick; ``executor`` (services,
        parameters) is serviced every ``service_period`` of wall time.
        """
        self.stalled_ticks = 0
        self.wait_for_subscribers(executor)
        wall0, sim0 = time.monotonic(), self.world.time
        rtf_wall, rtf_sim = wall0, sim0
        next_service = wall0
        service_period = self.service_period
        first_tick = True
        while rclpy.ok():
            self.answered = set()  # commands for this tick can only follow its sensors
            self.publish_sensors()
            # free-run too waits for the first tick's commands: controllers that are still
            # warming up (first pinocchio call, matching) would otherwise miss the start
            if self.lockstep or first_tick:
                waited_since = last_send = time.monotonic()
                while rclpy.ok() and not set(self.lockstep_sources) <= self.answered:
                    self.take_commands()
                    if set(self.lockstep_sources) <= self.answered:
                        break
                    self._wait_commands(command_executor, 0.01)
                    now = time.monotonic()
                    if now - last_send > self.retransmit_period:
                        self.publish_sensors()
                        last_send = now
                        executor.spin_once(timeout_sec=0.0)
                    # tick 0 waits for every source's start-up (imports, first pinocchio call, DDS
                    # matching: seconds on a loaded machine); later ticks only for a computation
                    timeout = self.start_timeout if first_tick else self.stall_timeout
                    if now - waited_since <= timeout:
                        continue
                    missing = sorted(set(self.lockstep_sources) - self.answered)
                    if not self.lockstep:
                        self.get_logger().warning(f"free-run: no first command from {missing} after "
                                                  f"{timeout:.0f} s; starting without it")
                        break
                    self.get_logger().error(f"lockstep stalled at t={self.world.time:.3f} s (tick "
                                            f"{int(round(self.world.time * self.control_rate))}): no command from "
                                            f"{', '.join(missing)} after {timeout:.0f} s "
                                            f"({'start_timeout' if first_tick else 'stall_timeout'}); "
                                            "ending the run")
                    self.stalled_ticks += 1
                    self.stalled = (",".join(missing), self.world.time)
                    break
                if self.stalled is not None:
                    break
                if first_tick:  # time (and the real-time factor) starts once the loop is closed
                    first_tick = False
                    wall0 = rtf_wall = time.monotonic()
            else:
                self.take_commands()
                if not self._can_take:
                    command_executor.spin_once(timeout_sec=0.0)
            now = time.monotonic()
            if now >= next_service:  # pushes, resets, obstacles, parameters
                executor.spin_once(timeout_sec=0.0)
                next_service = now + service_period
            if not rclpy.ok():
                break
            self._mux()
            self.world.step_control()
            self.truth.track()
            if self.end_time > 0 and self.world.time >= self.end_time - 1e-9:
                break
            if not self.lockstep and self.rtf_target > 0:
                ahead = (self.world.time - sim0) / self.rtf_target - (time.monotonic() - wall0)
                if ahead > 0:
                    time.sleep(ahead)
            now = time.monotonic()
            if now - rtf_wall >= 1.0:
                self.pub_rtf.publish(Float64(data=(self.world.time - rtf_sim) / (now - rtf_wall)))
                rtf_wall, rtf_sim = now, self.world.time
        self.finish(time.monotonic() - wall0)

    def finish(self, wall: float) -> None:
        if self.done:
            return
        self.done = True
        self._unless_shut_down(self.publish_sensors)  # the final state, so every consumer sees the last tick
        r = self.result()
        r["bridge_wall_time_s"] = round(wall, 3)
        r["bridge_cpu_s"] = round(time.process_time(), 3)
        self._unless_shut_down(lambda: self.pub_result.publish(String(data=json.dumps(r))))
        if self.metrics_file:
            with open(self.metrics_file, "w") as f:
                json.dump(r, f, indent=2)
        self.get_logger().info(f"run ended at t={self.world.time:.3f} s: fell={r['fell']}")
        if self.uncontrolled_ticks and self.sources:
            self.get_logger().warning(f"{self.uncontrolled_ticks} of {r['ticks']} ticks had no live joint command "
                                      f"(controllers late or absent); the robot held its last targets")

    @staticmethod
    def _unless_shut_down(publish) -> None:
        """Publish while the context is up; SIGINT may shut it down at any moment (even mid-call)."""
        if not rclpy.ok():
            return
        try:
            publish()
        except Exception:  # noqa: BLE001
            if not shutting_down():
                raise

    def close(self) -> None:
        if self._command_wait is not None:
            self._command_wait.close()
            self._command_wait = None
        self.world.close()


def main(args=None) -> int:
    rclpy.init(args=args)
    node = None
    try:
        try:
            node = SimBridge()
        except (scenario_mod.ScenarioError, ValueError) as e:  # a configuration error: say it, no traceback
            print(f"sim_bridge: {e}", file=sys.stderr)
            return 2
        executor = rclpy.executors.SingleThreadedExecutor()
        executor.add_node(node)
        command_executor = rclpy.executors.SingleThreadedExecutor()
        command_executor.add_node(node.command_node)
        with profiled(node):
            node.run(executor, command_executor)
        # the recorder may still be behind (starved of CPU): our writers keep what it has not acknowledged, but only
        # while they exist
        late = wait_acknowledged(node, node.ack_timeout) if rclpy.ok() else []
        if late:
            node.get_logger().warning(f"readers had not acknowledged everything on {late} after "
                                      f"{node.ack_timeout:.1f} s; a bag may miss the run's last messages")
        # linger briefly so latched results reach late subscribers
        end = time.monotonic() + 0.3
        while rclpy.ok() and time.monotonic() < end:
            executor.spin_once(timeout_sec=0.05)
    except (KeyboardInterrupt, rclpy.executors.ExternalShutdownException):
        pass
    except Exception:  # noqa: BLE001 - a take/publish cut short by shutdown is a clean stop
        if not shutting_down():
            raise
    finally:
        if node is not None:
            if not node.done and getattr(node, "stalled_ticks", None) is not None and node.metrics_file:
                node.finish(0.0)
            node.close()
            node.command_node.destroy_node()
            node.destroy_node()
        rclpy.try_shutdown()
    if node is not None and node.stalled is not None:
        return 3  # a stalled lockstep run is not a result: `humfall up` reports it with the log tail
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
