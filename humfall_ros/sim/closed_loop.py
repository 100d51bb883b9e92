"""The suite's functional core in one process: world -> estimator -> standing balance.

The ROS graph runs the same pieces in separate processes; this loop is for
unit tests, benchmarks and quick experiments where DDS would only add time.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from humfall_ros.control.standing import StandingBalance
from humfall_ros.model.estimation import CentroidalEstimator, estimate_error
from humfall_ros.model.humanoid import SIDES
from humfall_ros.sim.metrics import FallMetrics
from humfall_ros.sim.world import STANDING_POSTURE, Box, SimWorld


@dataclasses.dataclass
class LoopResult:
    metrics: dict
    joint_positions: np.ndarray          # ticks x joints
    max_errors: dict                     # estimator vs ground truth, until trunk_tilt_limit
    max_trunk_tilt_deg: float


def run_scenario(sc: dict, duration: float | None = None, trunk_tilt_limit_deg: float = 30.0,
                 kp: float = 0.3, kd: float = 0.05) -> LoopResult:
    """Run a validated scenario dict (humfall_ros.scenario) without ROS."""
    s = sc["sim"]
    posture = {**STANDING_POSTURE, **sc["robot"]["initial_posture"]}
    world = SimWorld(s["physics_rate"], s["control_rate"], friction=s["friction"], initial_posture=posture)
    try:
        boxes = [Box(o["name"], tuple(o["position"]), tuple(o["size"]), o["yaw"], o["is_target"])
                 for o in sc["obstacles"]]
        world.set_obstacles(boxes)
        for p in sc["push"]:
            world.add_push(p["force"], p["point"], p["duration"], p["link"], start=p["time"])
        target = next((b for b in boxes if b.is_target), None)
        metrics = FallMetrics(None if target is None else target.position[:2])
        first_push = min((p["time"] for p in sc["push"]), default=0.0)
        est = CentroidalEstimator(world.model)
        truth = CentroidalEstimator(world.model)
        balance = StandingBalance(world.model, posture, kp, kd)
        errors: dict[str, float] = {}
        joints = []
        tilt_limit = np.radians(trunk_tilt_limit_deg)
        ticks = int(round((duration or sc["duration"]) * s["control_rate"]))
        for _ in range(ticks):
            qj, vj, _ = world.joint_states()
            joints.append(qj)
            orn, gyro, _ = world.imu()
            wrenches = {side: world.foot_wrench(side) for side in SIDES}
            e = est.update(world.time, qj, vj, orn, gyro, wrenches)
            tilt = world.trunk_tilt()
            if tilt < tilt_limit and world.time > 0.05:  # skip the first settling contact
                g = truth.update(world.time, qj, vj, orn, gyro, wrenches, base_truth=world.base_state())
                for k, v in estimate_error(e, g).items():
                    errors[k] = max(errors.get(k, 0.0), v)
            world.set_joint_targets(balance.command(e.com, e.com_velocity, e.support_polygon))
            world.step_control()
            if metrics.initial_cop is None and world.time >= first_push - 1e-9:
                metrics.set_reference_cop(world.ground_truth_cop())
            q, _ = world.pinocchio_state()
            metrics.update(world.time, world.model.com(q), world.trunk_tilt(), world.base_state()[0][2],
                           world.distance_to(target.name) if target else None, world.non_foot_contact())
        r = metrics.result()
        return LoopResult(r, np.array(joints), errors, r["max_trunk_tilt_deg"])
    finally:
        world.close()
