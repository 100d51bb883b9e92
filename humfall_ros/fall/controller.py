"""The safe-fall controller of paper 1: optimal protective step, then inertia shaping (controller contract).

``SafeFallController.step`` releases (returns None) until ``observation.inputs["fall_event"]``
arrives; then it takes over until the robot is balanced again (the hand-back, below):

1. the decision (one tick): the edge pendulum's control duration (``dynamics.toppling``),
   the touchdown time (the control duration clipped to [min_swing_s, max_swing_s]), the
   stepping zones (``fall.stepping_zone``), the search of eq. 4 (``fall.step_search``), then the
   eq.-9 IK check of the chosen landing at the predicted landed stance foot;
2. the swing (``control.step_control``, eq. 9-10) to the landing pose, foot flat;
3. from touchdown, inertia shaping (``fall.inertia_shaping``, eq. 11-14) when enabled; after a captured
   step the capture balance (settle posture + ankle balance, ours);
4. the **hand-back** (ours; ``handback``): once the robot balances (phase ``landed`` past ``settle_s``, or
   ``hold``) and the FTB has said balanced with its fall event cleared (the ``recovered`` transition) for
   ``handback_delay_s``, ``step`` returns None (a release: contract.py) and the mux hands the robot to
   locomotion, which stands from the measured posture where the feet are. The delay lets the cleared
   ``fall_event`` reach locomotion on the graph before the release (in process it sees it on the
   recovery's tick), so both start standing on the same tick. A later fall event is a new take-over.

Inputs (``observation.inputs``): ``ftb/status`` (``fall.ftb.FtbStatus``: the event it carries; without
a status, the latched ``fall_event``), ``obstacles`` (a list
of boxes: dicts or objects with name, position (3,), size (3,), yaw, is_target), ``imu``
(orientation x, y, z, w and gyro, a tuple or an object with ``orientation``/``angular_velocity``).

Bad input never raises and never leaves the robot commandless once taken over: a target with
NaN or inside the robot, or no target, gives no step (hold the posture; the reason is in the
decision); a fall event stamped in the future (sim time went back) is ignored; an old or
inconsistent one is noted and the decision is made from the current state; a landing the IK
cannot reach falls back to the next case that needs no IK (lift or no change); any exception in
the decision or a tick holds the last command (or the measured posture) with the reason.
"""
from __future__ import annotations

import dataclasses
import math
import time
import traceback
from typing import Any

import numpy as np

from humfall_ros import params
from humfall_ros.control.contract import JointTargets, Observation
from humfall_ros.dynamics.toppling import FallOutcome, time_to_lean
from humfall_ros.fall import step_search as ss
from humfall_ros.fall.capture_balance import CaptureBalance, CaptureBalanceConfig
from humfall_ros.fall.ftb import FtbState, features_of
from humfall_ros.fall.geometry import polygon_margin_xy
from humfall_ros.fall.push_residual import PushResidual
from humfall_ros.fall.inertia_shaping import SHAPING_DIRECTIONS, ClearBox, ShapingConfig, shaping_velocities
from humfall_ros.control.step_control import (
    StepControlConfig,
    StepController,
    configuration_from_sensors,
    predicted_stance_placement,
    sensed_soles,
)
from humfall_ros.fall.stepping_zone import stepping_zone
from humfall_ros.model.humanoid import (SIDES, HumanoidModel, imu_quaternion, load_model, point_in_polygon_margin,
                                       support_polygon)


# joints inertia shaping may move, by name fragment: all of them (the paper), the pitch chain, or its upper body
# part (the hips left out: flexing them swings the legs, which kicked the target in walking_push)
RECRUIT = {"all": ("",), "pitch": ("chest_pitch", "hip_pitch", "shoulder_pitch"),
           "upper": ("chest_pitch", "shoulder_pitch")}


