"""Safe fall in one process: world -> sensors -> estimator -> standing balance | FTB -> safe-fall controller.

The acceptance experiments of issue 11 that need the simulator (the FTB's 0.9x / 1.1x pushes in 8
directions and quiet standing; ``standing_push`` with none / stepping / stepping + inertia shaping;
prediction against outcome). Until ``sim/closed_loop.py`` runs any list of controllers through the
mux, this loop does the hand-over itself: the standing balance drives until the FTB fires, then the
safe-fall controller (which never releases).

    .venv/bin/python benchmarks/fall_closed_loop.py ftb        # FTB sweep (JSON)
    .venv/bin/python benchmarks/fall_closed_loop.py push       # standing_push, three controllers (JSON)
"""
from __future__ import annotations

import dataclasses
import json
import math
import pathlib
import sys
import time

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from humfall_ros import params, scenario
from humfall_ros.control.contract import Observation, centroidal_from_estimate, stamp_ns_of
from humfall_ros.control.standing import StandingBalance
from humfall_ros.fall.ftb import FtbConfig, FtbMonitor
from humfall_ros.model.estimation import CentroidalEstimator
from humfall_ros.sim.ground_truth import GroundTruth
from humfall_ros.sim.sensors import SensorNoise, Sensors
from humfall_ros.sim.world import STANDING_POSTURE, SimWorld

# DESIGN.md "Measured facts": fall thresholds by push direction (mid-points of the bisection brackets) [N].
# Push angle convention of those figures: clockwise from +x (90 deg pushes to the right, -y).
THRESHOLDS = {0: 258.5, 30: 291.5, 60: 367.5, 90: 313.5, 120: 367.5, 150: 247.5, 180: 214.5, 270: 313.5}


def push_force(magnitude: float, angle_deg: float) -> list[float]:
    a = math.radians(angle_deg)
    return [magnitude * math.cos(a), -magnitude * math.sin(a), 0.0]


@dataclasses.dataclass
class LoopRecord:
    metrics: dict
    fall_event: object | None
    statuses: list
    decisions: list
    trace: list               # per tick: time, com, cop, ground-truth cop, contacts
    controller_info: dict


def run(sc: dict, controller=None, ftb_config: FtbConfig | None = None, duration: float | None = None,
        noise: SensorNoise | None = None, keep_statuses: bool = False, stop_after_fall_s: float = 0.6,
        on_tick=None) -> LoopRecord:
    """Run a scenario dict in process; ``controller`` (a contract controller or None) takes over on fall_event."""
    s = sc["sim"]
    posture = {**STANDING_POSTURE, **sc["robot"]["initial_posture"]}
    world = SimWorld(s["physics_rate"], s["control_rate"], friction=s["friction"], initial_posture=posture)
    try:
        gt = GroundTruth(world, sc)
        sensors = Sensors(world, noise)
        est = CentroidalEstimator(world.model)
        balance = StandingBalance(world.model, posture, *_balance_gains())
        ftb = FtbMonitor(ftb_config or FtbConfig.from_params(params.defaults("ftb_monitor")))
        if controller is not None:
            controller.reset()
        push_end = max((p["time"] + p["duration"] for p in sc["push"]), default=None)
        obstacles = [{"name": o["name"], "position": list(o["position"]), "size": list(o["size"]), "yaw": o["yaw"],
                          "is_target": o["is_target"]} for o in sc["obstacles"]]
        inputs: dict = {"obstacles": obstacles}
        if push_end is not None:
            inputs["push_end_time"] = push_end
        statuses, decisions, trace = [], [], []
        event = None
        active = "locomotion"
        ticks = round((duration or sc["duration"]) * s["control_rate"])
        for _ in range(ticks):
            r = sensors.read()
            e = est.update(world.time, r.joint_position, r.joint_velocity, r.imu_orientation, r.gyro, r.wrenches)
            inputs["imu"] = (np.asarray(r.imu_orientation, float), np.asarray(r.gyro, float))
            obs = Observation(stamp_ns_of(world.time), r.joint_position, r.joint_velocity,
                              centroidal_from_estimate(e), active, inputs)
            st = ftb.step(obs)
            if keep_statuses:
                statuses.append(st)
            if st.event is not None and event is None:
                event = st.event
                inputs["fall_event"] = event
            cmd = controller.step(obs) if controller is not None else None
            if cmd is not None:
                active = controller.source
                world.set_joint_targets(cmd.positions, cmd.velocities)
                d = getattr(controller, "decision", None)
                if d is not None and (not decisions or decisions[-1] is not d):
                    decisions.append(d)
            else:
                active = "locomotion"
                world.set_joint_targets(balance.command(e.com, e.com_velocity, e.support_polygon, e.feet_center))
            trace.append((world.time, e.com.copy(), e.cop.copy(), world.ground_truth_cop(), dict(e.contacts),
                          st.state.value))
            if on_tick is not None:
                on_tick(world, obs, st)
            world.step_control()
            gt.track()
            m = gt.metrics
            if m.landing_time is not None and world.time > m.landing_time + stop_after_fall_s:
                break
        res = gt.metrics.result()
        res["fall_event_time_s"] = None if event is None else event.time
        res["lead_time_s"] = None if event is None or gt.metrics.landing_time is None else \
            gt.metrics.landing_time - event.time
        res["ftb_final_state"] = ftb.state.value
        info = controller.info() if controller is not None and hasattr(controller, "info") else {}
        return LoopRecord(res, event, statuses, decisions, trace, info)
    finally:
        world.close()


