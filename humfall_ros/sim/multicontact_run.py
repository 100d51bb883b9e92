"""A multi-contact plan executed on the 3-D robot in PyBullet (issue 14; paper 2 Sec. III plans, we execute).

One run: the scenario's push (``config/scenarios/multicontact_push.yaml``) with the standing balance
as the ``locomotion`` source; at the first tick at or after the push's end the ``multicontact``
executor (``humfall_ros.multicontact.executor``, mux priority above every built-in source) takes the
measured state (ground truth, ``SimWorld.pinocchio_state``), maps it to the planar planner's state
(``planar_state``), makes it consistent with the two-foot mode (``project_to_mode``: feet flat on the
ground, eq. 3; contact velocities removed with the impact map, eq. 10), plans, and tracks the plan.

**Planning pauses the simulator.** The plan is computed inside the take-over tick, as a lockstep
source's answer: the physics does not advance while the planner runs, so the plan starts from the
state it was computed from. The tree search takes seconds (5-10 s unloaded with the departure
objective, docs/multicontact.md) and even a warm library re-plan (~1 s) is as long as the whole fall,
so planning in advance from a predicted state would still need a planner faster than the fall; the
execution figures here measure the executor and the plan on the 3-D robot, with planning latency
removed (stated in every report as ``plan.compute_s``).

Measured per control tick: the 3-D kinetic energy ½ vᵀ M(q) v (pinocchio ``crba`` on the free-flyer
model) and every robot-ground contact point (``SimWorld.ground_contacts``: the tick means of the
physics substeps' forces), grouped by limb (LF, RF: the feet; LH, RH: the forearms, whose end caps
are the hands: the hand links have no collision shape) and by link for everything else.
No rclpy here.
"""
from __future__ import annotations

import dataclasses
import math
import time
from typing import Any

import numpy as np
import pinocchio as pin
import pybullet as pb
from scipy.spatial.transform import Rotation

from humfall_ros import scenario as scenario_mod
from humfall_ros.dynamics.pendulum import GRAVITY, capture_point
from humfall_ros.multicontact.collocation import Segment
from humfall_ros.multicontact.collocation import capture_point as planar_capture_point
from humfall_ros.multicontact.executor import (ExecutorConfig, MulticontactExecutor, pitch_of, planar_state,
                                               planned_contacts, project_to_mode)
from humfall_ros.multicontact.modes import mode_label, parse_mode
from humfall_ros.sim.closed_loop import ClosedLoop
from humfall_ros.suite import locomotion_controller
from humfall_ros.scenario import push_time

EXECUTOR_PRIORITY = 40          # above locomotion 10, estop 20, safe_fall 30 (scenario.BUILTIN_PRIORITIES)
INITIAL_MODE = "LF/RF"
LIMBS = ("LF", "RF", "LH", "RH")


@dataclasses.dataclass(frozen=True)
class RunConfig:
    """Attributes:
        settle: time simulated after the plan's end [s] (5 s since session 41: the stop balance's hip strategy and
            its shift to the soles' middle take ~3 s from the touchdown).
        contact_force_min: a limb or link touches when its tick-mean contact force exceeds this [N].
        final_window: the final mode and KE are judged over this last stretch of the run [s].
        time_budget: the planner's wall-clock budget [s].
        executor: the executor's options (``ExecutorConfig``; its ``start_time`` is set to the run's take-over).
            Until session 42 RunConfig repeated its fields; :meth:`of` still takes them flat.
        plan_latency: the plan is made from the state at the push's end but the executor takes over
            this much later [s] (the standing balance in between): what a planner that needs that
            long would do without pausing the simulator. 0: paused (the plan's state is the take-over's).
        speed_limit: how the URDF joint speed limits act. ``"motor"`` (default, ``SimWorld``'s own since
            2026-12-02, so also what the ROS graph runs): each servo's ``maxVelocity`` (PyBullet's position
            motor limits the speed it drives at; the joint can still be back-driven faster by impacts):
            momentum is conserved. ``"solver"``: the solver's ``maxJointVelocity`` clamp SimWorld used
            before; it does not conserve momentum (measured: 70-100 N s gained in one tick, 12.8 N s in a
            tick without any contact, ~1000 J of kinetic energy; ``momentum_error_ns_max``). ``"none"``: no
            limit but the clipped velocity targets (the servos then drive joints 3-5 x past their limits).
        event_debounce: the report matches each planned contact event to the executed change of that limb (after
            its previous event) nearest the planned time among the changes that last this long [s] (session 41;
            before, the first change: the 60 J two-step plan's stance foot left the ground for 34 ms in the first
            swing, and the report gave its planned release at 0.04 s and its second landing at 0.07 s, 0.76 m off).
    """

    settle: float = 5.0
    contact_force_min: float = 5.0
    final_window: float = 0.1
    time_budget: float = 120.0
    executor: ExecutorConfig = dataclasses.field(default_factory=ExecutorConfig)
    plan_latency: float = 0.0
    speed_limit: str = "motor"
    event_debounce: float = 0.03

    @classmethod
    def of(cls, **options) -> RunConfig:
        """A run configuration from flat options: this class's fields and ``ExecutorConfig``'s (e.g.
        ``RunConfig.of(settle=2.0, stop_balance=False)``; the benchmark's ``--run name=value``)."""
        own = {f.name for f in dataclasses.fields(cls)} - {"executor"}
        executor = {f.name for f in dataclasses.fields(ExecutorConfig)} - {"start_time"}
        unknown = set(options) - own - executor
        if unknown:
            raise ValueError(f"not a RunConfig or ExecutorConfig option: {sorted(unknown)}")
        return cls(executor=ExecutorConfig(**{k: v for k, v in options.items() if k in executor}),
                   **{k: v for k, v in options.items() if k in own})


