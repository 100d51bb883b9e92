"""ftb_monitor: the fall trigger boundary (paper 1 §II-B) as a per-tick node (not a command source).

Gathers the tick's ``centroidal_state`` (and ``walking/state`` with ``use_walking_state``,
``estop/status`` with ``use_estop_status``) in its own tick gate, runs ``fall.ftb.FtbMonitor``
(the same object the in-process loop runs as a monitor) and publishes

* ``ftb/status`` (``humfall_interfaces/FtbStatus``) every tick, stamped like the tick; from
  the trigger on it carries the latched fall event, so ``safe_fall_controller`` acts on the
  status of tick k (lockstep-repeatable) rather than on when ``fall_event`` arrives;
* ``fall_event`` (``humfall_interfaces/FallEvent``, transient-local) once, on the edge; and once
  more with ``cleared = true`` when the FTB recovers (falling/fallen -> balanced: a step captured the
  fall) or is reset: stamped with that tick, the cleared event's fields. Every reader of the topic
  treats a cleared message as "no fall event" (``controller_node.fall_event_input``): locomotion takes
  the robot back once the safe-fall controller releases it.

Service ``ftb/reset`` (std_srvs/Trigger): back to balanced, the event cleared (published). A
retransmitted tick is answered with the last status; time going back resets the monitor.
The message converters here are also what the fall controller's node uses to read them.
"""
from __future__ import annotations

import math

import numpy as np
from humfall_interfaces.msg import CentroidalState, FallEvent, FtbStatus
from std_srvs.srv import Trigger

from humfall_ros.control.contract import Observation
from humfall_ros.control.tick_gate import Action, TickGate
from humfall_ros.fall import ftb as core
from humfall_ros.nodes.common import (NO_PUB_EVENTS, QOS_LATCHED, QOS_TICK_WRITER, FirstAnswerHold, HotLoop, Params,
                                     encode,
                                     ros_stamp, run_node, stamp_key)
from humfall_ros.nodes.controller_node import centroidal_from_msg
from rclpy.node import Node

STATE_CODE = {core.FtbState.BALANCED: FtbStatus.BALANCED, core.FtbState.FALLING: FtbStatus.FALLING,
              core.FtbState.FALLEN: FtbStatus.FALLEN}
CODE_STATE = {v: k for k, v in STATE_CODE.items()}


def _fill(target, v) -> None:
    v = np.asarray(v, float).reshape(-1)
    target.x, target.y = float(v[0]), float(v[1])
    target.z = float(v[2]) if v.size > 2 else 0.0


def _vec(p, n: int = 3) -> np.ndarray:
    return np.array([p.x, p.y, p.z][:n])


def _stamp_of(ns: int, header) -> None:
    header.stamp.sec, header.stamp.nanosec = divmod(int(ns), 1_000_000_000)


def cleared_msg(ev: core.FallEvent, stamp_ns: int, reason: str) -> FallEvent:
    """The "cleared" message: ``ev``'s fields, ``cleared = true``, stamped ``stamp_ns`` (the recovery's tick)."""
    msg = event_to_msg(ev)
    _stamp_of(stamp_ns, msg.header)
    msg.reason = reason
    msg.cleared = True
    return msg


def event_to_msg(ev: core.FallEvent, msg: FallEvent | None = None) -> FallEvent:
    msg = msg or FallEvent()
    _stamp_of(ev.stamp_ns, msg.header)
    msg.cleared = False
    msg.header.frame_id = "odom"
    msg.reason = ev.reason
    msg.lean_angle = float(ev.lean_angle)
    _fill(msg.com, ev.com)
    _fill(msg.com_velocity, ev.com_velocity)
    _fill(msg.cop, ev.cop)
    _fill(msg.capture_point, ev.reference_point)
    msg.trigger_mode = ev.trigger_mode
    _fill(msg.leading_edge_start, ev.leading_edge_start)
    _fill(msg.leading_edge_end, ev.leading_edge_end)
    msg.leading_corner = bool(ev.leading_corner)
    msg.fall_direction = float(ev.fall_direction)
    msg.control_duration = float(ev.control_duration)
    msg.theta_threshold = float(ev.theta_threshold)
    msg.energy_ratio = float(ev.energy_ratio)
    msg.separatrix_margin = float(ev.separatrix_margin)
    msg.support_polygon = []
    for p in np.asarray(ev.support_polygon, float).reshape(-1, 2):
        pt = type(msg.cop)()
        _fill(pt, p)
        msg.support_polygon.append(pt)
    msg.walking = bool(ev.walking)
    return msg


