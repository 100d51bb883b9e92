"""safe_fall_controller: paper 1's protective step and inertia shaping as a lockstep command source.

A ``ControllerNode`` (humfall_ros/nodes/controller_node.py) running
``fall.controller.SafeFallController`` as source ``safe_fall``. Its tick waits for
``centroidal_state``, ``joint_states``, ``mux/state``, ``ftb/status`` and ``imu`` of the
same stamp (and reads the latest ``walking/state``: the planned footstep while walking); it takes
over on the fall event that ``ftb/status`` of that tick carries (not
on the arrival of the latched ``fall_event``: lockstep runs stay repeatable) and keeps the robot
until it is balanced again: after a captured step, once ``ftb/status`` says balanced with the
event cleared (the FTB's ``recovered`` transition) for ``handback_delay_s``, it releases (an
empty command) and the mux hands the robot back to locomotion, which has seen the cleared
``fall_event`` by then and stands where the feet are. Targets come from the latched ``obstacles``
topic. The decision is published once (per take-over) on ``safe_fall/decision``
(``humfall_interfaces/SafeFallDecision``, transient-local).
Parameters: ``config/safe_fall_controller.yaml`` (``inertia_shaping`` is set by the launcher
from ``--controller stepping|stepping_inertia``).
"""
from __future__ import annotations

import math

import numpy as np
from humfall_interfaces.msg import FtbStatus, SafeFallDecision, WalkingState

from humfall_ros.fall.controller import SafeFallConfig, SafeFallController
from humfall_ros.nodes.common import QOS_LATCHED, QOS_RELIABLE, run_node
from humfall_ros.nodes.controller_node import IMU, OBSTACLES, ControllerNode, Input
from humfall_ros.nodes.ftb_monitor import status_from_msg

FTB_STATUS = Input("ftb/status", FtbStatus, "ftb/status", status_from_msg, per_tick=True)
# the latest walking/state (not waited for): the controller keeps the last walking one for the planned
# footstep of a single-support take-over (fall.controller.planned_landing_of reads the message)
WALKING_STATE = Input("walking/state", WalkingState, "walking/state", lambda msg: msg, qos=QOS_RELIABLE)


def make_controller(p: dict, model) -> SafeFallController:
    return SafeFallController(model, SafeFallConfig.from_params(p))


def _point(target, v) -> None:
    v = np.asarray(v, float).reshape(-1)
    target.x, target.y = float(v[0]), float(v[1])
    target.z = float(v[2]) if v.size > 2 else 0.0


def decision_to_msg(d, fall_event_stamp_ns: int | None) -> SafeFallDecision:
    """``fall.controller.SafeFallDecision`` -> the message (NaN where a value does not apply)."""
    m = SafeFallDecision()
    m.header.frame_id = "odom"
    m.header.stamp.sec, m.header.stamp.nanosec = divmod(int(d.stamp_ns), 1_000_000_000)
    if fall_event_stamp_ns is not None:
        m.fall_event_stamp.sec, m.fall_event_stamp.nanosec = divmod(int(fall_event_stamp_ns), 1_000_000_000)
    m.step_case, m.swing_side = d.case, d.swing_side
    for name in ("p1", "q1", "p2", "q2", "target"):
        _point(getattr(m, name), getattr(d, name))
    m.alpha1, m.alpha2, m.captured = float(d.alpha1), float(d.alpha2), bool(d.captured)
    m.control_duration, m.touchdown_time = float(d.control_duration), float(d.touchdown_time)
    m.theta_threshold = float(d.theta_threshold)
    m.landing = np.asarray(d.landing, float).reshape(3)
    m.zone_half_extent = np.asarray(d.zone_half_extent, float).reshape(3)
    m.zone_size = np.asarray(d.zone_size, float).reshape(2)
    m.gamma = np.asarray(d.gamma, float).reshape(3)
    m.cell_count = int(d.cell_count)
    m.search_time = float(d.search_time)
    m.ik_reachable = bool(d.ik_reachable)
    m.case_names = list(d.case_alpha2)
    m.case_alpha2 = [float(v) for v in d.case_alpha2.values()]
    m.reason = d.reason
    m.step_index = int(getattr(d, "step_index", 1))
    return m


class SafeFallControllerNode(ControllerNode):
    def __init__(self):
        super().__init__("safe_fall_controller", make_controller, inputs=[FTB_STATUS, IMU, OBSTACLES, WALKING_STATE])
        self.pub_decision = self.create_publisher(SafeFallDecision, "safe_fall/decision", QOS_LATCHED)
        self._published = None

    def after_step(self, observation, targets) -> None:
        d = self.controller.decision
        if d is None or d is self._published:
            return
        ev = observation.inputs.get("ftb/status")
        ev = getattr(ev, "fall_event", None)
        self.pub_decision.publish(decision_to_msg(d, None if ev is None else ev.stamp_ns))
        self._published = d
        a2 = "capture" if d.captured else (f"{math.degrees(d.alpha2):.1f} deg" if math.isfinite(d.alpha2) else "n/a")
        self.get_logger().info(f"decision at {d.stamp_ns * 1e-9:.3f} s: {d.case} (predicted alpha2 {a2}), "
                               f"{d.cell_count} cells in {d.search_time * 1e3:.1f} ms"
                               + (f"; {d.reason}" if d.reason else ""))


def main(args=None) -> int:
    return run_node(SafeFallControllerNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