def push_end_time(sc: dict) -> float:
    """End of the scenario's last push [s] (the executor's take-over)."""
    if not sc["push"]:
        raise ValueError("the scenario has no push")
    return max(push_time(sc, p) + p["duration"] for p in sc["push"])


def with_push(sc: dict, force_x: float, duration: float | None = None) -> dict:
    """``sc`` with its first push set to ``force_x`` [N] forward (and ``duration`` [s]), revalidated."""
    sc = scenario_mod.apply_override(sc, f"push.0.force=[{float(force_x)}, 0.0, 0.0]")
    if duration is not None:
        sc = scenario_mod.apply_override(sc, f"push.0.duration={float(duration)}")
    return sc


class _Probe:
    """Per-tick measurements of a world: 3-D KE, contact forces per limb and per link."""

    def __init__(self, world):
        self.world = world
        hm = world.model
        self.hm = hm
        self.data = hm.model.createData()
        names = {i: n for n, i in world.link_ids.items()}
        self.link_name = names
        feet = {"LF": world.foot_links["l"], "RF": world.foot_links["r"]}
        hands = {}
        for ext, side in (("LH", "l"), ("RH", "r")):
            # the hand frame's link has no collision shape: its parent link (the forearm) touches
            hand = world.link_ids[hm.hand_frame[side]]
            hands[ext] = pb.getJointInfo(world.robot, hand, physicsClientId=world.client)[16]
        self.limb_of_link = {v: k for k, v in {**feet, **hands}.items()}
        self.limb_link = {**feet, **hands}
        self.t: list[float] = []
        self.ke: list[float] = []
        self.limb_force: dict[str, list[float]] = {e: [] for e in LIMBS}
        self.limb_point: dict[str, list] = {e: [] for e in LIMBS}
        self.link_force: dict[str, dict[int, float]] = {}    # link name -> {tick: normal force}
        self.tilt: list[float] = []
        self.mass = pin.computeTotalMass(hm.model)
        self.momentum_error: list[float] = []      # |dp - (F_contact + M g) dt| per tick [N s]
        self.joint_speed_ratio: list[float] = []   # max |qdot| / URDF limit per tick
        self.fastest_joint: list[int] = []
        self._p_prev = None
        self.final_heights: dict[str, float] = {}
        self.foot_height: dict[str, list[float]] = {"LF": [], "RF": []}   # lowest sole corner per tick [m]
        self.base_pitch: list[float] = []     # the base's planar pitch per tick (ground truth) [rad]
        self.com_x: list[float] = []          # CoM x per tick (ground truth) [m]
        self.capture_x: list[float] = []      # capture point x = x + vx sqrt(z / g) per tick [m]
        self.toe_x: dict[str, list[float]] = {"LF": [], "RF": []}   # each sole's foremost corner x per tick [m]
        self.sole_x: dict[str, list[float]] = {"LF": [], "RF": []}  # each sole's centre x (its corners' mean) [m]

    def kinetic_energy(self, q=None, v=None) -> float:
        """½ vᵀ M(q) v of the world's state (or of the given ``q``, ``v``: the tick's, read once)."""
        if q is None:
            q, v = self.world.pinocchio_state()
        M = pin.crba(self.hm.model, self.data, q)
        return float(0.5 * v @ M @ v)

    def limb_heights(self) -> dict[str, float]:
        """Lowest sole corner of each foot, and each hand frame, above the ground [m] (ground truth)."""
        hm = self.hm
        hm.forward(self.world.pinocchio_configuration())
        out = {"LF": float(hm.sole_corners("l")[:, 2].min()), "RF": float(hm.sole_corners("r")[:, 2].min())}
        for ext, side in (("LH", "l"), ("RH", "r")):
            out[ext] = float(hm.frame_position(hm.hand_frame[side])[2])
        return out

    def record(self) -> None:
        w = self.world
        k = len(self.t)
        self.t.append(w.time)
        q, v = w.pinocchio_state()          # the tick's ground-truth state, read once for every figure below
        self.ke.append(self.kinetic_energy(q, v))
        self.tilt.append(w.trunk_tilt())
        force = {e: np.zeros(3) for e in LIMBS}
        moment = {e: np.zeros(3) for e in LIMBS}
        normal = {e: 0.0 for e in LIMBS}
        per_link: dict[int, float] = {}
        for cp in w.ground_contacts():
            f = cp[9] * np.asarray(cp[7]) + cp[10] * np.asarray(cp[11]) + cp[12] * np.asarray(cp[13])
            per_link[cp[3]] = per_link.get(cp[3], 0.0) + cp[9]
            limb = self.limb_of_link.get(cp[3])
            if limb is not None:
                force[limb] += f
                normal[limb] += cp[9]
                moment[limb] += cp[9] * np.asarray(cp[6])
        total = sum(force.values()) + np.zeros(3)
        for cp in w.ground_contacts():
            if cp[3] not in self.limb_of_link:
                total = total + cp[9] * np.asarray(cp[7]) + cp[10] * np.asarray(cp[11]) + cp[12] * np.asarray(cp[13])
        pin.centerOfMass(self.hm.model, self.data, q, v)
        c, vc = self.data.com[0], self.data.vcom[0]
        self.com_x.append(float(c[0]))
        self.capture_x.append(float(capture_point(c, vc)[0]))
        p = self.mass * np.array(vc)
        if self._p_prev is not None:
            dt = 1.0 / w.control_rate
            self.momentum_error.append(float(np.linalg.norm(p - self._p_prev - (total - [0, 0, self.mass * GRAVITY])
                                                            * dt)))
        else:
            self.momentum_error.append(0.0)
        self._p_prev = p
        ratio = np.abs(w.joint_states()[1]) / w.model.limits.velocity
        self.joint_speed_ratio.append(float(ratio.max()))
        self.fastest_joint.append(int(ratio.argmax()))
        hm = self.hm
        self.base_pitch.append(pitch_of(Rotation.from_quat(q[3:7]).as_matrix()))
        pin.framesForwardKinematics(hm.model, self.data, q)
        for e, side in (("LF", "l"), ("RF", "r")):
            corners = [self.data.oMf[hm.frame_ids[f]].translation for f in hm.corner_frames[side]]
            self.foot_height[e].append(float(min(c[2] for c in corners)))
            self.toe_x[e].append(float(max(c[0] for c in corners)))
            self.sole_x[e].append(float(np.mean([c[0] for c in corners])))
        for e in LIMBS:
            self.limb_force[e].append(float(np.linalg.norm(force[e])))
            self.limb_point[e].append(moment[e] / normal[e] if normal[e] > 1e-9 else None)
        for lid, fn in per_link.items():
            if lid not in self.limb_of_link:
                self.link_force.setdefault(self.link_name.get(lid, str(lid)), {})[k] = fn


