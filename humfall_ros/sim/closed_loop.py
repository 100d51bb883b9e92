"""The suite's functional core in one process: world -> estimator -> standing balance.

The ROS graph runs the same pieces in separate processes; this loop is for
unit tests, benchmarks and quick experiments where DDS would only add time.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from humfall_ros.control.standing import StandingBalance
from humfall_ros.model.estimation import CentroidalEstimator, estimate_error
from humfall_ros.sim.ground_truth import GroundTruth
from humfall_ros.sim.sensors import SensorNoise, Sensors
from humfall_ros.sim.world import STANDING_POSTURE, SimWorld


@dataclasses.dataclass
class LoopResult:
    metrics: dict
    joint_positions: np.ndarray          # ticks x joints
    max_errors: dict                     # estimator vs ground truth, until trunk_tilt_limit
    max_trunk_tilt_deg: float


def run_scenario(sc: dict, duration: float | None = None, trunk_tilt_limit_deg: float = 30.0,
                 kp: float = 0.3, kd: float = 0.05, noise: SensorNoise | None = None) -> LoopResult:
    """Run a validated scenario dict (humfall_ros.scenario) without ROS, with optional sensor noise."""
    s = sc["sim"]
    posture = {**STANDING_POSTURE, **sc["robot"]["initial_posture"]}
    world = SimWorld(s["physics_rate"], s["control_rate"], friction=s["friction"], initial_posture=posture)
    try:
        ground_truth = GroundTruth(world, sc)
        sensors = Sensors(world, noise)
        est = CentroidalEstimator(world.model)
        truth = CentroidalEstimator(world.model)
        balance = StandingBalance(world.model, posture, kp, kd)
        errors: dict[str, float] = {}
        joints = []
        tilt_limit = np.radians(trunk_tilt_limit_deg)
        ticks = int(round((duration or sc["duration"]) * s["control_rate"]))
        for _ in range(ticks):
            r = sensors.read()
            joints.append(r.joint_position)
            e = est.update(world.time, r.joint_position, r.joint_velocity, r.imu_orientation, r.gyro, r.wrenches)
            tilt = world.trunk_tilt()
            if tilt < tilt_limit and world.time > 0.05:  # skip the first settling contact
                # the truth: exact joints and base, the same wrenches (they only pick the contacts)
                qj, vj, _ = world.joint_states()
                g = truth.update(world.time, qj, vj, r.imu_orientation, r.gyro, r.wrenches,
                                 base_truth=world.base_state())
                for k, v in estimate_error(e, g).items():
                    errors[k] = max(errors.get(k, 0.0), v)
            world.set_joint_targets(balance.command(e.com, e.com_velocity, e.support_polygon, e.feet_center))
            world.step_control()
            ground_truth.track()
        r = ground_truth.metrics.result()
        return LoopResult(r, np.array(joints), errors, r["max_trunk_tilt_deg"])
    finally:
        world.close()
