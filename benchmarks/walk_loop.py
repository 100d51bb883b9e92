"""An in-process walking loop (SimWorld + Sensors + CentroidalEstimator + LocomotionController) and its metrics.

Shared by benchmarks/bench_walking.py and test/test_walking_sim.py until the lead's
ClosedLoop runs contract controllers with walking inputs. Measured against ground truth.
"""
from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

from humfall_ros.control.contract import (
    Observation,
    centroidal_from_estimate,
    stamp_ns_of,
)
from humfall_ros.model.estimation import CentroidalEstimator, estimate_error
from humfall_ros.model.humanoid import SIDES, point_in_polygon_margin, support_polygon
from humfall_ros.sim.sensors import SensorNoise, Sensors
from humfall_ros.sim.world import SimWorld
from humfall_ros.walking.config import LocomotionConfig
from humfall_ros.walking.controller import LocomotionController


@dataclasses.dataclass
class WalkResult:
    fell: bool
    speed_kmh: float
    steps: int
    zmp_rms_ss: float            # m, ground-truth CoP vs reference in single support
    zmp_max_ss: float
    cop_margin_ok_fraction: float  # ticks with the true CoP >= 1 cm inside the stance polygon
    distance: float              # m, walked (ground-truth feet centre, start to end)
    planned_distance: float
    lateral_drift: float         # m, off the planned line
    heading_drift_deg: float
    max_slip: float              # m, largest stance-foot slide during one stance
    peak_speed_ratio: float      # max |joint velocity| / URDF limit
    peak_speed_joint: str
    est_com_err: float           # m, feet relative
    est_cp_err: float
    tick_ms_median: float
    tick_ms_p99: float
    sim_time: float
    messages: list

    def as_dict(self) -> dict:
        d = dataclasses.asdict(self)
        return {k: (round(v, 5) if isinstance(v, float) else v) for k, v in d.items()}