def _first(mask: np.ndarray, start: int) -> int | None:
    idx = np.flatnonzero(mask[start:])
    return int(start + idx[0]) if len(idx) else None


def _lasting_changes(mask: np.ndarray, start: int, ticks: int) -> np.ndarray:
    """The indices from ``start`` where ``mask`` turns (or is, at ``start``) true and stays true for ``ticks`` ticks
    in a row, or to its end: contact changes that last, not a sole's chatter."""
    m = np.asarray(mask[start:], bool)
    if not len(m):
        return np.zeros(0, int)
    n = max(int(ticks), 1)
    padded = np.concatenate([m, np.repeat(m[-1:], n - 1)])
    lasting = np.lib.stride_tricks.sliding_window_view(padded, n).all(axis=1)
    entry = lasting & np.concatenate([[True], ~m[:-1]])
    return start + np.flatnonzero(entry)


def _matching_change(mask: np.ndarray, start: int, ticks: int, t: np.ndarray, planned_t: float) -> int | None:
    """The lasting change (``_lasting_changes``) nearest the planned time ``planned_t`` (``t``'s clock), or None."""
    ks = _lasting_changes(mask, start, ticks)
    return int(ks[np.argmin(np.abs(t[ks] - planned_t))]) if len(ks) else None


def execute(sc: dict, planner=None, segments: list[Segment] | None = None, start_time: float | None = None,
            cfg: RunConfig | None = None, duration: float | None = None, initial_mode: str = INITIAL_MODE,
            plan_from: str = "truth") -> dict:
    """Push, plan at the push's end (or take ``segments``), execute, measure; a JSON-able report.

    Args:
        sc: a validated scenario with a push (``multicontact_push``).
        planner: a ``FallPlanner`` (plans from the measured state at ``start_time``).
        segments: a stored plan instead (``Segment.from_dict``); it must have been planned from the
            state of this scenario at ``start_time`` (the report gives the mismatch).
        start_time: take-over time [s] (default: the push's end).
        duration: simulated time [s] (default: take-over + plan duration + ``cfg.settle``).
        initial_mode: the contact mode the measured state is made consistent with and planned from: the feet on
            the ground at the take-over ("LF/RF" standing; "LF" for a push in a walking robot's right swing,
            session 28, where ``cfg.executor.hold`` "measured" keeps the gait's lateral weight shift).
        plan_from: "truth" (the simulator's state at the take-over, projected onto the planar model) or "sensors"
            (``multicontact.live.SensedPlanSource``: the encoders, the IMU and the estimator, as the executor node
            plans with ``plan_live``); with "sensors" the report's ``state_at_plan`` also gives the ground truth's
            planar state and the difference.
    """
    if plan_from not in ("truth", "sensors"):
        raise ValueError(f"plan_from must be 'truth' or 'sensors', not {plan_from!r}")
    cfg = cfg or RunConfig()
    if (planner is None) == (segments is None):
        raise ValueError("give a planner or a stored plan (segments), not both")
    from humfall_ros.multicontact.model import load_model as load_planar

    pm = planner.model if planner is not None else load_planar()
    t_start = push_end_time(sc) if start_time is None else float(start_time)
    mode0 = parse_mode(initial_mode)
    info: dict[str, Any] = {}
    loop: ClosedLoop | None = None

    def measured_state():
        q3, v3 = loop.world.pinocchio_state()
        qp, vp = planar_state(pm, loop.model.joint_names, q3, v3)
        proj = project_to_mode(pm, qp, vp, mode0)
        info["state"] = {"time": loop.world.time, "ke_3d": probe.kinetic_energy(),
                         "ke_planar": proj.ke_before, "ke_planar_projected": proj.ke_after,
                         "projection_q_shift": proj.q_shift, "projection_contact_gap_m": proj.gap_before,
                         "projection_contact_slip_mps": proj.slip_before,
                         "lateral_velocity_mps": float(loop.world.base_state()[2][1]),
                         "q": proj.q.tolist(), "v": proj.v.tolist()}
        return proj

    def plan_source(obs):
        proj = info.pop("_early", None) or measured_state()
        t0 = time.perf_counter()
        r = planner.plan({"q": proj.q.tolist(), "v": proj.v.tolist(), "initial_mode": mode_label(mode0),
                          "time_budget": cfg.time_budget})
        info["plan"] = {"success": bool(r["success"]), "reason": r["reason"], "compute_s": time.perf_counter() - t0,
                        "contact_sequence": r["contact_sequence"], "node_ke": r["node_ke"],
                        "final_ke": r["final_ke"], "initial_ke": r["initial_ke"], "nlp_count": r["nlp_count"],
                        "landings": [x.to_dict() for x in r["landings"]]}
        return r["segments"] if r["success"] else None

    def sensed_source(obs):
        truth = measured_state()     # for the report only: the plan is made from the sensors
        segs = live(obs)
        li = live.info
        info["plan"] = {k: li.get(k) for k in ("success", "reason", "compute_s", "contact_sequence", "final_ke",
                                                "source")}
        if "q" in li:
            info["state"].update({"sensed_ke_planar": li["ke_planar"], "sensed_ke_planar_projected":
                                  li["ke_planar_projected"],
                                  "sensed_minus_truth_q_max": float(np.abs(np.subtract(li["q"], truth.q)).max()),
                                  "sensed_minus_truth_v_max": float(np.abs(np.subtract(li["v"], truth.v)).max()),
                                  "sensed_minus_truth_v": np.subtract(li["v"], truth.v).round(4).tolist()})
        return segs

    def stored_source(obs):
        proj = measured_state()
        s0 = segments[0]
        info["plan"] = {"success": True, "reason": "stored plan", "compute_s": 0.0,
                        "stored_state_error_q": float(np.abs(proj.q - s0.q[0]).max()),
                        "stored_state_error_v": float(np.abs(proj.v - s0.v[0]).max())}
        return list(segments)

    t_plan = t_start
    t_start = t_start + cfg.plan_latency
    ex_cfg = dataclasses.replace(cfg.executor, start_time=t_start)
    hm = _model()
    if plan_from == "sensors" and planner is not None:
        from humfall_ros.multicontact.live import SensedPlanSource

        live = SensedPlanSource(planner, hm, initial_mode, time_budget=cfg.time_budget)
        source = sensed_source
    else:
        source = plan_source if segments is None else stored_source
    executor = MulticontactExecutor([], pm.joint_names, _joint_names(), ex_cfg, plan_source=source, model=hm)
    loop = ClosedLoop(sc, controllers=[locomotion_controller(sc, hm), executor],
                      priorities={executor.source: EXECUTOR_PRIORITY})
    if cfg.speed_limit not in SPEED_LIMITS:
        raise ValueError(f"speed_limit must be one of {SPEED_LIMITS}")
    if cfg.speed_limit != "motor":  # "motor" is SimWorld's own
        _unclamp(loop.world, motor_limits=False, solver_clamp=cfg.speed_limit == "solver")
    probe = _Probe(loop.world)
    rate = sc["sim"]["control_rate"]
    try:
        t_end = None if duration is None else float(duration)
        while True:
            if cfg.plan_latency > 0 and "_early_done" not in info and loop.world.time >= t_plan - 0.5 / rate:
                info["_early"] = measured_state()      # the state the late plan is made from
                info["_early_done"] = True
            loop.step()
            probe.record()
            if t_end is None and (executor.take_over_time is not None or executor.failed):
                plan_T = sum(float(s.time[-1]) for s in executor.segments) if executor.segments else 0.0
                t_end = (executor.take_over_time or loop.world.time) + plan_T + cfg.settle
            if t_end is not None and loop.world.time >= t_end - 0.5 / rate:
                break
            if loop.world.time > t_start + 60.0:
                break
        probe.final_heights = probe.limb_heights()
    finally:
        loop.close()
    return _report(sc, pm, executor, probe, info, cfg, loop.active_sources)


