"""Safe-fall runs in process, on the suite's ``ClosedLoop`` (the shell of the fall experiments, not core).

What ``humfall up SCENARIO --controller none|stepping|stepping_inertia`` starts, in one
process and tick for tick the same (tested against real processes): the standing balance
(``locomotion``), the FTB as a monitor (``ftb_monitor``: ``ftb/status`` each tick, latched
``fall_event``) and, with a fall controller, ``SafeFallController`` (``safe_fall``) with the
launcher's ``inertia_shaping`` for the choice; every node's parameters from its declaration
plus the scenario's ``params.<node>``. The FTB also runs for ``none`` (in process only: it
commands nothing) so the uncontrolled runs have trigger and lead times.

The ground-truth metrics are ``sim.metrics.FallMetrics`` fed with the fall event, the
decision and the feet (``FallMetrics.update_feet``) each tick. Imports the simulator: this
module is for experiments (``sim.fall_sweep``, benchmarks, tests), not for nodes.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from humfall_ros.suite import CONTROLLERS, controllers_for  # noqa: F401 (CONTROLLERS: the kinds, for callers)


@dataclasses.dataclass
class FallRun:
    """One run's outcome.

    Attributes:
        metrics: ``FallMetrics.result()`` (ground truth, with the safe-fall facts).
        joint_positions: measured joint positions per tick (ticks x joints) [rad].
        active_sources: the mux's source per tick.
        decision: the controller's ``SafeFallDecision`` (None: no take-over).
        fall_event: the FTB's first ``FallEvent`` of the run, even if its recovery cleared it (None: no trigger).
        trace: per tick (t, CoM (3,), estimated CoP (3,), ground-truth CoP (3,) or None, FTB state) for plots.
        reasons: the controller's notes.
        search: the controller's ``StepDecision`` (every case's best candidate), for plots.
    """

    metrics: dict
    joint_positions: np.ndarray
    active_sources: list
    decision: object | None
    fall_event: object | None
    trace: list
    reasons: list
    search: object | None = None


def run(sc: dict, kind: str | None = None, noise=None, duration: float | None = None,
        stop_after_landing_s: float | None = 0.6, keep_trace: bool = False) -> FallRun:
    """Run a validated scenario with a fall controller ``kind`` (default: the scenario's ``controller``).

    Args:
        noise: sensor noise (default: the scenario's ``params.sim_bridge.noise_*``).
        duration: [s] (default: the scenario's).
        stop_after_landing_s: end this long after the trunk first lands (None: run the whole duration).
        keep_trace: keep the per-tick trace (plots).
    """
    from humfall_ros.sim.closed_loop import ClosedLoop
    from humfall_ros.sim.metrics import foot_state

    kind = kind or sc["controller"]
    ctrls, monitors = controllers_for(sc, kind)
    loop = ClosedLoop(sc, ctrls, monitors, noise=noise)
    ftb = monitors[0]
    safe = ctrls[1] if len(ctrls) > 1 else None
    m = loop.ground_truth.metrics
    trace = []
    first_event = None   # the run's fall event, kept when the FTB's recovery clears it later
    try:
        ticks = int(round((duration or sc["duration"]) * sc["sim"]["control_rate"]))
        for _ in range(ticks):
            obs = loop.step()
            w = loop.world
            cop, down, poses = foot_state(w)
            m.update_feet(w.time, cop, down, poses)
            if ftb.event is not None:
                m.note_fall_event(ftb.event.time)
                first_event = first_event or ftb.event
            if safe is not None and safe.decision is not None:
                m.note_decision(safe.decision)
            if keep_trace:
                q = w.pinocchio_configuration()
                trace.append((w.time, w.model.com(q), np.asarray(obs.state.cop, float).copy(), cop,
                              ftb.state.value, dict(down)))
            if stop_after_landing_s is not None and m.landing_time is not None \
                    and w.time > m.landing_time + stop_after_landing_s:
                break
        res = m.result()
    finally:
        loop.close()
    return FallRun(res, np.array(loop.joint_positions), list(loop.active_sources),
                   None if safe is None else safe.decision, first_event, trace,
                   [] if safe is None else list(safe.reasons), None if safe is None else safe.search_result)


def handback_run(sc: dict, kind: str = "stepping", duration: float | None = None,
                 walk_at: float | None = None, walk_speed: float = 1.0 / 3.6) -> dict:
    """One run through the hand-back (docs/safe_fall.md "The hand-back"), its figures as a JSON-ready dict.

    Ground truth (the world, not the estimator's odometry frame): the CoM and the soles (x, y, yaw) at the
    hand-back (the first tick locomotion drives after safe_fall), the middle of the two soles' corners then and
    at the end, the CoM speed over the last 0.5 s, the largest joint-target jump at the hand-back tick [rad],
    the trunk tilt at the end; times: the touchdown, the FTB's recovery (the event cleared), the hand-back.
    ``walk_at`` [s]: a walk command (``walk_speed`` [m/s], 2 steps) is given then (the stance test).
    """
    from humfall_ros.model.humanoid import SIDES
    from humfall_ros.sim.closed_loop import ClosedLoop

    ctrls, monitors = controllers_for(sc, kind)
    given = []
    cmd = (walk_speed, 0.0, 2)   # one object from walk_at on, as a latched topic's last message (acted on once)

    def walk(loop, obs):
        if walk_at is not None and obs.time >= walk_at - 1e-9:
            obs.inputs["cmd_walk"] = cmd
            if not given:
                given.append(obs.time)
    loop = ClosedLoop(sc, ctrls, monitors, inputs=walk)
    ftb, loco = monitors[0], ctrls[0]
    safe = ctrls[1].inner if len(ctrls) > 1 else None
    m = loop.model
    coms, targets, soles, recovered = [], [], [], None
    try:
        ticks = int(round((duration or sc["duration"]) * sc["sim"]["control_rate"]))
        for _ in range(ticks):
            obs = loop.step()
            st = loop.outputs[ftb.name][-1]
            if st.cleared is not None and recovered is None:
                recovered = obs.time
            w = loop.world
            q = w.pinocchio_configuration()
            coms.append(m.com(q))
            m.forward(q)
            feet = {}
            for sd in SIDES:
                M = m.frame_placement(m.sole_frame[sd])
                feet[sd] = [float(M.translation[0]), float(M.translation[1]),
                            math.atan2(M.rotation[1, 0], M.rotation[0, 0])]
            soles.append(feet)
            soles[-1]["mid"] = np.vstack([m.sole_corners(sd)[:, :2] for sd in SIDES]).mean(axis=0).tolist()
            targets.append(np.array(w.targets, float))
        res = loop.metrics()
        tilt = math.degrees(loop.world.trunk_tilt())
    finally:
        loop.close()
    act = loop.active_sources   # [k]: the source that drove the tick ending at observation k
    dt = 1.0 / sc["sim"]["control_rate"]
    hb = [k for k in range(1, len(act)) if act[k - 1] == "safe_fall" and act[k] == "locomotion"]
    C = np.array(coms)
    last = max(1, int(round(0.5 / dt)))
    out = {"kind": kind, "duration_s": round(len(act) * dt, 3), "fell": res.get("fell"),
           "min_target_distance_m": res.get("min_target_distance_m"),
           "fall_event_time_s": res.get("fall_event_time_s"),
           "touchdown_time_s": None if safe is None else safe.touchdown_at, "recovered_time_s": recovered,
           "handback_ticks": len(hb), "active_end": act[-1], "trunk_tilt_end_deg": round(tilt, 3),
           "com_speed_last_0.5s_max_m_s": float(np.max(np.linalg.norm(np.diff(C[-last:], axis=0), axis=1)) / dt),
           "com_end": C[-1].round(4).tolist(), "soles_end": soles[-1],
           "loco_messages": list(loco.messages), "walk_given_s": given[0] if given else None}
    if hb:
        k = hb[0]
        # the command of tick k-1 drove the world during tick k-1 -> k: targets[k-1] (applied at step k-1) is the
        # first locomotion command, targets[k-2] safe_fall's last one
        t_hb = (k - 1) * dt
        out.update({"handback_time_s": round(t_hb, 4),
                    "handback_after_touchdown_s": None if safe.touchdown_at is None
                    else round(t_hb - safe.touchdown_at, 4),
                    "handback_after_recovery_s": None if recovered is None else round(t_hb - recovered, 4),
                    "com_at_handback": C[k - 1].round(4).tolist(), "soles_at_handback": soles[k - 1],
                    "target_jump_at_handback_rad": float(np.max(np.abs(targets[k - 1] - targets[k - 2]))),
                    "com_move_after_handback_m": float(np.max(np.linalg.norm(C[k - 1:] - C[k - 1], axis=1))),
                    "com_over_soles_mid_end_m": float(np.hypot(*(C[-1][:2] - np.array(soles[-1]["mid"]))))})
    if safe is not None:
        out["handbacks"] = safe.handbacks
        out["reasons"] = list(safe.reasons)
    return out


def summary(r: FallRun) -> dict:
    """The acceptance figures of one run (JSON-ready)."""
    m = r.metrics
    out = {k: m.get(k) for k in ("fell", "fall_direction_deg", "avoidance_angle_deg", "avoidance_angle_p2_deg",
                                 "predicted_avoidance_deg", "predicted_avoidance_edge_deg", "predicted_captured",
                                 "captured", "decision_case", "decisions", "restep_times_s",
                                 "min_target_distance_m", "fall_event_time_s", "lead_time_s", "landing_time_s",
                                 "prediction", "measured_p2")}
    d = r.decision
    if d is not None:
        out["decision"] = {"case": d.case, "landing": np.asarray(d.landing).round(4).tolist(),
                           "p2": np.asarray(d.p2).round(4).tolist(), "q2": np.asarray(d.q2).round(4).tolist(),
                           "cells": d.cell_count, "search_ms": round(d.search_time * 1e3, 2),
                           "touchdown_time_s": d.touchdown_time, "control_duration_s": d.control_duration,
                           "case_alpha2_deg": {k: None if not math.isfinite(v) else round(math.degrees(v), 1)
                                               for k, v in d.case_alpha2.items()},
                           "reason": d.reason}
    if r.reasons:
        out["reasons"] = r.reasons
    return out


__all__ = ["CONTROLLERS", "FallRun", "controllers_for", "handback_run", "run", "summary"]


# python -m humfall_ros.sim.fall_runs handback SCENARIO KIND DURATION [walk_at=S] [KEY=VALUE ..]
if __name__ == "__main__":
    import json
    import sys

    from humfall_ros import scenario

    if len(sys.argv) < 5 or sys.argv[1] != "handback":
        raise SystemExit("usage: python -m humfall_ros.sim.fall_runs handback SCENARIO KIND DURATION [walk_at=S] "
                         "[KEY=VALUE ..]")
    extra = sys.argv[5:]
    walk_at = next((float(a.split("=", 1)[1]) for a in extra if a.startswith("walk_at=")), None)
    ov = [a for a in extra if not a.startswith("walk_at=")]
    sc_ = scenario.load(sys.argv[2], ov + [f"duration={sys.argv[4]}"])
    print(json.dumps(handback_run(sc_, sys.argv[3], walk_at=walk_at), default=float))
