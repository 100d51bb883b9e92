"""state_estimator: joint states + IMU + ankle wrenches -> centroidal_state.

Waits for all sensor messages of one stamp (the bridge sends them together),
runs the leg-odometry estimator (humfall_ros.model.estimation) and publishes
``centroidal_state`` with the same stamp, so lockstep controllers answer the
right tick. Standard PointStamped / PolygonStamped / MarkerArray copies go out
at ``viz_rate`` for RViz and Foxglove.
"""
from __future__ import annotations

import numpy as np
from geometry_msgs.msg import Point, Point32, PointStamped, PolygonStamped, WrenchStamped
from humfall_interfaces.msg import CentroidalState
from builtin_interfaces.msg import Time
from nav_msgs.msg import Odometry
from rclpy.node import Node
from sensor_msgs.msg import Imu, JointState
from std_msgs.msg import Header
from visualization_msgs.msg import Marker, MarkerArray

from humfall_ros.control.tick_gate import Action, TickGate
from humfall_ros.model.estimation import CentroidalEstimator
from humfall_ros.model.humanoid import SIDES, load_model
from humfall_ros.nodes.common import (
    NO_PUB_EVENTS,
    QOS_TICK_WRITER,
    FirstAnswerHold,
    HotLoop,
    Params,
    encode,
    run_node,
    stamp_key,
    xyz,
)
from humfall_ros.recording import cdr

SIDE_TOPIC = {"l": "left_foot/wrench", "r": "right_foot/wrench"}



def to_point(v) -> Point:
    """A geometry_msgs Point from a 2- or 3-vector or from anything with x, y, z."""
    if hasattr(v, "x"):
        return Point(x=float(v.x), y=float(v.y), z=float(v.z))
    return Point(x=float(v[0]), y=float(v[1]), z=float(v[2]) if len(v) > 2 else 0.0)


def fill_xyz(target, v) -> None:
    """Set a Point's or Vector3's (or its namespace's) x, y, z in place from a 2- or 3-vector."""
    target.x, target.y = float(v[0]), float(v[1])
    target.z = float(v[2]) if len(v) > 2 else 0.0