SPEED_LIMITS = ("motor", "none", "solver")


def _unclamp(world, motor_limits: bool, solver_clamp: bool = False) -> None:
    """Change how ``world`` bounds joint speeds (this world instance only). ``SimWorld`` gives each servo
    its URDF speed limit as ``maxVelocity`` (``motor_limits``, its own default); without: no limit at all,
    or with ``solver_clamp`` the solver's ``maxJointVelocity`` at the limits (what SimWorld did before
    2026-12-02: it does not conserve momentum)."""
    world._motor_max_velocity = [float(x) for x in world.model.limits.velocity] if motor_limits else None
    for name, limit in zip(world.model.joint_names, world.model.limits.velocity):
        pb.changeDynamics(world.robot, world.joint_ids[name], maxJointVelocity=float(limit) if solver_clamp else 1e4,
                          physicsClientId=world.client)
    world._apply_targets()


_MODEL_CACHE: dict = {}


def _model():
    if "hm" not in _MODEL_CACHE:
        from humfall_ros.model.humanoid import load_model

        _MODEL_CACHE["hm"] = load_model()
    return _MODEL_CACHE["hm"]


def _joint_names() -> list[str]:
    return list(_model().joint_names)


def _report(sc, pm, executor, probe: _Probe, info: dict, cfg: RunConfig, active: list[str]) -> dict:
    t = np.array(probe.t)
    ke = np.array(probe.ke)
    fmin = cfg.contact_force_min
    push = sc["push"][0]
    out: dict[str, Any] = {
        "scenario": sc["name"], "push": {"force": push["force"], "duration": push["duration"],
                                         "start": push_time(sc, push), "end": push_end_time(sc)},
        "plan": info.get("plan", {"success": False, "reason": executor.reason}),
        "state_at_plan": {k: v for k, v in info.get("state", {}).items() if k not in ("q", "v")},
        "take_over_time": executor.take_over_time, "plan_latency": cfg.plan_latency, "speed_limit": cfg.speed_limit,
        "executor_failed": executor.failed,
        "executor_reason": executor.reason, "ke_max": float(ke.max()) if len(ke) else float("nan"),
        "base_pitch_error_max": executor.pitch_error_max, "base_pitch_feedback_ticks": executor.pitch_feedback_ticks,
        "lateral_ticks": executor.lateral_ticks, "lateral_offset_max_rad": executor.lateral_offset_max,
        "stop_balance": None if executor.stop_balance is None else {
            "plan_time_s": executor.stop_balance_time, "capture_point_margin_m": executor.stop_balance.margin,
            "settle_converged": executor.stop_balance.settle_converged,
            "shift_plan_time_s": executor.stop_shift_time},
        "task_swings": executor.task_swings,
    }
    if executor.take_over_time is None:
        out["success"] = False
        return out
    t0 = executor.take_over_time
    k0 = int(np.searchsorted(t, t0 - 1e-9))
    segs = executor.segments
    out["_segments"] = list(segs)       # the executed plan (Segment objects; not JSON)
    out["plan"]["segments"] = [{"kind": s.kind, "mode": mode_label(s.mode), "target_mode": mode_label(s.target_mode),
                                "change": s.change, "extremity": s.extremity, "duration": float(s.time[-1]),
                                "ke_start": float(s.ke[0]), "ke_end": float(s.ke[-1])} for s in segs]
    out["plan"]["duration"] = float(sum(s.time[-1] for s in segs))
    off, curve = 0.0, []
    for s in segs:
        curve += [[off + float(tt), float(e)] for tt, e in zip(s.time, s.ke)]
        off += float(s.time[-1])
    out["plan"]["ke_curve"] = curve
    # the paper's objective prices the kinetic energy at the end of a transition only (eq. 9): what the
    # motion carries before it (the arms swung fast, then braked) is free, and an early touchdown meets it
    curve_t = np.array([c[0] for c in curve])
    curve_ke = np.array([c[1] for c in curve])
    out["plan"]["ke_max"] = float(curve_ke.max())
    out["plan"]["ke_max_time"] = float(curve_t[int(np.argmax(curve_ke))])
    out["switches"] = [{"segment": i, "plan_time": float(tp), "why": why} for i, tp, why in executor.switches]
    out["sources_after_take_over"] = sorted(set(active[k0 + 1:]))
    mirror = executor.mirrored_hand
    out["mirrored_hand"] = mirror
    planned_final = tuple(segs[-1].mode) + ((mirror,) if mirror else ())
    out["planned_final_mode"] = mode_label(segs[-1].mode) + (f" (+{mirror}: both_hands)" if mirror else "")
    # contact events: planned vs executed
    touching = {e: np.array(probe.limb_force[e]) > fmin for e in LIMBS}
    events = []
    planned_events = planned_contacts(pm, segs)
    if mirror:
        planned_events += [dataclasses.replace(ev, extremity=mirror) for ev in planned_events
                           if ev.extremity in ("LH", "RH") and ev.extremity != mirror]
    search_from = {e: k0 for e in LIMBS}   # a foot's landing after its release is searched after the release
    # a planned event is matched to the executed change of that limb nearest its planned time among those that last
    # ``event_debounce`` (after the limb's previous event): a stance foot that leaves the ground for a moment during
    # the swing is not its planned release 0.5 s later
    debounce = max(1, int(round(cfg.event_debounce * sc["sim"]["control_rate"])))
    for ev in planned_events:
        row = {"extremity": ev.extremity, "change": ev.change, "planned_time": ev.time,
               "planned_x": ev.position[0], "planned_z": ev.position[1]}
        want = ev.change == "add"
        k = _matching_change(touching[ev.extremity] == want, search_from[ev.extremity], debounce, t, t0 + ev.time)
        if k is not None:
            if want and ev.extremity in probe.foot_height and search_from[ev.extremity] > k0:
                # a foot's swing: how high its lowest sole corner got between its release and this landing
                row["swing_clearance_m"] = float(max(probe.foot_height[ev.extremity][search_from[ev.extremity]:k + 1]))
            search_from[ev.extremity] = k
        row["executed_time"] = None if k is None else float(t[k] - t0)
        if k is not None and want:
            # how hard the executed touchdown is against the plan's: the 3-D energy on the tick before it,
            # the plan's at that (executed) time, and the plan's at its own landing
            row["executed_ke_before"] = float(ke[max(k - 1, 0)])
            row["planned_ke_at_executed_time"] = float(np.interp(t[k] - t0, curve_t, curve_ke))
            row["planned_ke_before"] = float(np.interp(ev.time - 1e-9, curve_t, curve_ke))
        if k is not None and want and probe.limb_point[ev.extremity][k] is not None:
            p = probe.limb_point[ev.extremity][k]
            row["executed_x"], row["executed_y"], row["executed_z"] = (float(p[0]), float(p[1]), float(p[2]))
        if k is not None and want and ev.extremity in probe.sole_x:
            # the planned position of a foot is its sole's centre (toe / heel midpoint); ``executed_x`` is where the
            # first touch pressed (a heel or a toe), so the comparable figure is the executed sole's centre
            row["executed_sole_x"] = probe.sole_x[ev.extremity][k]
            row["sole_x_error_m"] = float(row["executed_sole_x"] - ev.position[0])
        events.append(row)
    out["contact_events"] = events
    # every limb's first change of contact after the take-over, planned or not
    out["limb_touchdowns"] = {}
    for e in LIMBS:
        k = _first(touching[e] != touching[e][k0], k0)
        out["limb_touchdowns"][e] = {"in_contact_at_take_over": bool(touching[e][k0]),
                                     "first_change_time": None if k is None else float(t[k] - t0)}
    out["peak_force_n"] = {e: float(np.max(probe.limb_force[e][k0:])) for e in LIMBS}
    out["peak_force_n_time"] = {e: float(t[k0 + int(np.argmax(probe.limb_force[e][k0:]))] - t0) for e in LIMBS}
    mg = pin.computeTotalMass(_model().model) * GRAVITY
    out["peak_force_mg"] = {e: v / mg for e, v in out["peak_force_n"].items()}
    # the end: kinetic energy, mode, other links
    kw = int(np.searchsorted(t, t[-1] - cfg.final_window))
    out["final_time"] = float(t[-1])
    out["final_ke"] = float(ke[-1])
    out["final_ke_window_max"] = float(ke[kw:].max())
    final_limbs = [e for e in LIMBS if touching[e][kw:].all()]
    out["final_mode"] = "/".join(final_limbs) if final_limbs else "(none)"
    out["final_mode_matches_plan"] = set(final_limbs) == set(planned_final)
    out["final_limb_height_m"] = probe.final_heights
    out["final_limb_load_n"] = {e: float(np.mean(probe.limb_force[e][kw:])) for e in LIMBS}
    # touching = loaded, or a foot resting on the ground without load (lowest sole corner within 2 mm)
    resting = [e for e in ("LF", "RF") if e not in final_limbs and probe.final_heights.get(e, 1.0) < 0.002]
    touching_end = [e for e in LIMBS if e in final_limbs or e in resting]
    out["final_mode_touching"] = "/".join(touching_end) if touching_end else "(none)"
    out["final_mode_touching_matches_plan"] = set(touching_end) == set(planned_final)
    others = {}
    for name, by_tick in probe.link_force.items():
        ks = sorted(k for k, f in by_tick.items() if k >= k0 and f > fmin)
        if ks:
            others[name] = {"first_time": float(t[ks[0]] - t0), "peak_normal_n": float(max(by_tick[k] for k in ks)),
                            "at_end": any(k >= kw for k in ks)}
    out["other_links_touching"] = others
    planned_ext = set().union(*[set(s.mode) | set(s.target_mode) for s in segs]) | ({mirror} if mirror else set())
    unplanned_limbs = [e for e in LIMBS if e not in planned_ext and touching[e][k0:].any()]
    out["unplanned_limbs_touching"] = unplanned_limbs
    out["final_trunk_tilt_deg"] = math.degrees(probe.tilt[-1])
    out["momentum_error_ns_max"] = float(max(probe.momentum_error[k0:]))
    ratio = np.array(probe.joint_speed_ratio[k0:])
    kmax = int(np.argmax(ratio))
    out["joint_speed_over_limit_max"] = float(ratio[kmax])
    out["joint_speed_over_limit_joint"] = probe.hm.joint_names[probe.fastest_joint[k0 + kmax]]
    out["joint_speed_over_limit_time"] = float(t[k0 + kmax] - t0)
    out["joint_speed_over_1_1_limit_s"] = float((ratio > 1.1).sum() / len(ratio) * (t[-1] - t0))
    k_end = int(np.searchsorted(t, t0 + out["plan"]["duration"]))
    out["feet_airborne_s"] = {e: float((~touching[e][k0:k_end]).sum() * (t[1] - t[0])) for e in ("LF", "RF")}
    out["ke_at_plan_end"] = float(ke[min(len(ke) - 1, int(np.searchsorted(t, t0 + out["plan"]["duration"])))])
    out["series"] = {"t": (t - t0).tolist(), "ke": ke.tolist(),
                     "base_pitch": list(probe.base_pitch),
                     "foot_height": {e: list(h) for e, h in probe.foot_height.items()},
                     "com_x": list(probe.com_x), "capture_point_x": list(probe.capture_x),
                     "toe_x": {e: list(x) for e, x in probe.toe_x.items()},
                     "plan": _plan_series(pm, segs),
                     "limb_force": {e: list(map(float, probe.limb_force[e])) for e in LIMBS},
                     "other_force": {n: [float(by.get(k, 0.0)) for k in range(len(t))]
                                     for n, by in probe.link_force.items()}}
    out["success"] = bool(out["final_ke"] < 0.5 and out["final_mode_touching_matches_plan"] and not others
                          and not unplanned_limbs)
    return out


