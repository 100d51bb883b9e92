"""Issue 12's e-stop trials in process: ClosedLoop(walking_estop) with the walking controller and the e-stop.

``run_trial(speed_kmh, phase)`` walks the scenario ``walking_estop`` at that speed and triggers the e-stop at
``estop.at = {step: 5, phase}`` (phases: ds_start, ds_mid, ss_start = ss at 0.1, ss_mid = 0.5, ss_end = 0.95),
then records, per tick, the estimator's CoG / CoP (what ``centroidal_state`` carries), walking's references
and the e-stop's status. ``metrics`` is result.json's ``estop`` section (humfall_ros.estop.metrics) plus the
acceptance figures; ``trace`` feeds humfall_ros.estop.plots.

The e-stop reads ``walking/state`` of the same tick (the node waits for it per tick): in process the
``WithInputs`` adapter puts the walking controller's ``state`` into the e-stop's observation after walking has
stepped (controllers step in list order). The walking controller yields when ``observation.active_source``
shows the e-stop drove the robot (the mux's take-over), as it would over ROS.

Run: ``python benchmarks/estop_trials.py [SPEED_KMH ...] [--phases ds_start,...] [--json out.json]``
(one JSON object per trial on stdout; the full table with ``--json``).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import pathlib
import sys
import time

import numpy as np
import pinocchio as pin

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))   # the source tree, not an installed copy

from humfall_ros import scenario  # noqa: E402
from humfall_ros.control.contract import Observation
from humfall_ros.estop.config import EstopConfig, trigger_params
from humfall_ros.estop.controller import EstopController
from humfall_ros.estop.frame import FootPose, PlanarMotion
from humfall_ros.estop.metrics import estop_result
from humfall_ros.estop.statespace import fit_zmp_lag
from humfall_ros.model.humanoid import point_in_polygon_margin
from humfall_ros.sim.closed_loop import ClosedLoop
from humfall_ros.suite import node_params
from humfall_ros.walking.controller import LocomotionController
from humfall_ros.walking.scenario import walk_schedule, walking_config

PHASES = ("ds_start", "ds_mid", "ss_start", "ss_mid", "ss_end")
SPEEDS = (0.5, 1.0, 1.35, 1.8, 2.5)


class WithInputs:
    """A contract controller whose observation gets further inputs from callables at its step.

    ``WithInputs(estop, {"walking/state": lambda: walking.state})`` gives the e-stop walking's state of
    the same tick (walking steps first in the ClosedLoop's list), as the node's per-tick subscription does.
    """

    def __init__(self, controller, providers: dict):
        self.inner = controller
        self.source = controller.source
        self.providers = dict(providers)

    def reset(self) -> None:
        self.inner.reset()

    def step(self, observation: Observation):
        extra = {k: f() for k, f in self.providers.items()}
        return self.inner.step(dataclasses.replace(observation, inputs={**observation.inputs, **extra}))


@dataclasses.dataclass
class Trial:
    speed_kmh: float
    phase: str
    metrics: dict
    trace: dict
    plan: object | None
    messages: list


def estop_config(sc: dict, **overrides) -> EstopConfig:
    """The e-stop's settings of scenario ``sc``: declared defaults, ``params.estop_planner``, the trigger."""
    p = node_params(sc, "estop_planner")
    p.update(trigger_params(sc["estop"]))
    p.update(overrides)
    return EstopConfig.from_params(p)


def run_trial(speed_kmh: float, phase: str = "ds_start", step: int = 5, after: float | None = None,
              overrides: list[str] | None = None, on_tick=None, **estop_overrides) -> Trial:
    """One trial (module docstring). ``after`` [s]: how long to run past the stop's start (default 4 s, 10 s
    with the feet step of the return home, ``align_feet``); ``on_tick(loop, obs, estop)`` is called after each
    tick (extra measurements). The stop's figures end where the feet step starts (``align_start_time``); the
    step's own are ``align_*`` (:func:`align_figures`)."""
    sc = scenario.load("walking_estop", [f"walk.speed_kmh={speed_kmh}", f"estop.at.step={step}",
                                         f"estop.at.phase={phase}", *(overrides or [])])
    loop = ClosedLoop(sc, controllers=[])
    model = loop.model
    dt = 1.0 / sc["sim"]["control_rate"]
    walk = LocomotionController(model, walking_config(sc), dt)
    estop = EstopController(model, estop_config(sc, **estop_overrides), dt)
    if after is None:
        after = 10.0 if estop.cfg.align_feet else 4.0
    from humfall_ros.control.mux import CommandMux, mux_order

    loop.controllers = [walk, WithInputs(estop, {"walking/state": lambda: walk.state})]
    loop.mux = CommandMux(mux_order([c.source for c in loop.controllers]), model.joint_names, loop.mux.timeout)
    for c in loop.controllers:
        c.reset()
    schedule = walk_schedule(sc)
    cmd = [(t, (c.speed, c.yaw_rate, c.n_steps)) for t, c in schedule]

    def inputs(_loop, obs: Observation) -> None:
        for t, c in cmd:
            if obs.time >= t - 1e-9:
                obs.inputs["cmd_walk"] = c    # the same object every tick: acted on once

    loop.inputs = inputs
    tr = {k: [] for k in ("t", "com", "com_velocity", "cop", "margin", "zmp_ref", "com_ref", "support", "state",
                          "estop_com_ref", "estop_zmp_ref", "active", "cop_truth", "walking",
                          "angular_momentum", "com_truth", "sole_truth", "corners_truth", "yaw_truth",
                          "contacts")}
    data = model.model.createData()
    walk_refused = None
    fell, fell_at, t_fell = False, None, math.inf
    t_end = sc["duration"]
    wall0 = time.perf_counter()
    try:
        while loop.world.time < t_end:
            obs = loop.step()
            if on_tick is not None:
                on_tick(loop, obs, estop)
            st = obs.state
            ws = walk.state
            es = estop.status
            tr["t"].append(obs.time)
            tr["com"].append(st.com.copy())
            tr["com_velocity"].append(st.com_velocity.copy())
            tr["angular_momentum"].append(np.asarray(st.angular_momentum, float).copy())
            tr["cop"].append(st.cop.copy())
            tr["margin"].append(point_in_polygon_margin(st.cop, st.support_polygon) if len(st.support_polygon) >= 3
                                else -math.inf)
            tr["zmp_ref"].append(np.asarray(ws.zmp_ref, float).copy())
            tr["com_ref"].append(np.asarray(ws.com_ref, float).copy())
            tr["support"].append(ws.support if ws.walking else "stand")
            tr["walking"].append(bool(ws.walking))
            tr["state"].append(es.state)
            tr["estop_com_ref"].append(np.array(es.com_ref))
            tr["estop_zmp_ref"].append(np.array(es.zmp_ref))
            tr["active"].append(loop.active)
            cop_truth = loop.world.ground_truth_cop()      # the tick's mean over its physics substeps
            tr["cop_truth"].append(np.full(3, np.nan) if cop_truth is None else cop_truth)
            q_true = loop.world.pinocchio_configuration()
            tr["com_truth"].append(pin.centerOfMass(model.model, data, q_true).copy())
            pin.updateFramePlacements(model.model, data)
            fp = {f: FootPose(data.oMf[model.frame_ids[model.foot_link[f]]].translation.copy(),
                              data.oMf[model.frame_ids[model.foot_link[f]]].rotation.copy()) for f in ("l", "r")}
            tr["sole_truth"].append(np.array([fp[f].sole_center(model, f)[:2] for f in ("l", "r")]))
            tr["corners_truth"].append(np.array([fp[f].sole_corners(model, f) for f in ("l", "r")]))
            tr["yaw_truth"].append(np.array([math.atan2(fp[f].rotation[1, 0], fp[f].rotation[0, 0])
                                             for f in ("l", "r")]))
            tr["contacts"].append(np.array([bool(st.left_contact), bool(st.right_contact)]))
            if walk_refused is None and any("refused" in m for m in walk.messages):
                walk_refused = next(m for m in walk.messages if "refused" in m)
                break
            if not fell and loop.ground_truth.metrics.result()["fell"]:
                fell, fell_at = True, obs.time
                t_fell = loop.world.time + 0.2
            if math.isfinite(estop.status.start_time):      # past the scenario's duration if need be
                t_end = estop.status.start_time + after
            if fell:
                t_end = min(t_end, t_fell)
    finally:
        metrics_gt = loop.ground_truth.metrics.result()
        loop.close()
    wall = time.perf_counter() - wall0
    full = {k: np.array(v) for k, v in tr.items()}
    fell = fell or bool(metrics_gt["fell"])
    a0 = float(estop.status.align_start_time)
    trace = full if not math.isfinite(a0) else {k: v[full["t"] < a0] for k, v in full.items()}
    plan = estop.plan
    s = estop.status
    m = {"speed_kmh": speed_kmh, "phase": phase, "walk_refused": walk_refused, "wall_s": round(wall, 1),
         "state": s.state, "fallback": s.fallback, "reason": s.reason, "crouch": s.crouch,
         "crouch_height_m": s.crouch_height}
    if plan is not None:
        start = float(s.start_time)
        # result.json's section as the run measures it (estimator CoG / CoP, the stop frame on the measured
        # feet from the status), and the same section from the pattern's frame (the old figures) for comparison
        m.update(estop_result(plan, full["t"], full["com"], full["cop"], full["margin"], start, fell,
                              estop.cfg.settle_speed, frame=estop.feet_frame, polygon=estop.feet_polygon,
                              end_time=s.align_start_time))
        m.update({f"{k}_pattern_frame": v for k, v in estop_result(
            plan, trace["t"], trace["com"], trace["cop"], trace["margin"], start, fell,
            estop.cfg.settle_speed).items() if k.startswith(("final_cog", "max_cop", "min_cop"))})
        m["result_feet_yaw_off_pattern_deg"] = math.degrees(s.feet_yaw_off_pattern)
        m.update(acceptance(plan, s, trace, start))
        truth = dict(trace, cop=trace["cop_truth"], margin=truth_margins(trace, plan, start))
        m.update({f"{k}_tick_avg": v for k, v in acceptance(plan, s, truth, start).items()
                  if "cop" in k or "margin" in k})
        m["max_cop_minor_m_tick_avg"] = float(np.nanmax(np.abs(plan.frame.to_local(
            trace["cop_truth"][trace["t"] >= start, :2])[:, 0])))
        # the same on the robot's feet (ground truth): the plan's frame carried from the pattern's feet onto
        # the measured soles at the start (the robot may have yawed / drifted off its pattern's world frame)
        m.update(feet_figures(plan, trace, start))
        m["final_cog_major_truth_m"] = m["final_cog_vs_n3_m_feet"] + float(plan.major.n3)
        mo = feet_motion(plan, trace, start)
        m["stop_time_truth_s"] = estop_result(plan, trace["t"], trace["com_truth"], trace["cop_truth"],
                                              trace["margin"], start, fell, estop.cfg.settle_speed,
                                              frame=plan.frame.moved(mo))["stop_time_s"]
        m.update(walking_touchdowns(trace, start))
        m.update(align_figures(estop, full, fell))
    else:
        m.update({"feasible": None, "fell": fell})
    m["trigger_time_s"] = s.trigger_time
    m["step"] = step
    m["fell_at_s"] = fell_at
    m["wait_s"] = (s.start_time - s.trigger_time) if plan is not None else math.nan
    return Trial(speed_kmh, phase, m, full, plan, list(estop.messages) + list(walk.messages))


def align_figures(estop, trace: dict, fell: bool) -> dict:
    """The feet step of the return home (§V step 3), ground truth: the final foot offset of the stepping sole
    from side by side along the feet's heading and across it (lateral distance minus the planned width), the
    final yaw difference, the tick-averaged CoP's smallest margin inside the support during the step (the hull
    of the true sole corners of the feet in contact, by the measured ankle forces; ``_planned_support``: of the
    planned support, both soles in double support and the stance sole in single support; the time the CoP is
    nearer than 5 mm to the contact support's edge), the
    time taken (start to end of the plan; and to the CoG slower than 0.01 m/s), and whether the robot stands
    (no fall, both feet in contact at the end)."""
    s = estop.status
    a = estop.align
    out = {"align_state": s.state, "align_swing": s.align_swing or None}
    if a is None or not math.isfinite(s.align_start_time):
        return out
    t = trace["t"]
    t0 = s.align_start_time
    idx = np.nonzero(t >= t0)[0]
    if not len(idx):
        return out
    from humfall_ros.model.humanoid import support_polygon

    margins, planned = [], []
    for i in idx:
        c = trace["cop_truth"][i]
        sup = a.sample(t[i] - t0).support
        corners = trace["corners_truth"][i][:, :, :2]
        poly = support_polygon(corners[0 if a.stance == "l" else 1] if sup != "double" else corners.reshape(-1, 2))
        planned.append(point_in_polygon_margin(c, poly) if np.isfinite(c).all() else -math.inf)
        touching = [corners[j] for j in (0, 1) if trace["contacts"][i][j]]
        margins.append(point_in_polygon_margin(c, support_polygon(np.vstack(touching)))
                       if touching and np.isfinite(c).all() else -math.inf)
    margins, planned = np.array(margins), np.array(planned)
    edge = np.nonzero(margins < 0.005)[0]
    k = {"l": 0, "r": 1}
    st_i, sw_i = k[a.stance], k[a.swing]
    yaw = trace["yaw_truth"][-1]
    h = math.atan2(math.sin(yaw[0]) + math.sin(yaw[1]), math.cos(yaw[0]) + math.cos(yaw[1]))
    d = trace["sole_truth"][-1][sw_i] - trace["sole_truth"][-1][st_i]
    hv = np.array([math.cos(h), math.sin(h)])
    d0 = trace["sole_truth"][idx[0]][sw_i] - trace["sole_truth"][idx[0]][st_i]
    speed = np.hypot(*trace["com_velocity"][idx, :2].T)
    moving = np.nonzero(speed >= 0.01)[0]
    settle = float(t[idx][moving[-1] + 1] - t0) if len(moving) and moving[-1] + 1 < len(idx) else math.nan
    ss = np.array([a.sample(x - t0).support != "double" for x in t[idx]])
    rel = trace["com_truth"][-1, :2] - 0.5 * (trace["sole_truth"][-1][0] + trace["sole_truth"][-1][1])
    out.update({
        "align_offset_before_m": float(d0 @ hv),
        "align_final_offset_along_m": float(d @ hv),
        "align_final_lateral_error_m": float(abs(d @ np.array([-hv[1], hv[0]])) - a.width),
        "align_final_yaw_diff_deg": math.degrees(math.remainder(yaw[sw_i] - yaw[st_i], math.tau)),
        "align_min_cop_margin_m": float(np.min(margins)),
        "align_min_cop_margin_planned_support_m": float(np.min(planned)),
        "align_cop_near_edge_s": float(len(edge) * np.median(np.diff(t))),
        "align_no_contact_ticks": int(np.sum(margins == -math.inf)),
        "align_cop_near_edge_first_s": float(t[idx][edge[0]] - t0) if len(edge) else None,
        "align_min_cop_margin_single_m": float(np.min(margins[ss])) if ss.any() else math.nan,
        "align_min_cop_margin_single_after_0.2s_m": float(np.min(margins[ss & (t[idx] >= t0 + a.t_lift + 0.2)]))
        if (ss & (t[idx] >= t0 + a.t_lift + 0.2)).any() else math.nan,
        "align_min_cop_margin_double_m": float(np.min(margins[~ss])) if (~ss).any() else math.nan,
        "align_duration_s": float(a.duration),
        "align_done_s": (s.align_end_time - t0) if math.isfinite(s.align_end_time) else math.nan,
        "align_settle_s": settle,
        "align_final_cog_from_feet_mid_m": float(np.linalg.norm(rel)),
        "align_both_feet_in_contact_end": bool(trace["contacts"][-1].all()),
        "align_stands": bool(not fell and trace["contacts"][-1].all()),
        "align_swing_slide_before_lift_m": float(np.linalg.norm(
            trace["sole_truth"][np.searchsorted(t, t0 + a.t_lift) - 1][sw_i] - trace["sole_truth"][idx[0]][sw_i])),
        "align_stance_slide_m": float(np.max(np.linalg.norm(trace["sole_truth"][idx][:, st_i]
                                                            - trace["sole_truth"][idx[0]][st_i], axis=1))),
    })
    return out


class ArmedAtStop:
    """A monitor (the FTB) stepped only from ``after`` [s] past the e-stop's start (``clock()``: sim time); before
    that it answers None and latches nothing (a false trigger of the walk or of the stop's first ticks does not
    hand the robot to safe_fall before the push)."""

    def __init__(self, monitor, estop, after: float = 0.0, clock=None):
        self.inner, self.estop, self.name = monitor, estop, monitor.name
        self.after, self.clock = float(after), clock

    def __getattr__(self, name):
        return getattr(self.inner, name)

    @property
    def latched(self):
        return self.inner.latched if self._armed() else {}

    @property
    def event(self):
        return self.inner.event if self._armed() else None

    def _armed(self) -> bool:
        st = self.estop.status.start_time
        return math.isfinite(st) and (self.clock is None or self.clock() >= st + self.after - 1e-9)

    def reset(self) -> None:
        self.inner.reset()

    def step(self, observation):
        return self.inner.step(observation) if self._armed() else None


def run_push_during_stop(speed_kmh: float = 1.0, phase: str = "ds_start", force=(300.0, 0.0, 0.0),
                         delay: float = 0.5, duration: float = 0.1, kind: str = "stepping", step: int = 5,
                         after: float = 4.0, armed: bool = True, arm_after: float = 0.0) -> dict:
    """A push on the chest ``delay`` [s] after the stop's start: the suite's ClosedLoop (``humfall up``'s
    controllers for ``controller: kind``: locomotion, the FTB monitor, safe_fall, the e-stop fed walking's
    state). Returns who commanded when (the mux's source per tick, compressed), the e-stop's state and
    messages, the FTB's fall event time and the ground-truth fall metrics. ``armed``: the FTB monitor runs from
    the stop's start only (:class:`ArmedAtStop`; in walking_estop at 1.0 km/h it fires during the walk, at
    2.9 s, before any push), from ``arm_after`` [s] past the stop's start (measured: armed at the start it fires
    12 ms into the stop, unpushed)."""
    sc = scenario.load("walking_estop", [f"walk.speed_kmh={speed_kmh}", f"estop.at.step={step}",
                                         f"estop.at.phase={phase}", f"controller={kind}",
                                         "params.ftb_monitor.use_walking_state=true"])
    loop = ClosedLoop(sc)
    estop = next(c.inner for c in loop.controllers if c.source == "estop")
    if armed:
        loop.monitors = [ArmedAtStop(m, estop, arm_after, lambda: loop.world.time) for m in loop.monitors]
    pushed_at = None
    sources, t_end = [], sc["duration"]
    try:
        while loop.world.time < t_end:
            obs = loop.step()
            if not sources or sources[-1][1] != loop.active:
                sources.append((round(obs.time, 3), loop.active))
            st = estop.status.start_time
            if pushed_at is None and math.isfinite(st) and obs.time >= st + delay:
                loop.world.add_push(np.asarray(force, float), (0.0, 0.0, 0.2), duration, link="chest")
                pushed_at = obs.time
            if math.isfinite(st):
                t_end = min(t_end, st + after)
        gt = loop.ground_truth.metrics.result()
    finally:
        loop.close()
    ev = getattr(loop.monitors[0], "event", None) if loop.monitors else None
    return {"speed_kmh": speed_kmh, "phase": phase, "force_n": list(force), "push_time_s": pushed_at,
            "estop_start_s": estop.status.start_time, "estop_state": estop.status.state,
            "fall_event_s": getattr(ev, "time", None), "sources": sources, "fell": gt["fell"],
            "metrics": {k: v for k, v in gt.items() if isinstance(v, (bool, int, float, str, type(None)))},
            "estop_messages": [m for m in estop.messages if "yield" in m or "fall" in m]}


def acceptance(plan, status, trace: dict, start: float, frame=None, polygon=None) -> dict:
    """The issue's per-trial figures beyond result.json's section (in the plan's frame, or ``frame`` /
    ``polygon``: the same carried onto the measured feet)."""
    frame = plan.frame if frame is None else frame
    polygon = plan.support_polygon if polygon is None else polygon
    t = trace["t"]
    after = t >= start
    local_com = frame.to_local(trace["com"][:, :2])
    local_cop = frame.to_local(trace["cop"][:, :2])
    # the feet's centre line is the Minor axis' x = 0 (through both sole centres, Fig. 3)
    v0 = float(np.hypot(*plan.state.com_velocity[:2]))
    bound = math.log(max(v0, 0.01) / 0.01) / plan.omega_c + 0.3
    speed = np.hypot(*trace["com_velocity"][:, :2].T)
    moving = np.nonzero(after & (speed >= 0.01))[0]
    settle = float(t[moving[-1] + 1] - start) if len(moving) and moving[-1] + 1 < len(t) else (
        0.0 if not len(moving) else math.nan)
    fin = local_com[-1]
    in_poly = point_in_polygon_margin(np.array([*trace["com"][-1, :2], 0.0]), polygon)
    cop_major = local_cop[after, 1]
    tail = t >= start + plan.stop_time
    return {
        "n3_lower_bound_m": float(plan.major.lower_bound),
        "v0_mps": v0,
        "final_cog_vs_n3_m": float(fin[1] - plan.major.n3),
        "min_cop_margin_from_start_m": float(np.min(trace["margin"][after])),
        "min_cop_margin_after_0.3s_m": float(np.min(trace["margin"][t >= start + 0.3])),
        "min_cop_margin_at_s": float(t[after][np.argmin(trace["margin"][after])] - start),
        "final_cog_inside_m": float(in_poly),
        "predicted_max_zmp_minor_m": float(plan.minor.max_zmp),
        "predicted_max_zmp_major_m": float(plan.major.max_zmp),
        "predicted_min_margin_m": float(plan.min_zmp_margin),
        "predicted_stop_time_s": float(plan.stop_time),
        "stop_time_estimator_v_s": settle,
        "stop_time_bound_s": bound,
        "max_cop_major_m": float(np.nanmax(cop_major)) if len(cop_major) else math.nan,
        # along the stop's direction (sign of n3): the largest CoP displacement beyond n3 (paper: <= n3 + 2 cm)
        "cop_major_overshoot_m": float(np.nanmax(np.sign(plan.major.n3) * cop_major) - abs(plan.major.n3))
        if len(cop_major) else math.nan,
        "cop_major_overshoot_after_0.3s_m": float(np.nanmax(np.sign(plan.major.n3) * local_cop[t >= start + 0.3, 1])
                                                  - abs(plan.major.n3)) if (t >= start + 0.3).any() else math.nan,
        "cop_major_settled_m": float(np.nanmedian(local_cop[tail, 1])) if tail.any() else math.nan,
        "max_displacement_m": float(np.max(np.abs(local_com[after, 1]))) if after.any() else math.nan,
        "omega_c": float(plan.omega_c), "beta": float(plan.beta),
    }


def truth_margins(trace: dict, plan, start: float, polygon=None) -> np.ndarray:
    """Distance [m] of the tick-averaged CoP inside the stop's double-support polygon (the plan's, from the
    feet at the start, or ``polygon``) from ``start`` [s] on; NaN before; -inf when airborne."""
    polygon = plan.support_polygon if polygon is None else polygon
    out = np.full(len(trace["t"]), np.nan)
    for i in np.nonzero(trace["t"] >= start)[0]:
        c = trace["cop_truth"][i]
        out[i] = point_in_polygon_margin(c, polygon) if np.isfinite(c).all() else -math.inf
    return out


def feet_motion(plan, trace: dict, start: float) -> PlanarMotion:
    """The rigid motion from the plan's (the pattern's) sole centres onto the measured ones at ``start``."""
    i = int(np.searchsorted(trace["t"], start))
    feet = plan.state.feet
    sl, sr = trace["sole_truth"][i]
    return PlanarMotion.between_feet(feet["l"].sole_center(MODEL(), "l"), feet["r"].sole_center(MODEL(), "r"),
                                     sl, sr)


def feet_figures(plan, trace: dict, start: float) -> dict:
    """The acceptance figures on the robot's own feet (ground truth CoG, tick-averaged CoP, sole centres): the
    plan's frame and polygon carried by :func:`feet_motion`; ``*_feet`` keys, plus the pattern-to-feet yaw and
    offset and how far a sole slid during the stop."""
    mo = feet_motion(plan, trace, start)
    frame = plan.frame.moved(mo)
    polygon = mo.apply(plan.support_polygon)
    i = int(np.searchsorted(trace["t"], start))
    slide = float(np.max(np.linalg.norm(trace["sole_truth"][i:] - trace["sole_truth"][i], axis=2)))
    truth = dict(trace, com=trace["com_truth"], cop=trace["cop_truth"],
                 margin=truth_margins(trace, plan, start, polygon))
    a = acceptance(plan, None, truth, start, frame=frame, polygon=polygon)
    after = trace["t"] >= start
    fin = frame.to_local(trace["com_truth"][-1, :2])
    plan_only = ("n3_lower_bound_m", "v0_mps", "omega_c", "beta", "predicted_max_zmp_minor_m",
                 "predicted_max_zmp_major_m", "predicted_min_margin_m", "predicted_stop_time_s", "stop_time_bound_s")
    out = {f"{k}_feet": v for k, v in a.items() if k not in plan_only}
    # the same final CoG on the soles where they ended (they may slide during the stop)
    last = PlanarMotion.between_feet(*[plan.state.feet[f].sole_center(MODEL(), f) for f in ("l", "r")],
                                     *trace["sole_truth"][-1])
    fin_end = plan.frame.moved(last).to_local(trace["com_truth"][-1, :2])
    out.update({"final_cog_vs_n3_m_end_feet": float(fin_end[1] - plan.major.n3),
                "final_cog_minor_m_end_feet": float(fin_end[0])})
    out.update({"final_cog_minor_m_feet": float(fin[0]),
                "max_cop_minor_m_feet": float(np.nanmax(np.abs(frame.to_local(trace["cop_truth"][after, :2])[:, 0]))),
                "pattern_to_feet_yaw_deg": math.degrees(mo.yaw),
                "pattern_to_feet_offset_m": float(np.linalg.norm(mo.apply(plan.frame.origin) - plan.frame.origin)),
                "sole_slide_m": slide})
    return out


def walking_touchdowns(trace: dict, start: float, window: float = 0.3) -> dict:
    """Walking's own touchdown transients before the stop (the comparison for the stop's first ticks): over
    each double-support start of the walk (support single -> double, after the first 1 s), the largest
    tick-averaged CoP displacement past the double support's final ZMP reference along the CoG's direction
    within ``window`` [s], and the CoP's smallest margin to the measured contact polygon in that window
    (-inf: a tick without a contact polygon). Medians and worst over the touchdowns [m]."""
    t, sup, cop, zr, v = trace["t"], trace["support"], trace["cop_truth"], trace["zmp_ref"], trace["com_velocity"]
    over, marg = [], []
    for i in range(1, len(t)):
        if not (sup[i] == "double" and str(sup[i - 1]).startswith("single") and t[0] + 1.0 < t[i] < start - 0.01):
            continue
        h = v[i, :2] / max(float(np.linalg.norm(v[i, :2])), 1e-9)
        j = i
        while j + 1 < len(t) and sup[j + 1] == "double":
            j += 1
        w = (t >= t[i]) & (t < t[i] + window)
        over.append(float(np.nanmax((cop[w, :2] - zr[j, :2]) @ h)))
        marg.append(float(np.min(trace["margin"][w])))
    if not over:
        return {}
    return {"walking_touchdown_cop_overshoot_m": float(np.median(over)),
            "walking_touchdown_cop_overshoot_max_m": float(np.max(over)),
            "walking_touchdown_min_margin_m": float(np.median(marg)),
            "walking_touchdowns": len(over)}


_MODEL = []


def MODEL():
    if not _MODEL:
        from humfall_ros.model.humanoid import load_model
        _MODEL.append(load_model())
    return _MODEL[0]


def fit_omega_f(trace: dict) -> dict:
    """eq. 2's omega_f fitted per world axis on the walking part (executed CoP vs walking's zmp_ref)."""
    w = trace["walking"] & (trace["active"] == "locomotion") & np.isfinite(trace["margin"])
    idx = np.nonzero(w)[0]
    if len(idx) < 50:
        return {}
    idx = idx[idx >= idx[0] + 250]        # skip the first 0.5 s of the walk (crouch start)
    t = trace["t"][idx]
    out = {}
    for src, tag in (("cop", ""), ("cop_truth", "_tick_avg")):
        for a, name in ((0, "x"), (1, "y")):
            om, rms = fit_zmp_lag(t, trace["zmp_ref"][idx, a], trace[src][idx, a])
            out[f"omega_f_{name}{tag}"] = om
            out[f"rms_{name}{tag}_m"] = rms
    return out


def figures_from_npz(path) -> dict:
    """Re-measure a saved trial (``--save``) offline: the tick-averaged CoP figures along the stop frame."""
    d = dict(np.load(path, allow_pickle=True))
    m = json.loads(str(d["metrics"]))
    if "frame_origin" not in d:
        return m
    t, start, n3 = d["t"], float(d["start"]), float(d["n3"])
    major = d["frame_major"] / np.linalg.norm(d["frame_major"])
    minor = np.array([major[1], -major[0]])
    after = t >= start
    rel = d["cop_truth"][:, :2] - d["frame_origin"]
    cop_major, cop_minor = rel @ major, rel @ minor
    poly = d["polygon"]
    margin = np.array([point_in_polygon_margin(np.array([*c[:2], 0.0]), poly) if np.isfinite(c).all() else -math.inf
                       for c in d["cop_truth"]])
    ok = after & np.isfinite(margin)
    m.update({
        "cop_major_overshoot_m_tick_avg": float(np.nanmax(np.sign(n3) * cop_major[after]) - abs(n3)),
        "cop_major_settled_m_tick_avg": float(np.nanmedian(cop_major[t >= start + 1.5])) if (t >= start + 1.5).any()
        else math.nan,
        "max_cop_minor_m_tick_avg": float(np.nanmax(np.abs(cop_minor[after]))),
        "min_cop_margin_from_start_m_tick_avg": float(np.min(margin[after])),
        "min_cop_margin_after_0.3s_m_tick_avg": float(np.min(margin[t >= start + 0.3])),
        "cop_margin_below_1cm_s": float(np.sum(ok & (margin < 0.01)) * np.median(np.diff(t))),
    })
    return m


def save_trace(path, trial: Trial) -> None:
    """The trace and the plan's frame / polygon / start (what humfall_ros.estop.plots.load_trace reads)."""
    p = trial.plan
    extra = {}
    if p is not None:
        extra = {"frame_origin": p.frame.origin, "frame_major": p.frame.major, "polygon": p.support_polygon,
                 "plan_soles": np.array([p.state.feet[f].sole_center(MODEL(), f)[:2] for f in ("l", "r")]),
                 "n3": p.major.n3, "start": trial.metrics.get("trigger_time_s", np.nan) + trial.metrics.get(
                     "wait_s", 0.0)}
    np.savez_compressed(path, **{k: v for k, v in trial.trace.items()}, **extra,
                        metrics=json.dumps(_clean(trial.metrics)))


def _clean(d: dict) -> dict:
    out = {}
    for k, v in d.items():
        if isinstance(v, (float, np.floating)):
            v = float(v)
            out[k] = None if not math.isfinite(v) else round(v, 5)
        elif isinstance(v, (np.bool_,)):
            out[k] = bool(v)
        else:
            out[k] = v
    return out


COLUMNS = (("speed_kmh", "km/h"), ("step", "step"), ("phase", "phase"), ("wait_s", "SS wait s"),
           ("feasible", "pred. feasible"), ("crouch_height_m", "CoG height m"), ("fell", "fell"),
           ("n3_m", "n3 m"), ("final_cog_vs_n3_m", "final CoG - n3 m"), ("final_cog_minor_m", "final CoG Minor m"),
           ("predicted_max_zmp_minor_m", "pred. max ZMP Minor m"), ("max_cop_minor_m_tick_avg", "max CoP Minor m"),
           ("min_cop_margin_from_start_m_tick_avg", "min CoP margin m"),
           ("min_cop_margin_after_0.3s_m_tick_avg", "min margin after 0.3 s m"),
           ("cop_margin_below_1cm_s", "time < 1 cm s"),
           ("cop_major_overshoot_m_tick_avg", "CoP beyond n3 m"),
           ("cop_major_settled_m_tick_avg", "CoP Major settled m"),
           ("stop_time_estimator_v_s", "stop time s"), ("stop_time_bound_s", "bound s"))


# the acceptance table on the robot's feet (ground truth; feet_figures)
FEET_COLUMNS = (("speed_kmh", "km/h"), ("step", "step"), ("phase", "phase"), ("wait_s", "SS wait s"),
                ("feasible", "pred. feasible"), ("fallback", "fallback"), ("crouch_height_m", "CoG height m"),
                ("fell", "fell"), ("pattern_to_feet_yaw_deg", "feet yaw off pattern deg"), ("n3_m", "n3 m"),
                ("final_cog_vs_n3_m_feet", "final CoG - n3 m"), ("final_cog_minor_m_feet", "final CoG Minor m"),
                ("final_cog_vs_n3_m_end_feet", "final CoG - n3 (end soles) m"),
                ("final_cog_minor_m_end_feet", "final CoG Minor (end soles) m"),
                ("final_cog_inside_m_feet", "final CoG inside m"),
                ("predicted_max_zmp_minor_m", "pred. max ZMP Minor m"), ("max_cop_minor_m_feet", "max CoP Minor m"),
                ("min_cop_margin_from_start_m_feet", "min CoP margin m"),
                ("min_cop_margin_after_0.3s_m_feet", "min margin after 0.3 s m"),
                ("cop_major_overshoot_m_feet", "CoP beyond n3 m"),
                ("walking_touchdown_cop_overshoot_m", "walking: CoP beyond DS-end ZMP m"),
                ("cop_major_overshoot_after_0.3s_m_feet", "CoP beyond n3 after 0.3 s m"),
                ("cop_major_settled_m_feet", "CoP Major settled m"),
                ("stop_time_estimator_v_s", "stop time s"), ("stop_time_bound_s", "bound s"),
                ("sole_slide_m", "sole slide m"))


# result.json's estop section (estimator, stop frame on the measured feet) beside the ground truth on the feet
RESULT_COLUMNS = (("speed_kmh", "km/h"), ("phase", "phase"),
                  ("result_feet_yaw_off_pattern_deg", "feet yaw off pattern deg"), ("n3_m", "n3 m"),
                  ("final_cog_major_m_pattern_frame", "result (pattern frame, before): final CoG Major m"),
                  ("final_cog_major_m", "result: final CoG Major m"),
                  ("final_cog_major_truth_m", "truth: final CoG Major m"),
                  ("final_cog_minor_m_pattern_frame", "result (before): final CoG Minor m"),
                  ("final_cog_minor_m", "result: final CoG Minor m"), ("final_cog_minor_m_feet", "truth: Minor m"),
                  ("max_cop_minor_m", "result: max CoP Minor m"), ("max_cop_minor_m_feet", "truth: max CoP Minor m"),
                  ("min_cop_margin_m", "result: min CoP margin m"),
                  ("min_cop_margin_from_start_m_feet", "truth: min CoP margin m"),
                  ("stop_time_s", "result: stop time s"), ("stop_time_estimator_v_s", "trials: stop time s"),
                  ("stop_time_truth_s", "truth: stop time s"))


def markdown_table(rows: list[dict], columns=COLUMNS) -> str:
    """The trial table (docs/estop.md), tick-averaged CoP figures; signed Major values as measured."""
    def f(v):
        if v is None:
            return "—"
        if isinstance(v, bool):
            return "yes" if v else "no"
        return f"{v:.3f}" if isinstance(v, float) else str(v)

    head = "| " + " | ".join(h for _, h in columns) + " |"
    sep = "|" + "---|" * len(columns)
    body = ["| " + " | ".join(f(r.get(k)) for k, _ in columns) + " |" for r in rows]
    return "\n".join([head, sep, *body])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("speeds", nargs="*", type=float, default=list(SPEEDS))
    ap.add_argument("--phases", default=",".join(PHASES))
    ap.add_argument("--json", default="")
    ap.add_argument("--fallback", default="")
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                    help="estop_planner parameter overrides (numbers parsed), e.g. crouch_min_cog_height=0.699")
    ap.add_argument("--scenario-set", nargs="*", default=[], metavar="KEY=VALUE",
                    help="scenario overrides, e.g. sim.contact_breaking_threshold=0.05")
    ap.add_argument("--step", type=int, default=5, help="estop.at.step (default 5: after the 5th step)")
    ap.add_argument("--fit", action="store_true", help="fit omega_f on each trial's walking part")
    ap.add_argument("--save", default="", help="folder for one .npz trace per trial (humfall_ros.estop.plots)")
    ap.add_argument("--markdown", nargs="*", default=None, help="print the table of these --json files and exit")
    ap.add_argument("--pattern-frame", action="store_true",
                    help="with --markdown: the old table in the pattern's frame (default: on the measured feet)")
    ap.add_argument("--result-vs-truth", action="store_true",
                    help="with --markdown: result.json's section (estimator, feet frame) beside the ground truth")
    ap.add_argument("--push", type=float, nargs="*", default=None, metavar="FX [FY]",
                    help="push during the stop (0.1 s on the chest, --push-delay after its start) with safe_fall")
    ap.add_argument("--push-delay", type=float, default=0.5)
    ap.add_argument("--controller", default="stepping")
    ap.add_argument("--arm-after", type=float, default=0.0, help="the FTB runs from this long after the stop's start")
    a = ap.parse_args(argv)
    if a.push is not None:
        f = [*a.push, 0.0, 0.0][:3]
        for v in a.speeds:
            for ph in a.phases.split(","):
                print(json.dumps(run_push_during_stop(v, ph, f, a.push_delay, kind=a.controller, step=a.step,
                                                      arm_after=a.arm_after),
                                 default=str), flush=True)
        return 0
    if a.markdown:
        rows = [figures_from_npz(path) if path.endswith(".npz") else r for path in a.markdown
                for r in ([None] if path.endswith(".npz") else json.load(open(path)))]
        print(markdown_table(rows, RESULT_COLUMNS if a.result_vs_truth else COLUMNS if a.pattern_frame
                             else FEET_COLUMNS))
        return 0
    rows = []
    over = {"fallback": a.fallback} if a.fallback else {}
    for kv in a.set:
        k, v = kv.split("=", 1)
        try:
            over[k] = {"true": True, "false": False}[v.lower()] if v.lower() in ("true", "false") else (
                int(v) if v.lstrip("-").isdigit() else float(v))
        except ValueError:
            over[k] = v
    for v in a.speeds:
        for ph in a.phases.split(","):
            tr = run_trial(v, ph, step=a.step, overrides=a.scenario_set, **over)
            m = tr.metrics
            if a.fit:
                m.update(fit_omega_f(tr.trace))
            m = _clean(m)
            rows.append(m)
            print(json.dumps(m), flush=True)
            if a.save and tr.plan is not None:
                pathlib.Path(a.save).mkdir(parents=True, exist_ok=True)
                save_trace(pathlib.Path(a.save) / f"estop_{v:g}_{ph}.npz", tr)
            if m.get("walk_refused"):
                break
    if a.json:
        with open(a.json, "w") as f:
            json.dump(rows, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
