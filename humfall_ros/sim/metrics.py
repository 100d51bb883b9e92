"""Ground-truth run metrics: did the robot fall, where, and how close to the target.

Avoidance angle (paper 1, Fig. 5): the angle at the initial CoP P between the
fall direction (P to the CoM's ground projection when the trunk lands) and
P to the target T: 0 deg falls onto the target, 180 deg straight away.

Safe-fall facts (issue 11), when fed: ``note_fall_event`` (the FTB's trigger time),
``note_decision`` (the fall controller's ``safe_fall/decision``) and ``update_feet`` each
tick (:func:`foot_state` of the world: ground-truth CoP, which soles touch, their poses).
Then ``avoidance_angle_p2_deg`` is the paper's alpha2: at P2, the mean ground-truth CoP
0.05-0.15 s after the swing sole's touchdown, between P2 -> landing CoM and P2 -> T;
``lead_time_s`` is trigger to first trunk contact; ``prediction`` compares the decision's
touchdown time, landing pose and alpha2 with the outcome.
"""
from __future__ import annotations

import math

import numpy as np

TARGET_CONTACT_M = 1e-3   # a robot-target distance below this is a touch (PyBullet's closest points read 0 at contact)

FALL_TRUNK_TILT = math.radians(45.0)   # trunk tilt beyond which the robot has fallen
FALL_WAIST_HEIGHT = 0.35               # m; waist below this: fallen
BOUNCE_S = 0.3                         # s; a step's sole that lifts and lands again within this is one touchdown (P2)


def angle_between_deg(a, b) -> float:
    a = np.asarray(a, float)[:2]
    b = np.asarray(b, float)[:2]
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    if na < 1e-9 or nb < 1e-9:
        return float("nan")
    return math.degrees(math.acos(float(np.clip(a @ b / (na * nb), -1.0, 1.0))))


def avoidance_angle_deg(cop, landing_com, target) -> float:
    """Angle at P between P->G_landing and P->T (paper 1, Fig. 5)."""
    p = np.asarray(cop, float)[:2]
    return angle_between_deg(np.asarray(landing_com, float)[:2] - p, np.asarray(target, float)[:2] - p)