def event_from_msg(msg: FallEvent) -> core.FallEvent:
    return core.FallEvent(
        stamp_key(msg.header.stamp), msg.trigger_mode, msg.reason, _vec(msg.leading_edge_start),
        _vec(msg.leading_edge_end), bool(msg.leading_corner), _vec(msg.cop), _vec(msg.capture_point),
        msg.fall_direction, msg.control_duration, msg.theta_threshold, msg.energy_ratio, msg.separatrix_margin,
        msg.lean_angle, _vec(msg.com), _vec(msg.com_velocity),
        np.array([[p.x, p.y] for p in msg.support_polygon], float).reshape(-1, 2), bool(msg.walking))


def status_to_msg(st: core.FtbStatus, msg: FtbStatus) -> FtbStatus:
    """Fill ``msg`` (reused each tick) from a status; the header stamp is the caller's."""
    f = st.features
    msg.state = STATE_CODE[st.state]
    msg.mode = st.mode
    msg.time_in_state = float(st.time_in_state)
    msg.reason = st.reason
    msg.event_tick = st.event is not None
    msg.has_fall_event = st.fall_event is not None
    if st.fall_event is not None:
        event_to_msg(st.fall_event, msg.fall_event)
    else:
        msg.fall_event = FallEvent()
    msg.valid = bool(f.valid)
    for name in ("energy_ratio", "separatrix_margin", "theta", "theta_dot", "pendulum_length", "lean_angle",
                 "capture_point_margin", "capture_point_error"):
        setattr(msg, name, float(getattr(f, name)))
    _fill(msg.leading_edge_start, f.edge_start)
    _fill(msg.leading_edge_end, f.edge_end)
    _fill(msg.edge_normal, f.edge_normal)
    msg.on_corner = bool(f.on_corner)
    return msg


def status_from_msg(msg: FtbStatus) -> core.FtbStatus:
    """The functional core's status (what the in-process loop hands the controllers)."""
    f = core.FtbFeatures(msg.energy_ratio, msg.separatrix_margin, msg.theta, msg.theta_dot, msg.pendulum_length,
                         msg.lean_angle, msg.capture_point_margin, msg.capture_point_error,
                         _vec(msg.leading_edge_start, 2), _vec(msg.leading_edge_end, 2), _vec(msg.edge_normal, 2),
                         bool(msg.on_corner), bool(msg.valid))
    ev = event_from_msg(msg.fall_event) if msg.has_fall_event else None
    return core.FtbStatus(stamp_key(msg.header.stamp), CODE_STATE[msg.state], msg.mode, f, msg.time_in_state,
                          msg.reason, ev if msg.event_tick else None, ev)


def GaitFromMsg(msg):  # noqa: N802 - kept name (was a class whose int(msg.support) raised on the string field)
    """``walking/state`` (WalkingState: ``support`` is the string "double" / "single_left" / "single_right")
    as ``fall.ftb.GaitReference`` (``core.gait_reference``)."""
    return core.gait_reference(msg)