class StateEstimator(Node):
    def __init__(self):
        super().__init__("state_estimator")
        P = Params(self)
        self.use_ground_truth = P.declare("use_ground_truth")
        viz_rate = P.declare("viz_rate")
        contact_force = P.declare("contact_force")
        self.model = load_model()
        self.estimator = CentroidalEstimator(self.model, contact_force=contact_force,
                                             com_velocity_time_constant=P.declare("com_velocity_time_constant"),
                                             com_velocity_band=P.declare("com_velocity_band"))
        self.viz_period = 1.0 / viz_rate if viz_rate > 0 else float("inf")
        self.last_viz = -float("inf")
        self.last_msg: bytes | None = None  # the last answer as published
        self.first_answer = FirstAnswerHold(self)  # so that the bag gets tick 0's centroidal state too
        # refilled each tick as a namespace and encoded by publish_encoded (rclpy's checking setters and its
        # conversion at publish were ~0.15 ms a tick)
        self.msg = cdr.blank(CentroidalState)
        self.msg.header.frame_id = "odom"
        self.bad_messages = 0
        # one tick = every sensor message of one stamp; a repeated joint_states stamp = a retransmitted tick
        self.gate = TickGate({"js", "imu", "l", "r"} | ({"odom"} if self.use_ground_truth else set()), trigger="js")
        def publisher(msg_type, topic):
            return self.create_publisher(msg_type, topic, QOS_TICK_WRITER, event_callbacks=NO_PUB_EVENTS)

        self.pub = publisher(CentroidalState, "centroidal_state")
        self.pub_com = publisher(PointStamped, "centroidal_state/com")
        self.pub_cop = publisher(PointStamped, "centroidal_state/cop")
        self.pub_cp = publisher(PointStamped, "centroidal_state/capture_point")
        self.pub_poly = publisher(PolygonStamped, "centroidal_state/support_polygon")
        self.pub_markers = publisher(MarkerArray, "centroidal_state/markers")
        # one tick's sensor messages arrive together: the hot loop takes them in one go
        # the loop sleeps on the input the bridge publishes last in a tick (the right ankle's wrench, or the
        # ground-truth odometry) and then takes the others; if one of them is late it waits on all
        last = "odom" if self.use_ground_truth else "r"
        self.hot_loop = sensors = HotLoop(self, on_batch=self._on_batch, gathering=lambda: self.gate.gathering(last))
        sensors.subscribe(JointState, "joint_states", lambda m: self._add("js", m), decoded=True)
        sensors.subscribe(Imu, "imu", lambda m: self._add("imu", m), decoded=True)
        for s, topic in SIDE_TOPIC.items():
            sensors.subscribe(WrenchStamped, topic, lambda m, s=s: self._add(s, m), decoded=True, trigger=s == last)
        if self.use_ground_truth:
            sensors.subscribe(Odometry, "ground_truth/odom", lambda m: self._add("odom", m), decoded=True,
                              trigger=True)
        # a start-up line, as the other nodes give (launchers and tests wait for one)
        self.get_logger().info(f"estimating from {'ground truth' if self.use_ground_truth else 'the sensors'}; "
                               f"tick inputs {sorted(self.gate.required)}")

    def _add(self, kind: str, msg) -> None:
        action = self.gate.offer(kind, stamp_key(msg.header.stamp), msg)
        if action is Action.RETRANSMIT:
            # a retransmitted tick: answer it again so lockstep can move on
            if self.last_msg is not None and self.first_answer.ready([self.pub]):
                self.pub.publish(self.last_msg)  # the bytes of the last answer
            return
        if action is Action.RESET:
            # time went back (sim/reset): what we knew belongs to the old run
            self.get_logger().info(f"sim time went back to {stamp_key(msg.header.stamp) * 1e-9:.3f} s: "
                                   "estimator reset")
            self.estimator.reset()
            self.last_msg = None
        if not self.hot_loop.batching:  # callbacks from a plain executor: answer at once
            self._on_batch()

    def _on_batch(self) -> None:
        """Estimate the newest tick whose sensor messages are all here.

        In lockstep that is the only one. In free-run on a busy machine several may
        have queued up: the older ones are stale, and answering each would only put
        the controller further behind, so the gate drops them (as are incomplete ones).
        """
        tick = self.gate.poll()
        if tick is None:
            return
        try:
            self._estimate(tick.stamp_ns, tick.inputs)
        except Exception as e:  # noqa: BLE001 - a bad message must never kill the estimator
            self.bad_messages += 1
            self.get_logger().error(f"estimate failed at stamp {tick.stamp_ns}: {e}", throttle_duration_sec=1.0)

    def _estimate(self, k: int, slot: dict) -> None:
        js: JointState = slot["js"]
        if list(js.name) != self.model.joint_names:
            idx = {n: i for i, n in enumerate(js.name)}
            missing = [n for n in self.model.joint_names if n not in idx]
            if missing:
                raise ValueError(f"joint_states lacks {missing[:3]}")
            order = [idx[n] for n in self.model.joint_names]
            qj = np.array(js.position)[order]
            vj = np.array(js.velocity)[order]
        else:
            qj, vj = np.array(js.position), np.array(js.velocity)
        imu: Imu = slot["imu"]
        o = imu.orientation
        quat = [o.x, o.y, o.z, o.w]
        gyro = [imu.angular_velocity.x, imu.angular_velocity.y, imu.angular_velocity.z]
        wrenches = {}
        for s in SIDES:
            w = slot[s].wrench
            wrenches[s] = ([w.force.x, w.force.y, w.force.z], [w.torque.x, w.torque.y, w.torque.z])
        truth = None
        if self.use_ground_truth:
            od: Odometry = slot["odom"]
            p, oq = od.pose.pose.position, od.pose.pose.orientation
            tl, ta = od.twist.twist.linear, od.twist.twist.angular
            truth = ([p.x, p.y, p.z], [oq.x, oq.y, oq.z, oq.w], [tl.x, tl.y, tl.z], [ta.x, ta.y, ta.z])
        t = k * 1e-9
        e = self.estimator.update(t, qj, vj, quat, gyro, wrenches, base_truth=truth)
        msg = self.msg  # refilled each tick (publish copies it): cheaper than a new message
        msg.header.stamp.sec, msg.header.stamp.nanosec = int(js.header.stamp.sec), int(js.header.stamp.nanosec)
        fill_xyz(msg.com, e.com)
        fill_xyz(msg.com_velocity, e.com_velocity)
        fill_xyz(msg.cop, e.cop)
        fill_xyz(msg.capture_point, e.capture_point)
        fill_xyz(msg.angular_momentum, e.angular_momentum)
        msg.support_polygon = [xyz(p) for p in e.support_polygon]
        fill_xyz(msg.feet_center, e.feet_center)
        msg.lean_angle = float(e.lean_angle)
        msg.lean_direction = float(e.lean_direction)
        msg.normal_force = float(e.normal_force)
        msg.left_contact, msg.right_contact = bool(e.contacts["l"]), bool(e.contacts["r"])
        msg.cop_on_edge = e.cop_on_edge
        msg.left_normal_force = float(e.foot_normal_force["l"])
        msg.right_normal_force = float(e.foot_normal_force["r"])
        fill_xyz(msg.left_cop, e.foot_cop["l"])
        fill_xyz(msg.right_cop, e.foot_cop["r"])
        fill_xyz(msg.com_velocity_fused, e.com_velocity_fused)
        fill_xyz(msg.capture_point_fused, e.capture_point_fused)
        self.last_msg = encode(self.pub, msg)
        if self.first_answer.ready([self.pub]):  # the first waits for its readers (the recorder) to match
            self.pub.publish(self.last_msg)
        if t - self.last_viz >= self.viz_period - 1e-9:
            self.last_viz = t
            self._publish_viz(msg)

    def _publish_viz(self, msg) -> None:
        """``msg``: this tick's centroidal state (a namespace, see ``self.msg``) as real messages for RViz."""
        h = Header(frame_id=msg.header.frame_id, stamp=Time(sec=msg.header.stamp.sec, nanosec=msg.header.stamp.nanosec))
        com, cop, cp = to_point(msg.com), to_point(msg.cop), to_point(msg.capture_point)
        polygon = [to_point(p) for p in msg.support_polygon]
        for pub, p in ((self.pub_com, com), (self.pub_cop, cop), (self.pub_cp, cp)):
            pub.publish(PointStamped(header=h, point=p))
        poly = PolygonStamped(header=h)
        poly.polygon.points = [Point32(x=p.x, y=p.y, z=0.0) for p in polygon]
        self.pub_poly.publish(poly)
        arr = MarkerArray()
        colors = {"com": (0.1, 0.4, 1.0), "cop": (1.0, 0.2, 0.1), "capture_point": (0.1, 0.8, 0.2)}
        for i, (name, p) in enumerate((("com", com), ("cop", cop), ("capture_point", cp))):
            m = Marker(header=h, ns=name, id=i, type=Marker.SPHERE, action=Marker.ADD)
            m.pose.position = p
            m.pose.orientation.w = 1.0
            m.scale.x = m.scale.y = m.scale.z = 0.04
            m.color.r, m.color.g, m.color.b = colors[name]
            m.color.a = 1.0
            arr.markers.append(m)
        m = Marker(header=h, ns="support_polygon", id=3, type=Marker.LINE_STRIP, action=Marker.ADD)
        m.pose.orientation.w = 1.0
        m.scale.x = 0.01
        m.color.r, m.color.g, m.color.b, m.color.a = 1.0, 0.8, 0.0, 1.0
        m.points = polygon + polygon[:1]
        arr.markers.append(m)
        self.pub_markers.publish(arr)


def main(args=None) -> int:
    return run_node(StateEstimator, args)


if __name__ == "__main__":
    raise SystemExit(main())