class FallMetrics:
    """Accumulates ground-truth facts tick by tick."""

    def __init__(self, target_xy=None):
        self.target_xy = None if target_xy is None else np.asarray(target_xy, float)[:2]
        self.initial_cop = None
        self.fell = False
        self.fall_time = None
        self.landing_com = None
        self.landing_time = None
        self.min_target_distance = math.inf
        self.max_trunk_tilt = 0.0
        self.last_com = None
        self.fall_event_time = None
        self.decision: dict | None = None
        self.resteps: dict[int, dict] = {}   # step_index (2, 3, ..) -> a new decision after a failed capture
        self._feet_t = None
        self._lifted: dict[str, bool] = {}
        # side -> every touchdown after a lift-off: (t, (x, y, yaw), tilt [deg], CoPs 0.05-0.15 s after it)
        self._touchdown_log: dict[str, list[tuple]] = {}

    def note_fall_event(self, t: float) -> None:
        """The FTB's trigger time [s] (``fall_event``'s stamp); the first one counts."""
        if self.fall_event_time is None and t is not None and math.isfinite(float(t)):
            self.fall_event_time = float(t)

    def note_decision(self, d) -> None:
        """The fall controller's decision (``fall.controller.SafeFallDecision`` or the message's fields).

        Reads: stamp_ns or time [s], case, swing_side, landing (x, y, yaw), alpha2 [rad] (NaN: capture),
        captured, touchdown_time [s after the decision], step_index (1 when absent). The first one sets the
        decision time; a later one with the same step_index (a re-planned landing, same decision) updates the
        rest; a higher step_index is a new decision after a failed capture (``max_extra_steps``), kept apart.
        """
        if d is None:
            return
        def get(k, default=None):
            return d.get(k, default) if isinstance(d, dict) else getattr(d, k, default)

        t = get("time")
        if t is None:
            t = get("stamp_ns", 0) * 1e-9
        index = int(get("step_index", 1) or 1)
        known = self.decision if index <= 1 else self.resteps.get(index)
        if known is not None:
            t = known["time"]
        rec = {"time": float(t), "case": str(get("case", get("step_case", ""))),
               "swing_side": str(get("swing_side", "")),
               "landing": [float(x) for x in np.asarray(get("landing", [math.nan] * 3), float)],
               "alpha2": float(get("alpha2", math.nan)), "captured": bool(get("captured", False)),
               "alpha2_edge": float(get("alpha2_edge", math.nan)),
               "touchdown_time": float(get("touchdown_time", math.nan))}
        if index <= 1:
            self.decision = rec
        else:
            self.resteps[index] = rec

    def update_feet(self, t: float, cop, down: dict, poses) -> None:
        """Per tick: ground-truth CoP (None airborne), soles touching {side: bool}, sole poses
        {side: (x, y, yaw [rad], tilt from flat [deg])}. A repeated ``t`` is ignored.

        ``cop`` and ``poses`` may also be zero-argument callables giving them: they are then called only on
        the ticks that use them (a touchdown, the CoP window after it), at most once each
        (``foot_state(world, lazy=True)``: the bridge's per-tick cost)."""
        if self._feet_t is not None and t <= self._feet_t:
            return
        self._feet_t = t
        for side, is_down in down.items():
            log = self._touchdown_log.setdefault(side, [])
            if not is_down:
                self._lifted[side] = True
            elif self._lifted.get(side):
                self._lifted[side] = False
                if callable(poses):
                    poses = poses()
                x, y, yaw, tilt = poses[side]
                log.append((float(t), (float(x), float(y), float(yaw)), float(tilt), []))
            # P2 is the CoP on the new support: only while the step's sole is down
            if is_down and log and log[-1][0] + 0.05 - 1e-9 <= t <= log[-1][0] + 0.15 + 1e-9:
                if callable(cop):
                    cop = cop()
                if cop is not None:
                    log[-1][3].append(np.asarray(cop, float)[:2].copy())

    @property
    def touchdowns(self) -> dict[str, tuple]:
        """side -> (t, (x, y, yaw), tilt [deg]) of the step that answers the fall: the first touchdown after
        the fall event (with no event, the first after any lift-off). While walking, earlier touchdowns
        are the walk's own steps. Kept for every touchdown and chosen here, so the result does not
        depend on when the event became known (the bridge learns it over the graph)."""
        return {side: e[:3] for side, e in ((s, self._step_entry(s)) for s in self._touchdown_log) if e is not None}

    def _entries_after_event(self, side: str, after: float | None = None) -> list:
        """``side``'s touchdowns after the fall event (with no event, all of them), or after ``after`` [s]."""
        if after is None:
            after = self.fall_event_time if self.fall_event_time is not None else -math.inf
        return [e for e in self._touchdown_log.get(side, []) if e[0] > after]

    def _step_entry(self, side: str, after: float | None = None):
        entries = self._entries_after_event(side, after)
        return entries[0] if entries else None

    def _step_cops(self, side: str, after: float | None = None) -> list:
        """The CoPs of P2: 0.05-0.15 s after the step's touchdown. A sole that bounces off before that
        window (seen in the sweep: down at 1.012 s, up, down again at 1.144 s) has none there: then the
        window after its next touchdown counts, if that comes within ``BOUNCE_S`` of the first."""
        entries = self._entries_after_event(side, after)
        for e in entries:
            if e[0] - entries[0][0] > BOUNCE_S:
                break
            if e[3]:
                return e[3]
        return []

    def set_reference_cop(self, cop) -> None:
        """The P of Fig. 5: the CoP when the disturbance begins."""
        if self.initial_cop is None and cop is not None:
            self.initial_cop = np.asarray(cop, float)[:2].copy()

    def update(self, t: float, com, trunk_tilt: float, waist_height: float, target_distance: float | None,
               non_foot_contact: bool) -> None:
        com = np.asarray(com, float)
        self.last_com = com
        self.max_trunk_tilt = max(self.max_trunk_tilt, trunk_tilt)
        if target_distance is not None:
            self.min_target_distance = min(self.min_target_distance, target_distance)
        if not self.fell and (trunk_tilt > FALL_TRUNK_TILT or waist_height < FALL_WAIST_HEIGHT):
            self.fell = True
            self.fall_time = t
        # the trunk "meets the ground" (or an object): first non-foot contact once falling
        if self.landing_com is None and non_foot_contact and (self.fell or trunk_tilt > math.radians(20)):
            self.landing_com = com.copy()
            self.landing_time = t

    def result(self) -> dict:
        land = self.landing_com if self.landing_com is not None else self.last_com
        out = {
            "fell": bool(self.fell),
            "fall_time_s": self.fall_time,
            "landing_time_s": self.landing_time,
            "max_trunk_tilt_deg": math.degrees(self.max_trunk_tilt),
            "fall_direction_deg": None,
            "avoidance_angle_deg": None,
            "min_target_distance_m": None if not math.isfinite(self.min_target_distance)
            else round(float(self.min_target_distance), 4),
            "initial_cop": None if self.initial_cop is None else [float(x) for x in self.initial_cop],
            "landing_com": None if land is None else [float(x) for x in land],
        }
        if self.fell and self.initial_cop is not None and land is not None:
            d = land[:2] - self.initial_cop
            out["fall_direction_deg"] = math.degrees(math.atan2(d[1], d[0]))
            if self.target_xy is not None:
                out["avoidance_angle_deg"] = avoidance_angle_deg(self.initial_cop, land, self.target_xy)
        out.update(self._safe_fall(land))
        return out

    def _safe_fall(self, land) -> dict:
        d = self.decision or {}
        # alpha2 is measured at the CoP after the last step that answered the fall: the first decision's, or,
        # after failed captures, the last new decision's (``resteps``; its predictions then stand beside it)
        last = self.resteps[max(self.resteps)] if self.resteps else None
        dm = last if last is not None and last["case"].startswith("step") else d
        out = {"fall_event_time_s": self.fall_event_time,
               "lead_time_s": None if self.fall_event_time is None or self.landing_time is None
               else round(self.landing_time - self.fall_event_time, 4),
               "avoidance_angle_p2_deg": None, "measured_p2": None,
               "predicted_avoidance_deg": None if not math.isfinite(dm.get("alpha2", math.nan))
               else math.degrees(dm["alpha2"]),
               "predicted_avoidance_edge_deg": None if not math.isfinite(dm.get("alpha2_edge", math.nan))
               else math.degrees(dm["alpha2_edge"]),
               "predicted_captured": d.get("captured"), "decision_case": d.get("case"),
               "decisions": (1 if self.decision is not None else 0) + len(self.resteps),
               "restep_times_s": [round(r["time"], 4) for _, r in sorted(self.resteps.items())],
               "captured": None, "prediction": None}
        side = d.get("swing_side") or None
        if side is None and self.fall_event_time is not None:  # no decision fed: the first step after the trigger
            after = [(v[0], s) for s, v in self.touchdowns.items() if v[0] > self.fall_event_time]
            side = min(after)[1] if after else None
        td = self.touchdowns.get(side) if side else None
        if self.decision is not None:
            stepped = td is not None and d["case"].startswith("step")
            # a robot that ends up leaning on the target did not stop its own fall (measured: walking_push 300 N with
            # the push deferral "captured" while its trunk rested on the target box)
            touched = self.min_target_distance < TARGET_CONTACT_M
            out["captured"] = bool(stepped and not self.fell and not touched)
        m_side, m_after = side, None
        if dm is not d:
            m_side, m_after = dm.get("swing_side") or None, dm["time"]
        m_td = self._step_entry(m_side, m_after) if m_side else None
        cops = self._step_cops(m_side, m_after) if m_td is not None else []
        if cops:
            p2 = np.mean(cops, axis=0)
            out["measured_p2"] = [float(x) for x in p2]
            if self.fell and land is not None and self.target_xy is not None:
                out["avoidance_angle_p2_deg"] = avoidance_angle_deg(p2, land, self.target_xy)
        if self.decision is not None and td is not None and d["case"].startswith("step"):
            pred_td = d["time"] + d["touchdown_time"]
            lx, ly, lyaw = d["landing"]
            (x, y, yaw), tilt = td[1], td[2]
            yaw_err = math.degrees(abs((yaw - lyaw + math.pi) % (2 * math.pi) - math.pi))
            out["prediction"] = {
                "touchdown_time_s": td[0], "predicted_touchdown_time_s": pred_td,
                "touchdown_error_s": round(td[0] - pred_td, 4),
                "landing": [x, y, yaw], "predicted_landing": [lx, ly, lyaw],
                "landing_error_m": float(math.hypot(x - lx, y - ly)), "landing_yaw_error_deg": yaw_err,
                "landing_tilt_deg": tilt,
                "alpha2_error_deg": None if out["avoidance_angle_p2_deg"] is None
                or out["predicted_avoidance_deg"] is None
                else abs(out["avoidance_angle_p2_deg"] - out["predicted_avoidance_deg"]),
                "alpha2_edge_error_deg": None if out["avoidance_angle_p2_deg"] is None
                or out["predicted_avoidance_edge_deg"] is None
                else abs(out["avoidance_angle_p2_deg"] - out["predicted_avoidance_edge_deg"])}
        return out


def foot_state(world, lazy: bool = False) -> tuple:
    """(ground-truth CoP or None, {side: sole touches the ground}, {side: (x, y, yaw, tilt [deg])}) of a SimWorld.

    What ``FallMetrics.update_feet`` takes (GroundTruth.track may pass ``*foot_state(world)``). ``lazy``: the
    CoP and the poses as functions of no argument, for ``update_feet`` to call on the ticks it needs them
    (the poses take a forward kinematics pass; the same numbers either way, from the world as it is now).
    """
    contacts = world.ground_contacts()
    down = {side: any(cp[3] == link for cp in contacts) for side, link in world.foot_links.items()}

    def poses() -> dict:
        m = world.model
        m.forward(world.pinocchio_configuration())
        out = {}
        for side in world.foot_links:
            M = m.frame_placement(m.sole_frame[side])
            R = M.rotation
            tilt = math.degrees(math.acos(float(np.clip(R[2, 2], -1.0, 1.0))))
            out[side] = (float(M.translation[0]), float(M.translation[1]), math.atan2(R[1, 0], R[0, 0]), tilt)
        return out

    if lazy:
        return world.ground_truth_cop, down, poses
    return world.ground_truth_cop(), down, poses()