def _balance_gains() -> tuple[float, float]:
    d = params.defaults("locomotion")
    return d.get("ankle_kp", 0.3), d.get("ankle_kd", 0.05)


def ftb_sweep(duration: float = 2.5) -> dict:
    """No trigger at 0.9x, a trigger at 1.1x the per-direction threshold; lead times."""
    rows = []
    for angle, thr in THRESHOLDS.items():
        for factor in (0.9, 1.1):
            sc = scenario.load("standing_push")
            sc["push"][0]["force"] = push_force(factor * thr, angle)
            rec = run(sc, duration=duration)
            m = rec.metrics
            rows.append({"angle_deg": angle, "factor": factor, "force_n": round(factor * thr, 1), "fell": m["fell"],
                         "triggered": rec.fall_event is not None,
                         "trigger_time_s": None if rec.fall_event is None else round(rec.fall_event.time, 3),
                         "landing_time_s": m["landing_time_s"], "lead_time_s": m["lead_time_s"],
                         "reason": None if rec.fall_event is None else rec.fall_event.reason})
    ok_low = all(not r["triggered"] for r in rows if r["factor"] == 0.9)
    ok_high = all(r["triggered"] for r in rows if r["factor"] == 1.1)
    return {"rows": rows, "no_trigger_at_0.9": ok_low, "trigger_at_1.1": ok_high}


def quiet(duration: float = 60.0, noise: SensorNoise | None = None) -> dict:
    sc = scenario.load("standing_quiet")
    t0 = time.perf_counter()
    rec = run(sc, duration=duration, noise=noise)
    return {"duration_s": duration, "noise": noise is not None, "triggered": rec.fall_event is not None,
            "ftb_final_state": rec.metrics["ftb_final_state"], "wall_s": round(time.perf_counter() - t0, 1)}


class Outcome:
    """Ground-truth facts of a controlled run the metrics module lacks: touchdown, landing pose, alpha2."""

    def __init__(self):
        self.swing = None
        self.lifted = False
        self.touchdown_time = None
        self.landing_pose = None
        self.cops_after = []
        self.touchdown_tilt_deg = None

    def __call__(self, world, obs, st, controller):
        import pinocchio as pin

        from humfall_ros.fall.stepping_zone import sole_pose_2d

        side = getattr(controller, "swing_side", None)
        if side is None or controller.decision is None or controller.chosen.landing is None:
            return
        self.swing = side
        link = world.foot_links[side]
        touching = any(cp[3] == link for cp in world.ground_contacts())
        if not touching:
            self.lifted = True
        elif self.lifted and self.touchdown_time is None:
            self.touchdown_time = world.time
            m = world.model
            m.forward(world.pinocchio_configuration())
            M = m.frame_placement(m.sole_frame[side])
            self.landing_pose = sole_pose_2d(M)
            self.touchdown_tilt_deg = math.degrees(float(np.linalg.norm(pin.log3(
                pin.rpy.rpyToMatrix(0, 0, self.landing_pose[2]).T @ M.rotation))))
        if self.touchdown_time is not None and self.touchdown_time + 0.05 <= world.time <= self.touchdown_time + 0.15:
            c = world.ground_truth_cop()
            if c is not None:
                self.cops_after.append(c[:2])