def _plan_series(pm, segs, dt: float = 0.01) -> dict:
    """The plan's root pitch, each foot's lowest point (toe or heel) and foremost x, the CoM's x and the capture
    point's x over plan time, every ``dt`` [s]."""
    out = {"t": [], "base_pitch": [], "foot_height": {"LF": [], "RF": []}, "toe_x": {"LF": [], "RF": []},
           "com_x": [], "capture_point_x": []}
    off = 0.0
    for seg in segs:
        T = float(seg.time[-1])
        for tl in np.arange(0.0, T, dt):
            qp, vp = MulticontactExecutor.planar(seg, float(tl))
            out["t"].append(off + float(tl))
            out["base_pitch"].append(float(qp[2]))
            out["com_x"].append(float(pm.com(qp)[0]))
            out["capture_point_x"].append(planar_capture_point(pm, qp, vp))
            for e in ("LF", "RF"):
                toe, heel = pm.point(f"{e}_toe", qp), pm.point(f"{e}_heel", qp)
                out["foot_height"][e].append(float(min(toe[1], heel[1])))
                out["toe_x"][e].append(float(max(toe[0], heel[0])))
        off += T
    return out


def state_at(sc: dict, t: float) -> dict:
    """The standing robot pushed by ``sc`` until sim time ``t`` (no executor): KE, planar state (for push tables)."""
    from humfall_ros.multicontact.model import load_model as load_planar

    pm = load_planar()
    hm = _model()
    loop = ClosedLoop(sc, controllers=[locomotion_controller(sc, hm)])
    probe = _Probe(loop.world)
    try:
        while loop.world.time < t - 1e-9:
            loop.step()
        q3, v3 = loop.world.pinocchio_state()
        qp, vp = planar_state(pm, hm.joint_names, q3, v3)
        proj = project_to_mode(pm, qp, vp, parse_mode(INITIAL_MODE))
        return {"time": loop.world.time, "ke_3d": probe.kinetic_energy(), "ke_planar": proj.ke_before,
                "ke_planar_projected": proj.ke_after, "projection_contact_gap_m": proj.gap_before,
                "projection_contact_slip_mps": proj.slip_before, "projection_q_shift": proj.q_shift,
                "pitch_rate": float(vp[2]), "lateral_velocity_mps": float(loop.world.base_state()[2][1])}
    finally:
        loop.close()


__all__ = ["EXECUTOR_PRIORITY", "SPEED_LIMITS", "RunConfig", "execute", "push_end_time", "state_at", "with_push"]