@dataclasses.dataclass(frozen=True)
class SafeFallConfig:
    """``config/safe_fall_controller.yaml`` (flat keys; units in the names)."""

    inertia_shaping: bool = True
    stepping: bool = True
    theta_threshold_deg: float = 15.0
    min_swing_s: float = 0.25
    max_swing_s: float = 0.25
    stale_event_s: float = 0.1
    inconsistent_com_m: float = 0.3
    min_target_distance_m: float = 0.25
    control_period_s: float = 0.002
    zone_velocity_fraction: float = 1.0
    reach_fraction: float = 0.98
    hip_drop_m: float = 0.08
    max_yaw_change_rad: float = 0.3
    cell_xy: float = 0.03
    cell_yaw: float = 0.1
    min_zone_cells: int = 150
    capture_depth_m: float = 0.04
    capture_cop_delay_s: float = 0.0
    capture_offset_m: float = 0.0
    swing_com_shift: bool = False
    max_step_length_m: float = 0.0
    fall_heading_horizon_s: float = 0.5
    fall_ranking: str = "paper"
    capture_margin: float = 0.02
    obstacle_clearance: float = 0.03
    swing_clearance: float = 0.05
    press_depth: float = 0.01
    swing_gain: float = 0.5
    ik_velocity_fraction: float = 0.95
    stance_leg_weight: float = 10.0
    replan_s: float = 0.0
    replan_single_support_s: float = 0.05
    replan_capture_away: bool = False
    replan_keep_capture: bool = True    # re-plan: keep a landing that still captures (hysteresis, ours)
    replan_max_shift_mps: float = 1.0   # re-plan: landing moves at most this x the time to touchdown (0: no bound)
    shaping_lean_deg: float = 20.0
    shaping_gain: float = 0.02
    shaping_sign: float = -1.0
    shaping_recruit: str = "all"
    shaping_damping: float = 1e-4
    shaping_velocity_fraction: float = 1.0
    shaping_direction: str = "away"
    shaping_settled_sign: float = -1.0
    shaping_settled_s: float = 0.2
    shaping_settled_only: bool = True
    ik_retry_cells: int = 4
    shaping_sweep_horizon_s: float = 0.1
    shaping_sweep_clearance_m: float = 0.15
    single_support_lift_m: float = 0.01
    capture_balance: bool = True
    balance_kp: float = 0.3
    balance_kd: float = 0.1
    balance_max_offset: float = 0.12
    balance_hip_flex_rad: float = 0.0
    balance_hip_rise_s: float = 0.15
    balance_hip_hold_s: float = 0.6
    balance_hip_release_s: float = 1.0
    balance_hip_margin_m: float = 0.0
    balance_lateral_gain: float = 0.0
    balance_lateral_damping: float = 0.2
    balance_lateral_max: float = 0.2
    settle_s: float = 0.5
    settle_target: str = "middle"
    handback: bool = True
    handback_delay_s: float = 0.02
    defer_push_residual_mps: float = 1.0
    push_residual_window_s: float = 0.02
    max_defer_s: float = 0.04
    defer_scope: str = "walking"
    max_extra_steps: int = 0
    restep_after_s: float = 0.1
    capture_abandon: bool = True
    capture_abandon_margin_m: float = 0.02

    @classmethod
    def from_params(cls, d: dict[str, Any]) -> SafeFallConfig:
        """From a ``params.defaults("safe_fall_controller")``-shaped dict; unknown keys are refused."""
        return params.config_from(cls, d, "safe_fall_controller")

    @property
    def search(self) -> ss.SearchConfig:
        return ss.SearchConfig(self.cell_xy, self.cell_yaw, self.capture_margin,
                               obstacle_clearance=self.obstacle_clearance, min_zone_cells=self.min_zone_cells,
                               capture_depth=self.capture_depth_m, cop_delay=self.capture_cop_delay_s,
                               capture_offset=self.capture_offset_m, max_step_length=self.max_step_length_m,
                               fall_ranking=self.fall_ranking, fall_heading_horizon=self.fall_heading_horizon_s)

    @property
    def step(self) -> StepControlConfig:
        return StepControlConfig(clearance=self.swing_clearance, press_depth=self.press_depth,
                                 swing_gain=self.swing_gain, velocity_fraction=self.ik_velocity_fraction,
                                 stance_leg_weight=self.stance_leg_weight)

    @property
    def balance(self) -> CaptureBalanceConfig:
        return CaptureBalanceConfig(settle_s=self.settle_s, settle_target=self.settle_target, kp=self.balance_kp,
                                    kd=self.balance_kd, max_offset=self.balance_max_offset,
                                    hip_flex_rad=self.balance_hip_flex_rad, hip_rise_s=self.balance_hip_rise_s,
                                    hip_hold_s=self.balance_hip_hold_s, hip_release_s=self.balance_hip_release_s,
                                    hip_margin_m=self.balance_hip_margin_m, lateral_gain=self.balance_lateral_gain,
                                    lateral_damping=self.balance_lateral_damping,
                                    lateral_max=self.balance_lateral_max)

    @property
    def shaping(self) -> ShapingConfig:
        return ShapingConfig(gain=self.shaping_gain, sign=self.shaping_sign, damping=self.shaping_damping,
                             direction=self.shaping_direction, sweep_horizon_s=self.shaping_sweep_horizon_s,
                             sweep_clearance_m=self.shaping_sweep_clearance_m,
                             velocity_fraction=self.shaping_velocity_fraction)


@dataclasses.dataclass
class SafeFallDecision:
    """``safe_fall/decision``: what the controller decided at take-over (world frame, ground z = 0).

    Attributes:
        stamp_ns: tick of the decision [ns].
        case: ``StepCase`` value ("step_left", "lift_right", "no_change", "no_target", ...).
        swing_side: "l", "r" or "".
        p1, q1: CoP and reference point (capture point) at the decision [m], (2,).
        p2, q2: the chosen candidate's new CoP (nearest point of its support polygon to Q2) and
            predicted reference point at touchdown [m], (2,).
        target: T [m], (2,) (NaN: none).
        alpha1: avoidance angle at the decision, angle(Q1 P1 T) [rad].
        alpha2: predicted avoidance angle of the choice, angle(Q2 P2 T) [rad] (NaN for a capture).
        captured: Q2 inside the new support polygon (no fall predicted).
        control_duration: time to theta_threshold about the leading edge [s] (inf: never by the model).
        touchdown_time: predicted time from the decision to touchdown [s].
        theta_threshold: [rad].
        landing: landing sole (x [m], y [m], yaw [rad]) (NaN without a step).
        zone_half_extent: eq. 8's (D_x [m], D_y [m], D_beta [rad]) of the chosen swing side.
        zone_size: the capped zone's bounding box (x, y) [m].
        gamma: eq. 8's equivalent common joint speed (x, y, beta rows) [rad/s].
        cell_count: cells evaluated over the step cases [-].
        search_time: wall time of pendulum + zone + search [s].
        ik_reachable: the eq.-9 IK check passed (True when no IK was needed).
        case_alpha2: best predicted alpha2 per case [rad] (NaN: capture or case absent).
        reason: why this choice (fallbacks, bad input).
        alpha2_edge: predicted avoidance angle of a predicted fall from the fall about the new support's edge
            (``fall_heading_horizon_s``; ours) [rad] (NaN for a capture).
        replans: times the landing was re-decided during the swing (``replan_s``); the fields above
            are then the last re-decision's (``replan_stamp_ns``), the case and swing side stay.
        step_index: 1 for the decision on the fall event; 2, 3, ... for a new decision after a step whose
            predicted capture failed (``max_extra_steps``; ours).
    """

    stamp_ns: int
    case: str
    swing_side: str
    p1: np.ndarray
    q1: np.ndarray
    p2: np.ndarray
    q2: np.ndarray
    target: np.ndarray
    alpha1: float
    alpha2: float
    captured: bool
    control_duration: float
    touchdown_time: float
    theta_threshold: float
    landing: np.ndarray
    zone_half_extent: np.ndarray
    zone_size: np.ndarray
    gamma: np.ndarray
    cell_count: int
    search_time: float
    ik_reachable: bool
    case_alpha2: dict
    reason: str = ""
    replans: int = 0
    replan_stamp_ns: int = 0
    alpha2_edge: float = math.nan
    step_index: int = 1


def _get(o, key, default=None):
    return o.get(key, default) if isinstance(o, dict) else getattr(o, key, default)


def _side(v) -> str:
    """A footstep's side: "l"/"r", "left"/"right" or the message's LEFT = 0 / RIGHT = 1."""
    if isinstance(v, str):
        return v[:1].lower()
    return "l" if int(v) == 0 else "r"


def planned_landing_of(gait, swing: str) -> np.ndarray | None:
    """The gait's planned landing (x [m], y [m], yaw [rad]) of the ``swing`` sole, or None.

    ``gait``: the walking controller's ``WalkingState`` (``next_footsteps``: (side, x, y, yaw, index,
    stop) tuples, the one in flight first) or its ROS message (``Footstep[]``: side 0/1, position, yaw).
    The first upcoming footstep of the swing side is the one in flight.
    """
    for f in getattr(gait, "next_footsteps", None) or []:
        if isinstance(f, (tuple, list)):
            side, x, y, yaw = _side(f[0]), float(f[1]), float(f[2]), float(f[3])
        else:
            side, x, y, yaw = _side(f.side), float(f.position.x), float(f.position.y), float(f.yaw)
        if side == swing:
            v = np.array([x, y, yaw])
            return v if np.all(np.isfinite(v)) else None
    return None