def run_walk(speed_kmh: float, steps: int = 20, yaw_rate_deg_s: float = 0.0, config: LocomotionConfig | None = None,
             noise: SensorNoise | None = None, stand_time: float = 0.5, max_time: float | None = None,
             trace: bool = False, on_tick=None) -> tuple[WalkResult, dict]:
    """Stand ``stand_time``, walk ``steps`` steps (start + stop included) and settle."""
    world = SimWorld(1000.0, 500.0)
    model = world.model
    try:
        sensors = Sensors(world, noise)
        est = CentroidalEstimator(model)
        truth_est = CentroidalEstimator(model)
        ctl = LocomotionController(model, config, dt=1.0 / world.control_rate)
        ctl.reset()
        cfg = ctl.cfg
        walk_time = cfg.crouch_duration + cfg.start_duration + (steps + 1) * cfg.step_period + cfg.stop_duration \
            + cfg.settle_duration
        total = max_time or (stand_time + walk_time + 1.0)
        speed = speed_kmh / 3.6
        zmp_err_ss, margin_ok, margin_n = [], 0, 0
        tick_times = []
        peak = np.zeros(model.njoints)
        est_com, est_cp = 0.0, 0.0
        fell = False
        started = False
        stance_anchor: dict = {}
        max_slip = 0.0
        tr = {k: [] for k in ("t", "cop", "zmp", "com", "com_ref", "support", "feet")} if trace else {}
        start_feet = None
        active = "none"
        while world.time < total:
            r = sensors.read()
            stamp = stamp_ns_of(world.time)
            e = est.update(stamp * 1e-9, r.joint_position, r.joint_velocity, r.imu_orientation, r.gyro, r.wrenches)
            obs = Observation(stamp, np.asarray(r.joint_position, float), np.asarray(r.joint_velocity, float),
                              centroidal_from_estimate(e), active, {})
            if not started and world.time >= stand_time:
                started = True
                reason = ctl.set_walk_command(speed, math.radians(yaw_rate_deg_s), n_steps=steps)
                if reason:
                    raise RuntimeError(reason)
                q_true = world.pinocchio_configuration()
                model.forward(q_true)
                start_feet = {s: model.frame_placement(model.sole_frame[s]).copy() for s in SIDES}
            if on_tick is not None:
                on_tick(world, ctl, obs)
            t0 = time.perf_counter()
            out = ctl.step(obs)
            tick_times.append(time.perf_counter() - t0)
            if out is not None:
                world.set_joint_targets(out.positions, out.velocities)
                active = ctl.source
            world.step_control()
            # ---- ground truth
            qj, vj, _ = world.joint_states()
            peak = np.maximum(peak, np.abs(vj))
            if world.trunk_tilt() > math.radians(30) or world.non_foot_contact():
                fell = True
                break
            st = ctl.state
            cop = world.ground_truth_cop()
            q_true = world.pinocchio_configuration()
            model.forward(q_true)
            if st.walking and cop is not None:
                if st.support != "double":
                    side = "l" if st.support == "single_left" else "r"
                    zmp_err_ss.append(np.linalg.norm(cop[:2] - st.zmp_ref[:2]))
                    poly = support_polygon(model.sole_corners(side)[:, :2])
                    pos = model.frame_placement(model.sole_frame[side]).translation.copy()
                    if side not in stance_anchor:
                        stance_anchor = {side: pos}
                    max_slip = max(max_slip, float(np.linalg.norm(pos[:2] - stance_anchor[side][:2])))
                else:
                    poly = support_polygon(np.vstack([model.sole_corners(s)[:, :2] for s in SIDES]))
                    stance_anchor = {}
                margin_n += 1
                margin_ok += point_in_polygon_margin(cop, poly) >= 0.01
                g = truth_est.update(world.time, qj, vj, r.imu_orientation, r.gyro, r.wrenches,
                                     base_truth=world.base_state())
                err = estimate_error(e, g)
                est_com = max(est_com, err["com_error_feet_relative"])
                est_cp = max(est_cp, err["capture_point_error_feet_relative"])
            if trace:
                tr["t"].append(world.time)
                tr["cop"].append(cop[:2] if cop is not None else [np.nan, np.nan])
                tr["zmp"].append(st.zmp_ref[:2].copy())
                tr["com"].append(model.com(q_true))
                tr["com_ref"].append(st.com_ref.copy())
                tr["support"].append(st.support if st.walking else "stand")
                tr["feet"].append([model.frame_placement(model.sole_frame[s]).translation.copy() for s in SIDES])
        q_true = world.pinocchio_configuration()
        model.forward(q_true)
        end_feet = {s: model.frame_placement(model.sole_frame[s]) for s in SIDES}
        c0 = 0.5 * (start_feet["l"].translation + start_feet["r"].translation) if start_feet else np.zeros(3)
        c1 = 0.5 * (end_feet["l"].translation + end_feet["r"].translation)
        d = c1 - c0
        planned = steps * speed * cfg.step_period
        yaw1 = math.atan2(end_feet["l"].rotation[1, 0] + end_feet["r"].rotation[1, 0],
                          end_feet["l"].rotation[0, 0] + end_feet["r"].rotation[0, 0])
        ratio = peak / model.limits.velocity
        j = int(np.argmax(ratio))
        ts = np.array(tick_times) * 1e3
        zr = np.array(zmp_err_ss) if zmp_err_ss else np.array([np.nan])
        res = WalkResult(fell, speed_kmh, steps, float(np.sqrt(np.mean(zr ** 2))), float(np.max(zr)),
                         margin_ok / max(margin_n, 1), float(np.hypot(d[0], d[1]) if yaw_rate_deg_s else d[0]),
                         planned, float(abs(d[1])) if not yaw_rate_deg_s else float("nan"),
                         math.degrees(yaw1) - (yaw_rate_deg_s * steps * cfg.step_period),
                         max_slip, float(ratio[j]), model.joint_names[j], est_com, est_cp,
                         float(np.median(ts)), float(np.percentile(ts, 99)), world.time, list(ctl.messages))
        return res, tr
    finally:
        world.close()


if __name__ == "__main__":
    import json
    import sys

    kmh = float(sys.argv[1]) if len(sys.argv) > 1 else 1.0
    n = int(sys.argv[2]) if len(sys.argv) > 2 else 4
    res, _ = run_walk(kmh, n)
    print(json.dumps(res.as_dict()))