class FtbMonitorNode(Node):
    def __init__(self):
        super().__init__("ftb_monitor")
        self.params = Params(self).declare_all()
        self.config = core.FtbConfig.from_params(self.params)
        self.monitor = core.FtbMonitor(self.config)
        self.pub_status = self.create_publisher(FtbStatus, "ftb/status", QOS_TICK_WRITER, event_callbacks=NO_PUB_EVENTS)
        self.pub_event = self.create_publisher(FallEvent, "fall_event", QOS_LATCHED)
        kinds = ({"centroidal_state"} | ({"walking/state"} if self.config.use_walking_state else set())
                 | ({"estop/status"} if self.config.use_estop_status else set()))
        self.gate = TickGate(kinds, trigger="centroidal_state")
        self.hot_loop = HotLoop(self, on_batch=self._on_batch, gathering=self.gate.gathering)
        self.hot_loop.subscribe(CentroidalState, "centroidal_state", lambda m: self._offer("centroidal_state", m),
                                decoded=True, trigger=True)
        if self.config.use_walking_state:
            from humfall_interfaces.msg import WalkingState

            self.hot_loop.subscribe(WalkingState, "walking/state", lambda m: self._offer("walking/state", m),
                                    decoded=True)
        if self.config.use_estop_status:
            from humfall_interfaces.msg import EstopStatus

            self.hot_loop.subscribe(EstopStatus, "estop/status", lambda m: self._offer("estop/status", m),
                                    decoded=True)
        self.create_service(Trigger, "ftb/reset", self._on_reset)
        self.msg = FtbStatus()
        self.msg.header.frame_id = "odom"
        self.last: bytes | None = None  # the last status as published (encoded: rclpy's conversion of FtbStatus was
        # the node's largest per-tick cost)
        self.first_answer = FirstAnswerHold(self)  # so that the bag gets tick 0's status too
        self.failures = 0
        self.get_logger().info(f"FTB mode {self.config.mode.value}; tick inputs {sorted(kinds)}")

    def _offer(self, kind: str, msg) -> None:
        action = self.gate.offer(kind, stamp_key(msg.header.stamp), msg)
        if action is Action.RETRANSMIT:
            if self.last is not None and self.first_answer.ready([self.pub_status]):
                self.pub_status.publish(self.last)
            return
        if action is Action.RESET:
            self.get_logger().info(f"sim time went back to {stamp_key(msg.header.stamp) * 1e-9:.3f} s: FTB reset")
            self.monitor.reset()
            self.last = None
        if not self.hot_loop.batching:
            self._on_batch()

    def _on_batch(self) -> None:
        tick = self.gate.poll()
        if tick is None:
            return
        cs = tick.inputs["centroidal_state"]
        try:
            inputs = {}
            if "walking/state" in tick.inputs:
                inputs["walking/state"] = GaitFromMsg(tick.inputs["walking/state"])
            if "estop/status" in tick.inputs:  # core.stop_reference reads the message's fields as they are
                inputs["estop/status"] = tick.inputs["estop/status"]
            obs = Observation(tick.stamp_ns, np.zeros(0), np.zeros(0), centroidal_from_msg(cs), "", inputs)
            st = self.monitor.step(obs)
            status_to_msg(st, self.msg)
        except Exception as e:  # noqa: BLE001 - a bad tick never kills the monitor; the status says invalid
            self.failures += 1
            self.get_logger().error(f"tick {tick.stamp_ns * 1e-9:.3f} s failed: {e!r}", throttle_duration_sec=1.0)
            self.msg.valid = False
            self.msg.event_tick = False
            self.msg.reason = f"tick failed: {e!r}"
            st = None
        self.msg.header.stamp = ros_stamp(cs.header.stamp)
        if st is not None and st.event is not None:
            self.pub_event.publish(event_to_msg(st.event))  # once, on the edge (latched)
            d = st.event.control_duration
            self.get_logger().info(f"fall event at {st.event.time:.3f} s: {st.event.reason}; control duration "
                                   f"{d:.3f} s" if math.isfinite(d) else "fall event: never reaches the threshold")
        if st is not None and st.cleared is not None:
            self.pub_event.publish(cleared_msg(st.cleared, tick.stamp_ns, st.reason))  # latched: the event is over
            self.get_logger().info(f"fall event of {st.cleared.time:.3f} s cleared at {tick.stamp_ns * 1e-9:.3f} s: "
                                   f"{st.reason}")
        self.last = encode(self.pub_status, self.msg)
        if self.first_answer.ready([self.pub_status]):  # the first waits for its readers (the recorder) to match
            self.pub_status.publish(self.last)

    def _on_reset(self, request, response):
        before = self.monitor.state.value
        ev, last = self.monitor.event, self.monitor.last_stamp
        self.monitor.reset()
        if ev is not None:
            self.pub_event.publish(cleared_msg(ev, last if last is not None else ev.stamp_ns, "ftb/reset"))
        response.success = True
        response.message = f"FTB reset ({before} -> balanced)"
        self.get_logger().info(response.message)
        return response


def main(args=None) -> int:
    return run_node(FtbMonitorNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