def _gait_stance(gait) -> str | None:
    """The gait's stance side in single support ("l" / "r"), "double", or None (no gait seen: standing)."""
    if gait is None:
        return None
    v = getattr(gait, "support", "double")
    if isinstance(v, str):
        return {"single_left": "l", "single_right": "r", "left": "l", "right": "r"}.get(v, "double")
    return "double"


def _walking(gait) -> bool:
    return gait is not None and bool(getattr(gait, "walking", False)) and not bool(getattr(gait, "released", False))


def fall_event_of(obs: Observation):
    """The fall event to act on this tick: the one ``ftb/status`` of this tick carries (lockstep-repeatable:
    it does not depend on when the latched ``fall_event`` arrives), else the latched ``fall_event`` input."""
    st = obs.inputs.get("ftb/status")
    if st is not None:
        return _get(st, "fall_event") or _get(st, "event")
    return obs.inputs.get("fall_event")


class SafeFallController:
    """Paper 1's fall controller (module docstring); ``source = "safe_fall"``."""

    source = "safe_fall"

    def __init__(self, model: HumanoidModel | None = None, config: SafeFallConfig | None = None):
        self.m = model or load_model()
        self.config = config or SafeFallConfig()
        self.stepper = StepController(self.m, self.config.step)
        self._sole_local = self.m.sole_corners_local["l"][:, :2].copy()
        if self.config.shaping_direction not in SHAPING_DIRECTIONS:
            raise ValueError(f"shaping_direction must be one of {', '.join(SHAPING_DIRECTIONS)}, "
                             f"got {self.config.shaping_direction!r}")
        if self.config.shaping_recruit not in RECRUIT:
            raise ValueError(f"shaping_recruit must be one of {sorted(RECRUIT)}, got {self.config.shaping_recruit!r}")
        names = RECRUIT[self.config.shaping_recruit]
        self._recruit = np.array([any(k in n for k in names) for n in self.m.joint_names])
        self.reset()

    def reset(self) -> None:
        self.taken_over = False
        self.decision: SafeFallDecision | None = None
        self.search_result: ss.StepDecision | None = None
        self.phase = "released"
        self.hold: np.ndarray | None = None
        self.last_command: np.ndarray | None = None
        self.touchdown_at: float | None = None
        self.swing_side: str | None = None
        self.target: np.ndarray | None = None
        self.reasons: list[str] = []
        self.ignored_events = 0
        self.shaping_config = self.config.shaping
        self.gait = None
        self.single_support: str | None = None
        self.balancer: CaptureBalance | None = None   # from the touchdown of a captured step
        self.swing_com_gain: dict = {}      # set at each decision (swing_com_shift)
        self.shape_allowed = self.config.inertia_shaping   # set at touchdown (a target, not a lift)
        self._swept_noted = False
        self.recovered_since: float | None = None
        self.handbacks: list[dict] = []   # one per hand-back: time [s], CoM [m], CoM speed [m/s], feet (x, y, yaw)
        self.push_residual = PushResidual(self.config.push_residual_window_s)
        self.swing_start_xy: np.ndarray | None = None   # the swing sole's x, y at the decision [m]
        self.pending_event = None            # the fall event taken over for, until its decision is made
        self.deferral: dict | None = None    # the last deferral: its start, decision time, residual at both
        self.decisions: list[SafeFallDecision] = []   # every decision of this take-over, in order
        self.restep_since: float | None = None        # a failed capture read since (debounce) [s]

    # ------------------------------------------------------------------ contract
    def step(self, obs: Observation) -> JointTargets | None:
        s = obs.state
        if s is not None and self.config.defer_push_residual_mps > 0.0:
            self.push_residual.update(obs.time, s.com, s.capture_point, s.cop)
        if not self.taken_over:
            gait = obs.inputs.get("walking/state")
            if _walking(gait):
                self.gait = gait   # the last walking state (the walking controller releases on the event)
            ev = fall_event_of(obs)
            if ev is None:
                return None
            stamp = _get(ev, "stamp_ns", obs.stamp_ns)
            if stamp > obs.stamp_ns:
                self.ignored_events += 1
                return None   # from the future: sim time went back, the event belongs to another run
            self.taken_over = True
            self.hold = np.asarray(obs.joint_position, float).copy()
            self.last_command = self.hold.copy()
            self.pending_event = ev
        if self.pending_event is not None:
            if self._defer(obs):
                return JointTargets(self.hold.copy())
            ev, self.pending_event = self.pending_event, None
            self._decide(obs, ev)
        try:
            if self._hand_back(obs):
                return None
            return self._tick(obs)
        except Exception as exc:  # noqa: BLE001
            self.phase = "hold"
            self.reasons.append(f"tick failed ({type(exc).__name__}: {exc}); holding the last command")
            self._note_failure()
            return JointTargets(self.last_command.copy())

    def _decide(self, obs: Observation, ev) -> None:
        """:meth:`_take_over` for the fall event ``ev`` (None: a new decision after a failed capture); if it fails,
        hold the last command (at the take-over: the measured posture), never crash a falling robot."""
        try:
            self._take_over(obs, ev)
        except Exception as exc:  # noqa: BLE001 - never crash a falling robot: hold the posture
            self.phase = "hold"
            self.hold = self.last_command.copy()
            self.reasons.append(f"decision failed ({type(exc).__name__}: {exc}); holding the posture")
            self._note_failure()

    def _defer(self, obs: Observation) -> bool:
        """Hold the posture and decide later while the push still acts (ours; ``fall.push_residual``): True while
        the capture point's residual exceeds ``defer_push_residual_mps`` and the deferral is shorter than
        ``max_defer_s`` (0: off); with ``defer_scope`` walking only when the fall event came while walking (the
        swing foot is already off the ground, so waiting costs no lift; standing, the wait delays the lift-off). The
        step is then chosen from the state the push leaves."""
        c = self.config
        if c.defer_push_residual_mps <= 0.0 or (c.defer_scope == "walking" and self.gait is None):
            return False
        r = self.push_residual.magnitude()
        if self.deferral is None or "decision_s" in self.deferral:   # a new take-over: its deferral starts
            self.deferral = {"start_s": obs.time, "residual_start_mps": r}
            self.phase = "deferred"
        waited = obs.time - self.deferral["start_s"]
        wait = math.isfinite(r) and r > c.defer_push_residual_mps and waited < c.max_defer_s - 1e-9
        if not wait:
            self.deferral.update(decision_s=obs.time, residual_decision_mps=r)
            if waited > 0.0:
                self.reasons.append(f"decision deferred {waited * 1000:.0f} ms: push residual "
                                    f"{self.deferral['residual_start_mps']:.2f} -> {r:.2f} m/s")
        return wait

    def _hand_back(self, obs: Observation) -> bool:
        """True on the tick the controller lets go (the module docstring's step 4); the take-over is then over."""
        c = self.config
        balancing = self.phase == "hold" or (self.phase == "landed" and self.balancer is not None
                                             and self.balancer.settled(obs.time))
        st = obs.inputs.get("ftb/status")
        balanced = fall_event_of(obs) is None and (st is None or getattr(st, "state", None) is FtbState.BALANCED)
        if not (c.handback and balancing and balanced):
            self.recovered_since = None
            return False
        if self.recovered_since is None:
            self.recovered_since = obs.time
        if obs.time - self.recovered_since < c.handback_delay_s - 1e-9:
            return False
        s = obs.state
        feet = {}
        quat = imu_quaternion(obs.inputs.get("imu"))
        if quat is not None:
            q = configuration_from_sensors(self.m, obs.joint_position, quat, s.com)
            self.m.forward(q)
            for sd in SIDES:
                M = self.m.frame_placement(self.m.sole_frame[sd])
                feet[sd] = [float(M.translation[0]), float(M.translation[1]),
                            math.atan2(M.rotation[1, 0], M.rotation[0, 0])]
        since = None if self.touchdown_at is None else obs.time - self.touchdown_at
        self.handbacks.append({"time_s": obs.time, "since_touchdown_s": since, "phase": self.phase,
                               "com": np.asarray(s.com, float).tolist(),
                               "com_speed": float(np.linalg.norm(np.asarray(s.com_velocity, float))), "feet": feet})
        self.reasons.append(f"hand-back at {obs.time:.3f} s ("
                            + (f"{since:.3f} s after touchdown" if since is not None else "no touchdown")
                            + f"): the FTB balanced, fall event cleared, for {c.handback_delay_s:.3f} s; released")
        if self.decision is not None:
            self.decision.reason = "; ".join(self.reasons)
        # the take-over is over (the decision, the reasons and the touchdown stay for the run's metrics)
        self.taken_over = False
        self.phase = "released"
        self.hold = self.last_command = None
        self.balancer = None
        self.gait = None
        self.single_support = None
        self.recovered_since = None
        self.shaping_config = c.shaping
        self.shape_allowed = c.inertia_shaping
        return True

    def _note_failure(self) -> None:
        self._traceback = traceback.format_exc()
        if self.decision is not None:
            self.decision.reason = "; ".join(self.reasons)

    # ------------------------------------------------------------------ decision
    def _target(self, obs: Observation, soles: dict) -> tuple[np.ndarray | None, str]:
        obstacles = obs.inputs.get("obstacles") or []
        targets = [o for o in obstacles if bool(_get(o, "is_target", False))]
        if not targets:
            return None, "no target to avoid: no step"
        t = np.asarray(_get(targets[0], "position", [math.nan] * 3), float).reshape(-1)[:2]
        if t.shape != (2,) or not np.all(np.isfinite(t)):
            return None, "target position is not finite: ignored, no step"
        com = np.asarray(obs.state.com, float)[:2]
        hull = support_polygon(np.vstack([soles["l"], soles["r"]]).tolist()).tolist()
        if math.hypot(t[0] - com[0], t[1] - com[1]) < self.config.min_target_distance_m or \
                polygon_margin_xy(float(t[0]), float(t[1]), hull) > 0:
            return None, f"target at {t.round(3).tolist()} is inside the robot: ignored, no step"
        return t, ""

    def _clear_boxes(self, obs: Observation) -> list[ClearBox]:
        """The obstacles as boxes the shaping's limb-sweep guard keeps the limbs clear of (finite ones only)."""
        out = []
        for o in obs.inputs.get("obstacles") or []:
            p = np.asarray(_get(o, "position", [math.nan] * 3), float).reshape(-1)
            s = np.asarray(_get(o, "size", [math.nan] * 3), float).reshape(-1)
            yaw = float(_get(o, "yaw", 0.0) or 0.0)
            if p.size == 3 and s.size == 3 and np.all(np.isfinite(p)) and np.all(np.isfinite(s)) and math.isfinite(yaw):
                out.append(ClearBox(p, 0.5 * np.abs(s), yaw))
        return out

    def _sweep_frames(self, state) -> list[str]:
        """The limb points the limb-sweep guard follows: knees, elbows, hands, and the sole corners of a foot off
        the ground (a loaded sole does not sweep: the shaping moves the body over it)."""
        frames = []
        for sd, loaded in (("l", state.left_contact), ("r", state.right_contact)):
            frames += [f"{sd}_shank", f"{sd}_forearm", self.m.hand_frame[sd]]
            if not loaded:
                frames += list(self.m.corner_frames[sd])
        return frames

    def _obstacle_footprints(self, obs: Observation) -> list[ss.Footprint]:
        out = []
        for o in obs.inputs.get("obstacles") or []:
            p = np.asarray(_get(o, "position", [math.nan] * 3), float).reshape(-1)
            s = np.asarray(_get(o, "size", [math.nan] * 3), float).reshape(-1)
            yaw = float(_get(o, "yaw", 0.0) or 0.0)
            if p.size >= 2 and s.size >= 2 and np.all(np.isfinite(p[:2])) and np.all(np.isfinite(s[:2])) \
                    and math.isfinite(yaw):
                out.append(ss.Footprint(p[:2].copy(), 0.5 * s[:2], yaw))
        return out

    def _take_over(self, obs: Observation, ev) -> None:
        c = self.config
        t_dec = time.perf_counter()
        cpu_dec = time.thread_time()
        s = obs.state
        notes = []
        ev_time = _get(ev, "stamp_ns", obs.stamp_ns) * 1e-9
        if obs.time - ev_time > c.stale_event_s:
            notes.append(f"fall event {obs.time - ev_time:.3f} s old: deciding from the current state")
        ev_com = _get(ev, "com")
        if ev_com is not None and np.all(np.isfinite(ev_com)) and \
                np.linalg.norm(np.asarray(ev_com, float) - np.asarray(s.com, float)) > c.inconsistent_com_m:
            notes.append("fall event inconsistent with the state (CoM moved): deciding from the current state")
        sensed = sensed_soles(self.m, obs.joint_position, obs.inputs.get("imu"), s.com)
        if sensed is None:
            raise ValueError("no IMU orientation in the inputs")
        q, soles = sensed
        self.q_decision = q
        placements = {sd: self.m.frame_placement(self.m.sole_frame[sd]).copy() for sd in SIDES}
        target, why = self._target(obs, soles)
        self.target = target
        if why:
            notes.append(why)
        f = features_of(s)
        theta_thr = math.radians(c.theta_threshold_deg)
        dT = math.inf
        if f.valid:
            r = time_to_lean(f.theta, f.theta_dot, theta_thr, f.pendulum_length)
            dT = r.time if r.outcome is FallOutcome.FALLS else math.inf
            edge = (f.edge_start, f.edge_end)
            normal = f.edge_normal
        else:
            edge = (np.asarray(s.cop, float)[:2], np.asarray(s.cop, float)[:2])
            normal = np.asarray(s.capture_point, float)[:2] - np.asarray(s.cop, float)[:2]
        touchdown = float(np.clip(dT, c.min_swing_s, c.max_swing_s))
        from humfall_ros.fall.stepping_zone import sole_pose_2d

        # single support (walking): one foot loaded and the other off the ground; the candidates are
        # continue the planned step (the gait's footstep in flight), re-target the swing sole, keep it lifted
        # (standing, a foot off the ground is a double-support situation: the five cases, as before)
        single, planned = None, None
        loaded = [sd for sd in SIDES if s.contacts[sd]]
        # (the gait's support and footstep belong to the walk the fall event interrupted: not to a new decision)
        gait_support = _gait_stance(self.gait) if not self.decisions else None
        if len(loaded) == 1 and gait_support == loaded[0]:
            swing_sd = "r" if loaded[0] == "l" else "l"
            if placements[swing_sd].translation[2] > c.single_support_lift_m:
                single = loaded[0]
                planned = planned_landing_of(self.gait, swing_sd) if self.gait is not None else None
                notes.append(f"single support on {single}: swing {swing_sd} at "
                             f"{placements[swing_sd].translation[2] * 100:.1f} cm, planned landing "
                             + ("unknown" if planned is None else f"{np.round(planned, 3).tolist()}"))
        self.single_support = single
        sit = ss.FallSituation(np.asarray(s.com, float), np.asarray(s.com_velocity, float), np.asarray(s.cop, float),
                               np.asarray(s.capture_point, float), edge, normal, soles,
                               {sd: sole_pose_2d(placements[sd]) for sd in SIDES}, target, touchdown, dT,
                               obstacles=self._obstacle_footprints(obs), single_support=single,
                               planned_landing=planned)
        # (ours) Q2 moved by the swing leg's own mass carried to each landing (HumanoidModel.swing_com_gain)
        self.swing_com_gain = {sd: self.m.swing_com_gain(q, sd) for sd in SIDES} if c.swing_com_shift else {}
        sit.swing_com_gain = self.swing_com_gain
        scfg = c.search
        stance_sides, pivots = ss.case_pivots(sit, scfg)
        G, V, Q = ss.predict_touchdown(s.com, s.com_velocity, pivots, touchdown, scfg.rk4_steps,
                                       cop_delay=scfg.cop_delay, offset=scfg.capture_offset)
        zones = {}
        lift_pred = {}
        velocity_td = {None: V[0]}   # the CoM velocity at touchdown by swing side (None: no change)
        for k, stance in enumerate(stance_sides, start=1):
            swing = "l" if stance == "r" else "r"
            lift_pred[swing] = (pivots[k], G[k], Q[k])
            velocity_td[swing] = V[k]
            if c.stepping and target is not None:
                zones[swing] = stepping_zone(self.m, q, swing, touchdown, Q[k] - pivots[k].mean(axis=0), G[k],
                                             c.zone_velocity_fraction, c.reach_fraction, hip_drop=c.hip_drop_m,
                                             max_yaw_change=c.max_yaw_change_rad)
        sit.zones = zones
        res = ss.search(sit, self._sole_local, scfg, prediction=(G, Q, V))
        search_time = time.perf_counter() - t_dec
        self.decision_cpu_s = time.thread_time() - cpu_dec   # the same span in this thread's CPU time [s]
        self.search_result = res
        ranked = sorted(res.cases.values(), key=lambda cr: cr.score, reverse=True)
        if not c.stepping:
            ranked = [cr for cr in ranked if cr.landing is None and cr.case.swing is None] or ranked
        chosen, reachable = None, True
        for n, cr in enumerate(ranked):
            if cr.landing is None:
                chosen = cr
                break
            swing = self.swing_of(cr.case)
            piv, G_td, Q_td = lift_pred[swing]
            stance = "r" if swing == "l" else "l"
            pv = piv.mean(axis=0)
            st_landed = predicted_stance_placement(placements[stance], pv, s.com - np.append(pv, 0.0),
                                                   G_td - np.append(pv, 0.0))
            landing = StepController.landing_placement(*cr.landing)
            ok, err = self.stepper.reachable(q, swing, st_landed, landing)
            if ok:
                chosen = cr
                break
            reachable = False
            notes.append(f"{cr.case.value} to {np.round(cr.landing, 3).tolist()} not reachable by the IK "
                         f"({err * 100:.1f} cm off)")
            if cr.case is ss.StepCase.CONTINUE_STEP or swing not in zones or c.ik_retry_cells <= 0:
                notes[-1] += ": next case"
                continue
            # the zone's reach cap is a bound, not the IK: try the case's next cells that rank above the next case,
            # skipping those as near a failed landing as the IK missed it by
            floor = ranked[n + 1].score if n + 1 < len(ranked) else -math.inf
            failed = [(np.asarray(cr.landing[:2], float), err)]
            start = np.asarray(sit.sole_poses[swing], float)[:2]
            cand = ss.ranked_cells(cr.case, ss.zone_cells(zones[swing], scfg, self._obstacle_footprints(obs), start),
                                   piv, Q_td, target, G_td, self._sole_local, scfg, start=start,
                                   v_td=velocity_td.get(swing), com_gain=self.swing_com_gain.get(swing))
            tries = 0
            for alt in cand:
                if alt.score < floor or tries >= c.ik_retry_cells:
                    break
                xy = np.asarray(alt.landing[:2], float)
                if any(np.linalg.norm(xy - f) < e for f, e in failed):
                    continue
                tries += 1
                ok, e = self.stepper.reachable(q, swing, st_landed, StepController.landing_placement(*alt.landing))
                if ok:
                    chosen, reachable = alt, True
                    notes.append(f"{cr.case.value} to {np.round(alt.landing, 3).tolist()} instead (cell tried "
                                 f"{tries} of {c.ik_retry_cells})")
                    break
                failed.append((xy, e))
            if chosen is not None:
                break
            notes[-1] += f"; {tries} further cells not reachable either: next case"
        if chosen is None:
            chosen = ranked[-1]
        self.chosen = chosen
        case = chosen.case
        swing = self.swing_of(case)
        self.swing_side = swing
        if swing is not None:
            if chosen.landing is not None:
                landing = StepController.landing_placement(*chosen.landing)
            else:  # keep it lifted: straight up (single support: no lower than it is), flat
                lp = placements[swing]
                yaw = math.atan2(lp.rotation[1, 0], lp.rotation[0, 0])
                z = max(0.10, float(lp.translation[2])) if single else 0.10
                landing = StepController.landing_placement(lp.translation[0], lp.translation[1], yaw,
                                                           z + self.stepper.config.press_depth)
            self.swing_start_xy = np.asarray(sit.sole_poses[swing], float)[:2].copy()
            self.stepper.start(q, swing, landing, obs.time, touchdown)
            self.phase = "swing"
            self.lift_off_yaw = math.atan2(placements[swing].rotation[1, 0], placements[swing].rotation[0, 0])
        else:
            self.phase = "hold"
        zone = zones.get(swing) if swing else None
        nan2 = np.full(2, np.nan)
        self.reasons.extend(notes)
        self.decision = SafeFallDecision(
            obs.stamp_ns, case.value, swing or "", res.p1.copy(), res.q1.copy(), np.asarray(chosen.p2, float)[:2],
            np.asarray(chosen.q2, float)[:2], target if target is not None else nan2, res.alpha1, chosen.alpha2,
            chosen.captured, dT, touchdown, theta_thr,
            np.asarray(chosen.landing, float) if chosen.landing is not None else np.full(3, np.nan),
            zone.half_extent_eq8.copy() if zone else np.full(3, np.nan),
            np.array(zone.size) if zone else nan2, zone.gamma.copy() if zone else np.full(3, np.nan),
            res.cell_count, search_time, reachable,
            {k.value: v.alpha2 for k, v in res.cases.items()}, "; ".join(self.reasons))
        self.decision.alpha2_edge = self._alpha2_edge(chosen, velocity_td.get(swing), target)
        self.decision.step_index = len(self.decisions) + 1
        self.decisions.append(self.decision)
        self.predicted_touchdown_time = obs.time + touchdown

    def _alpha2_edge(self, chosen, velocity, target) -> float:
        """The predicted avoidance angle of a predicted fall from the fall about the new support's edge or corner
        (the search's ``_alpha_edge`` over ``fall_heading_horizon_s``; ours, beside paper 1's angle(Q2 P2 T)) [rad]
        (NaN for a capture or without a target)."""
        if chosen.captured or target is None or velocity is None or not math.isfinite(chosen.alpha2):
            return math.nan
        p2 = np.asarray(chosen.p2, float)
        return float(ss._alpha_edge(p2[:1], p2[1:2], chosen.q2, chosen.com_touchdown, velocity, target,
                                    np.asarray(chosen.polygon, float)[None], self.config.fall_heading_horizon_s)[0])

    def swing_of(self, case: ss.StepCase) -> str | None:
        """The sole a case moves: its own for lift / step, the non-stance one for continue (single support)."""
        if case is ss.StepCase.CONTINUE_STEP:
            return None if self.single_support is None else ("r" if self.single_support == "l" else "l")
        return case.swing

    # ------------------------------------------------------------------ ticks
    def _tick(self, obs: Observation) -> JointTargets:
        c = self.config
        st = obs.inputs.get("ftb/status")
        if self.phase == "landed" and len(self.decisions) <= c.max_extra_steps:
            self._restep(obs)
        # (the capture balance goes on: the FTB's falling_timeout_s reads "fallen" for a robot rocking to a stand)
        ends = ("shaping",) if c.capture_balance else ("landed", "shaping")
        if self.phase in ends and getattr(st, "state", None) is FtbState.FALLEN:
            # the trunk is down (FTB: fallen): shaping ends with the fall (paper 1 §IV shapes until the
            # impact); kept on, its integrated joint velocities flipped the lying robot over and walked
            # it back into the target 1.3 s after it landed
            self.phase = "hold"
            self.hold = self.last_command.copy()
            self.reasons.append(f"fallen at {obs.time:.3f} s: inertia shaping ends, holding the posture")
        if self.phase == "swing":
            p = self.stepper.plan
            tau = (obs.time - p.start_time) / p.duration
            landed = tau > 0.6 and (obs.state.left_contact if p.swing == "l" else obs.state.right_contact)
            is_lift = self.chosen.landing is None
            if (landed and not is_lift) or tau > 1.3:
                if not is_lift:
                    self.touchdown_at = obs.time
                shape = c.inertia_shaping and self.target is not None and not is_lift
                self.shape_allowed = shape
                # a predicted capture holds (or balances) and shapes only once the robot is seen falling about its
                # new support; unless the capture point is already too far outside the soles to be stopped
                given_up = self.chosen.captured and shape and self._capture_given_up(obs)
                if self.chosen.captured and not is_lift and c.capture_balance and not given_up:
                    self.phase = "landed"
                else:
                    self.phase = ("shaping" if given_up or not self.chosen.captured else "landed") if shape else "hold"
                self.hold = self.last_command.copy()
                self.falling_since = None
            else:
                quat = imu_quaternion(obs.inputs.get("imu"))
                if quat is None:
                    self.reasons.append("IMU lost during the swing: holding the last command")
                    self.phase = "hold"
                    return JointTargets(self.last_command.copy())
                q = configuration_from_sensors(self.m, obs.joint_position, quat, obs.state.com)
                replan = c.replan_single_support_s if self.single_support else c.replan_s
                if not is_lift and obs.time - p.start_time < replan - 1e-9:
                    self._replan(obs, q)
                pos, vel, _ = self.stepper.command(q, obs.time, c.control_period_s)
                self.last_command = pos
                return JointTargets(pos, vel)
        if self.phase == "landed" and self.shape_allowed:
            f = features_of(obs.state, self._soles_hull(obs) if c.capture_balance else None)
            # (with the capture balance the P->G lean is not used: rocking onto a sole's corner read 20 deg)
            leaning = not c.capture_balance and f.lean_angle > math.radians(c.shaping_lean_deg)
            if f.valid and (f.separatrix_margin > 0.0 or leaning):
                self.falling_since = obs.time if self.falling_since is None else self.falling_since
                if obs.time - self.falling_since >= 0.01 - 1e-9:
                    stood = None if self.touchdown_at is None else obs.time - self.touchdown_at
                    # with the capture balance the robot has settled once the settle posture is reached (before,
                    # its rocking reads falling over the soles' hull: walking_push shaped at 0.206 s and fell)
                    wait = max(c.shaping_settled_s, c.settle_s) if c.capture_balance else c.shaping_settled_s
                    settled = stood is not None and stood >= wait - 1e-9
                    when = f"at {obs.time:.3f} s ({stood if stood is not None else math.nan:.3f} s after touchdown)"
                    if settled:
                        # a slow topple from a settled stance (ours): its own sign
                        self.phase = "shaping"
                        self.shaping_config = dataclasses.replace(c.shaping, sign=c.shaping_settled_sign)
                        self.reasons.append(f"captured step, but falling about the new support {when}: "
                                            f"inertia shaping, sign {self.shaping_config.sign:+.0f}")
                    elif c.shaping_settled_only and c.capture_balance:
                        # the landing's jolt, not a topple (walking_push: read 12 ms after touchdown; holding then
                        # let the robot fall): keep balancing, look again
                        self.falling_since = None
                    elif c.shaping_settled_only:
                        self.phase = "hold"
                        self.reasons.append(f"captured step, but falling about the new support {when}: "
                                            "no inertia shaping (shaping_settled_only)")
                    else:
                        self.phase = "shaping"
                        self.reasons.append(f"captured step, but falling about the new support {when}: "
                                            f"inertia shaping, sign {self.shaping_config.sign:+.0f}")
            else:
                self.falling_since = None
        if self.phase == "landed" and c.capture_balance:
            return self._balance(obs)
        if self.phase == "shaping":
            quat = imu_quaternion(obs.inputs.get("imu"))
            if quat is not None:
                q = configuration_from_sensors(self.m, obs.joint_position, quat, obs.state.com)
                q[7:] = self.last_command  # shape from the commanded posture (position-controlled joints lag)
                qd, info = shaping_velocities(self.m, q, obs.state.cop, self.target, c.control_period_s,
                                              recruit=self._recruit, cfg=self.shaping_config, com=obs.state.com,
                                              keep_clear=self._clear_boxes(obs),
                                              sweep_frames=self._sweep_frames(obs.state))
                if info["swept"] and not self._swept_noted:
                    self._swept_noted = True
                    name, now, nxt = info["swept"][0]
                    self.reasons.append(f"{obs.time:.3f} s: inertia shaping would sweep {name} to {nxt:.2f} m of an "
                                        f"obstacle ({now:.2f} m now): the joints carrying it there held")
                pos = np.clip(self.last_command + qd * c.control_period_s, self.m.limits.lower, self.m.limits.upper)
                self.last_command = pos
                return JointTargets(pos, qd)
        return JointTargets(self.hold.copy() if self.hold is not None else np.asarray(obs.joint_position, float))

    def _capture_given_up(self, obs: Observation) -> bool:
        """At the touchdown of a predicted capture: is the measured capture point's margin inside both soles' hull
        below ``capture_abandon_margin_m`` (``capture_abandon``; ours, session 42)? The decision's Q2 is 14-33 cm short
        of the touchdown's capture point when decided during the push (session 39), so a predicted capture may land
        beyond any balance (the ankle balance needs the capture point 2-3.5 cm inside): the step is then a fall, and
        inertia shaping starts at the touchdown as after a predicted fall (paper 1 §IV), not once the balance is seen
        failing, when the fall's direction is already set."""
        c = self.config
        hull = self._soles_hull(obs) if c.capture_abandon else None
        if hull is None:
            return False
        margin = point_in_polygon_margin(np.asarray(obs.state.capture_point, float)[:2], hull)
        if margin >= c.capture_abandon_margin_m:
            return False
        self.reasons.append(f"{obs.time:.3f} s: touchdown with the capture point {margin:+.3f} m inside the soles: "
                            "the capture is given up, inertia shaping from the touchdown")
        return True

    def _restep(self, obs: Observation) -> None:
        """After a predicted capture: once the robot is seen falling about its new support (the 2-D pendulum over
        the soles' hull past its crest for 10 ms, ``restep_after_s`` or more after the touchdown), decide again from
        this state (eq. 4 with its five cases; ours: paper 1 takes one step). The swing starts on this tick."""
        c = self.config
        if self.touchdown_at is None or obs.time - self.touchdown_at < c.restep_after_s - 1e-9:
            return
        f = features_of(obs.state, self._soles_hull(obs))
        if not (f.valid and f.separatrix_margin > 0.0):
            self.restep_since = None
            return
        self.restep_since = obs.time if self.restep_since is None else self.restep_since
        if obs.time - self.restep_since < 0.01 - 1e-9:
            return
        since = obs.time - self.touchdown_at
        self.reasons.append(f"{obs.time:.3f} s: the capture failed (falling about the new support {since:.3f} s "
                            f"after touchdown): decision {len(self.decisions) + 1}")
        self.restep_since, self.touchdown_at, self.balancer = None, None, None
        self._decide(obs, None)

    def _balance(self, obs: Observation) -> JointTargets:
        """After a captured step: the capture balance (``fall.capture_balance``: settle posture + ankle strategy,
        ours; the paper stops at the step), started on its first tick."""
        if self.balancer is None:
            self.balancer = CaptureBalance(self.m, self.config.balance, self.stepper, self.hold)
        self.last_command = self.balancer.command(obs)
        return JointTargets(self.last_command)

    @property
    def balance_margin(self) -> float:
        """The capture point's margin inside both soles' hull when the capture balance started [m] (NaN: none)."""
        return math.nan if self.balancer is None else self.balancer.margin

    def _soles_hull(self, obs: Observation):
        """The hull of both soles (touching or not) in the measured configuration [m], (k, 2), or None (no IMU).

        The new support after a step: with the capture balance the robot rocks from one sole's corner to the
        other's, and over the touching corners alone the energy read "falling" (standing_push: 0.6 s after
        touchdown, inertia shaping then took over from the balance and the robot fell)."""
        sensed = sensed_soles(self.m, obs.joint_position, obs.inputs.get("imu"), obs.state.com)
        return None if sensed is None else support_polygon(np.vstack(list(sensed[1].values())).tolist())

    def _replan(self, obs: Observation, q: np.ndarray) -> None:
        """Re-decide the landing of the chosen swing side from this tick's state (ours, not the paper's).

        The FTB may fire while the push still acts (measured: 1.3x standing_push fires at 0.578 s, the
        push ends at 0.6 s); a landing decided then misses the velocity the push still adds (the
        predicted capture point at touchdown was 0.2 m short). For the first ``replan_s`` of the swing
        the decision of eq. 4 is repeated each tick for the same swing foot, with the remaining time to
        the planned touchdown, and the swing re-targets (minimum jerk: the early change is small).
        """
        c = self.config
        plan = self.stepper.plan
        swing, stance = plan.swing, ("r" if plan.swing == "l" else "l")
        remaining = self.predicted_touchdown_time - obs.time
        if remaining < c.min_swing_s * 0.5 or self.target is None:
            return
        t0 = time.perf_counter()
        s = obs.state
        self.m.forward(q)
        soles = {sd: self.m.sole_corners(sd)[:, :2] for sd in SIDES}
        u = np.asarray(s.capture_point, float)[:2] - np.asarray(s.cop, float)[:2]
        if np.linalg.norm(u) < 1e-6:
            return
        u = u / np.linalg.norm(u)
        pivot = ss._pivot(soles, stance, u, c.search.corner_tie)
        G, _, Q = ss.predict_touchdown(s.com, s.com_velocity, [pivot], remaining, c.search.rk4_steps,
                                       cop_delay=c.search.cop_delay, offset=c.search.capture_offset)
        zone = stepping_zone(self.m, q, swing, remaining, Q[0] - pivot.mean(axis=0), G[0], c.zone_velocity_fraction,
                             c.reach_fraction, hip_drop=c.hip_drop_m, max_yaw_change=c.max_yaw_change_rad,
                             yaw_reference=self.lift_off_yaw)
        # (the step length from where the swing sole lifted off, as at the decision)
        cells = ss.zone_cells(zone, c.search, self._obstacle_footprints(obs), self.swing_start_xy)
        if c.replan_max_shift_mps > 0 and len(cells):
            # (ours) a re-target late in the swing may move the landing only as far as the swing can still follow:
            # walking_push 300 N with a 0.08 s window re-targeted 27 cm sideways 80 ms into a 0.25 s swing and landed
            # 174 ms late, 6.7 deg tilted
            cur = np.asarray(self.chosen.landing, float)
            near = np.hypot(cells[:, 0] - cur[0], cells[:, 1] - cur[1]) <= c.replan_max_shift_mps * remaining
            cells = cells[near]
            if not len(cells):
                return
        case = self.chosen.case
        if case is ss.StepCase.CONTINUE_STEP:   # re-deciding the planned step over the cells: a re-target
            case = ss.StepCase.STEP_LEFT if swing == "l" else ss.StepCase.STEP_RIGHT
        start = self.m.frame_placement(self.m.sole_frame[swing]).translation[:2]
        gain = self.swing_com_gain.get(swing)   # (from the decision's posture; the rest of the step is from here)
        r = None
        if c.replan_keep_capture and self.chosen.captured and len(cells):
            # hysteresis (ours): the landing chosen last tick stays while it still captures and the zone still
            # reaches it; re-deciding each tick from scratch let the pick jump between far-apart captures (walking_push:
            # x 1.06 <-> 1.69 m from one tick to the next), so the outcome hung on which tick the window ended at
            cur = np.asarray(self.chosen.landing, float).reshape(1, 3)
            if np.any(np.hypot(cells[:, 0] - cur[0, 0], cells[:, 1] - cur[0, 1]) <= c.search.cell_xy):
                kept = ss._cells(case, cur, pivot, Q[0], self.target, G[0], self._sole_local, c.search, start=start,
                                 com_gain=gain)
                if kept is not None and kept.captured:
                    r = kept
        if r is None and c.replan_capture_away and len(cells):
            # among the captures (Q2 >= capture_margin inside), the landing farthest from the target (ours): the
            # deepest one moves forward with the push, towards the target (walking_push 360 N: under its edge)
            h = ss._hull_core(cells, self._sole_local, pivot.reshape(-1, 2),
                              np.ascontiguousarray(ss.shifted_q2(Q[0], cells, start, gain)))
            ok = h.margin >= c.capture_margin
            if np.any(ok):
                far = np.hypot(cells[:, 0] - self.target[0], cells[:, 1] - self.target[1])
                i = int(np.argmax(np.where(ok, far, -np.inf)))
                cells = cells[i:i + 1]
        if r is None:
            r = ss._cells(case, cells, pivot, Q[0], self.target, G[0], self._sole_local, c.search, start=start,
                          com_gain=gain)
        if r is None:
            return
        if r.case is not self.chosen.case:
            self.reasons.append(f"re-plan at {obs.time:.3f} s: the planned step re-targeted ({r.case.value})")
            self.decision.case = r.case.value
        self.chosen = r
        plan.landing = StepController.landing_placement(*r.landing)
        d = self.decision
        d.p2, d.q2 = np.asarray(r.p2, float)[:2].copy(), np.asarray(r.q2, float)[:2].copy()
        d.alpha2, d.captured, d.landing = r.alpha2, r.captured, np.asarray(r.landing, float).copy()
        d.cell_count, d.search_time = r.cells, time.perf_counter() - t0
        d.replans += 1
        d.replan_stamp_ns = obs.stamp_ns

    def info(self) -> dict:
        """Predictions for comparison with the outcome."""
        out: dict = {"reasons": list(self.reasons)}
        if self.decision is not None:
            d = self.decision
            out["prediction"] = {"touchdown_time_s": getattr(self, "predicted_touchdown_time", None),
                                 "landing": None if not np.all(np.isfinite(d.landing)) else d.landing.tolist(),
                                 "alpha2_deg": math.degrees(d.alpha2) if math.isfinite(d.alpha2) else None,
                                 "case": d.case}
            out["measured_touchdown_time_s"] = self.touchdown_at
        return out


__all__ = ["SafeFallConfig", "SafeFallController", "SafeFallDecision", "fall_event_of"]