def standing_push(kind: str, push_scale: float = 1.0, noise: SensorNoise | None = None, duration: float = 3.0,
                  ftb_mode: str = "ftb") -> dict:
    """standing_push with controller none / stepping / stepping_inertia; metrics and prediction vs outcome."""
    from humfall_ros.fall.controller import SafeFallConfig, SafeFallController
    from humfall_ros.sim.metrics import avoidance_angle_deg

    sc = scenario.load("standing_push")
    sc["push"][0]["force"] = [f * push_scale for f in sc["push"][0]["force"]]
    ctrl = None
    if kind != "none":
        d = params.defaults("safe_fall_controller")
        d["inertia_shaping"] = kind == "stepping_inertia"
        ctrl = SafeFallController(config=SafeFallConfig.from_params(d))
    out = Outcome()
    fcfg = params.defaults("ftb_monitor")
    fcfg["mode"] = ftb_mode
    t0 = time.perf_counter()
    rec = run(sc, ctrl, FtbConfig.from_params(fcfg), duration=duration, noise=noise,
              on_tick=(lambda w, o, st: out(w, o, st, ctrl)) if ctrl else None)
    m = dict(rec.metrics)
    m["wall_s"] = round(time.perf_counter() - t0, 1)
    target = np.array(sc["obstacles"][0]["position"][:2])
    if ctrl is not None and ctrl.decision is not None:
        d = ctrl.decision
        m["decision"] = {"case": d.case, "alpha1_deg": math.degrees(d.alpha1),
                         "predicted_avoidance_deg": None if not math.isfinite(d.alpha2) else math.degrees(d.alpha2),
                         "captured": d.captured, "p1": d.p1.tolist(), "q1": d.q1.tolist(), "p2": d.p2.tolist(),
                         "q2": d.q2.tolist(), "landing": d.landing.tolist(), "control_duration_s": d.control_duration,
                         "touchdown_time_s": d.touchdown_time, "zone_half_extent": d.zone_half_extent.tolist(),
                         "zone_size_m": d.zone_size.tolist(), "gamma": d.gamma.tolist(), "cells": d.cell_count,
                         "search_ms": d.search_time * 1e3, "ik_reachable": d.ik_reachable, "reason": d.reason,
                         "case_alpha2_deg": {k: (None if not math.isfinite(v) else math.degrees(v))
                                             for k, v in d.case_alpha2.items()}}
        m["predicted_avoidance_deg"] = m["decision"]["predicted_avoidance_deg"]
        m["captured"] = d.captured
        pred_td = ctrl.predicted_touchdown_time
        m["outcome"] = {"touchdown_time_s": out.touchdown_time, "predicted_touchdown_s": pred_td,
                        "touchdown_error_s": None if out.touchdown_time is None else out.touchdown_time - pred_td,
                        "landing_pose": None if out.landing_pose is None else out.landing_pose.tolist(),
                        "landing_tilt_deg": out.touchdown_tilt_deg}
        if out.landing_pose is not None and np.all(np.isfinite(d.landing)):
            m["outcome"]["landing_error_m"] = float(np.linalg.norm(out.landing_pose[:2] - d.landing[:2]))
            m["outcome"]["landing_yaw_error_deg"] = math.degrees(abs(out.landing_pose[2] - d.landing[2]))
        if out.cops_after and m.get("landing_com") is not None:
            p2 = np.mean(out.cops_after, axis=0)
            m["measured_p2"] = p2.tolist()
            m["avoidance_angle_p2_deg"] = avoidance_angle_deg(p2, m["landing_com"], target)
        m["reasons"] = ctrl.reasons
    return m


def main(argv: list[str]) -> None:
    what = argv[0] if argv else "ftb"
    if what == "ftb":
        out = ftb_sweep()
    elif what == "quiet":
        from humfall_ros.sim.sensors import TYPICAL_NOISE

        out = {"exact": quiet(), "typical_noise": quiet(noise=TYPICAL_NOISE)}
    elif what == "push":
        scale = float(argv[1]) if len(argv) > 1 else 1.0
        kinds = argv[2].split(",") if len(argv) > 2 else ["none", "stepping", "stepping_inertia"]
        out = {k: standing_push(k, scale) for k in kinds}
    else:
        raise SystemExit(f"unknown experiment {what!r}")
    print(json.dumps(out, default=str))


if __name__ == "__main__":
    main(sys.argv[1:])
