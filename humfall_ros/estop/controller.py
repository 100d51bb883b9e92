"""EstopController: the e-stop as a controller-contract source ("estop"). No rclpy, no simulator.

States (:class:`EstopState`; the transition rules are :data:`TRANSITIONS`, printable and tested):

* ``idle`` -- releases every tick (``step`` returns None) and watches for a trigger:
  ``observation.inputs["estop"]`` (a new :class:`TopicEvent` from the latched ``estop`` topic, or
  the rising edge of a truthy level), or the scheduled trigger
  (``trigger_time``: the first tick stamped at or after it; ``trigger_step`` + ``trigger_phase``:
  the first tick of that walking step in that phase, from ``inputs["walking/state"]``; steps counted as
  the scenario's ``estop.at.step``, see :meth:`EstopController._at_phase`).
* ``waiting`` -- triggered in single support: keeps releasing (walking plays its pattern) until
  the first double-support tick, then plans from the pattern state of that tick.
* ``stopping`` -- plans at once from the current pattern state (paper 3 §III-A: reference CoG and
  velocity, reference ZMP, foot poses, CoG height; never the walking parameters or future steps)
  and plays the plan: both feet held (hard IK tasks), the CoG on the plan's reference (velocity
  feed-forward; the difference between the measured-posture CoG and the pattern's reference at
  the start is blended out over ``BLEND_TIME`` so the first command is the measured posture), the
  trunk upright, the other joints stopped by eq. 23 within ``joint_stop_time`` (shortened so no
  joint passes a limit); joint targets through the shared whole-body IK, plus the ankle strategy
  (``ankle_kp``, ``ankle_kd`` on the measured CoG's error to the reference, relative to the feet)
  as the stabiliser that makes the executed ZMP follow (eq. 2's lag).
* ``stopped`` -- the plan has reached its final point (velocity exactly 0): the upper body moves
  home (``home_duration``), then ``aligning`` (``align_feet``, the feet a step apart, the measured CoG
  slower than ``align_max_speed``) or ``holding``.
* ``aligning`` -- return home, step 3 (paper 3 §V; humfall_ros/estop/align.py): the rear foot steps beside
  the other at the standard step width (walking's preview control moves the CoG over the stance sole in
  double support, walking's swing trajectory, the CoG back to the middle), starting from the held posture's
  CoG target at rest (bumpless); then ``holding`` with the feet side by side.
* ``holding`` -- holds the final posture until a release (``inputs["estop_release"]``: a new
  :class:`TopicEvent`, acted on once, or a truthy level)
  when the measured CoG is slower than ``settle_speed``; then ``idle`` (walking takes the robot
  back from the measured posture).
* ``refused`` -- the state was outside the model's validity (CoG height, speed, non-finite,
  omega_f vs omega_c): nothing was taken over, the robot stays with walking, the reason is in the
  status; a new trigger (edge) is tried again.
* ``yielded`` -- a fall event (``inputs["fall_event"]``): safe-fall has priority. Before a
  takeover the e-stop does not take over; after one it keeps commanding its last targets (the
  mux gives safe_fall precedence; if nobody else commands the robot still has this one).

Bumpless take-over: ``observation.joint_targets`` (the targets the mux applied during the last tick,
model order), when known, seeds the IK instead of the measured joints: position servos sag under load,
and commanding the measured posture relaxes every loaded joint at once (measured: a 100 N standing
push, take-over at the toe, bounced both feet off the ground).

Bad input, each logged to ``messages``: a trigger before the state is known is kept pending and
acted on at the first tick with a known state; a second trigger during a stop is ignored; a
release while moving is refused (the robot is held); the e-stop never returns None once it
has taken over, until a granted release.

The pattern state comes from ``inputs["walking/state"]`` (``humfall_ros.walking.controller.WalkingState``;
fields read: ``walking``, ``support``, ``phase_fraction``, ``step_index``, ``com_ref``,
``com_velocity_ref``, ``zmp_ref``, ``left_foot``, ``right_foot`` -- sole poses ``(x, y, z, yaw)``)
while walking, and from the centroidal state when standing (CoM, CoM velocity, measured CoP as the
ZMP, the soles from walking's state or, without one, from the measured joints with the feet flat,
their mean heading 0 and their ankles' mid-point at ``state.feet_center``).
"""
from __future__ import annotations

import dataclasses
import enum
import math

import numpy as np
import pinocchio as pin

from humfall_ros.control.contract import JointTargets, Observation, stamp_ns_of
from humfall_ros.dynamics.pendulum import GRAVITY
from humfall_ros.estop.align import AlignPlan, AlignSettings, plan_alignment
from humfall_ros.estop.config import EstopConfig, TriggerPhase
from humfall_ros.estop.frame import FootPose, PlanarMotion
from humfall_ros.estop.planner import EstopInputError, EstopPlanner, PatternState, StopPlan
from humfall_ros.estop.posture import configuration_from_feet
from humfall_ros.estop.statespace import return_home, stop_duration_within_limits
from humfall_ros.model.humanoid import SIDES, HumanoidModel, base_rotation_from_imu, quat_matrix
from humfall_ros.model.ik import ComTask, FrameTask, OrientationTask, PostureTask, WholeBodyIK
from humfall_ros.walking.compliance import planned_loads, sole_contact, sole_sinkage
from humfall_ros.walking.stabilizer import WalkingStabilizer
from humfall_ros.walking.swing import min_jerk

BLEND_TIME = 0.3          # s: the measured-posture CoG offset at the start is blended out over this


class EstopState(str, enum.Enum):
    IDLE = "idle"
    WAITING = "waiting"
    STOPPING = "stopping"
    STOPPED = "stopped"
    ALIGNING = "aligning"
    HOLDING = "holding"
    REFUSED = "refused"
    YIELDED = "yielded"


TRANSITIONS: dict[EstopState, tuple[tuple[str, EstopState], ...]] = {
    EstopState.IDLE: (("trigger in double support / standing", EstopState.STOPPING),
                      ("trigger in single support", EstopState.WAITING),
                      ("trigger, state invalid", EstopState.REFUSED),
                      ("trigger while falling", EstopState.YIELDED)),
    EstopState.WAITING: (("first double-support tick", EstopState.STOPPING),
                         ("state invalid at double support", EstopState.REFUSED),
                         ("fall event", EstopState.YIELDED)),
    EstopState.STOPPING: (("plan reaches its end (velocity 0)", EstopState.STOPPED),
                          ("fall event", EstopState.YIELDED)),
    EstopState.STOPPED: (("upper body home, feet side by side or align_feet off", EstopState.HOLDING),
                         ("upper body home, feet a step apart, CoG at rest, align_feet", EstopState.ALIGNING),
                         ("fall event", EstopState.YIELDED)),
    EstopState.ALIGNING: (("step done, CoG back in the middle", EstopState.HOLDING),
                          ("fall event", EstopState.YIELDED)),
    EstopState.HOLDING: (("release, CoG at rest", EstopState.IDLE), ("fall event", EstopState.YIELDED)),
    EstopState.REFUSED: (("new trigger", EstopState.STOPPING), ("release", EstopState.IDLE)),
    EstopState.YIELDED: (("release, not taken over", EstopState.IDLE),),
}


@dataclasses.dataclass(frozen=True)
class EstopStatus:
    """The ``estop/status`` message (units in brackets; NaN / empty before a plan).

    Attributes:
        stamp_ns: tick [ns].
        state: :class:`EstopState` value.
        active: the e-stop has taken over (walking must release; False while ``waiting``).
        phase_at_trigger: walking's support at the trigger ("double", "single_left", "single_right",
            "standing", "" before one).
        step_at_trigger: walking's step index at the trigger (-1 before one).
        phase_fraction_at_trigger: elapsed fraction of that support phase.
        trigger_time, start_time: sim time of the trigger and of the stop's start [s].
        omega_c, alpha, beta, omega_f: [1/s] (alpha = -omega_c at the trigger height).
        gains_minor: k_x1..3 of eq. 4; gains_major: k_y1, k_y2 of eq. 12 (eq. 19-20).
        poles_minor_re, poles_minor_im: Minor-axis poles [1/s].
        n_major: n1, n2, n3 of eq. 16 [m]; n_minor_re/_im: residues of pbar_x at the poles [m].
        max_zmp_minor, max_zmp_major: predicted ZMP (lagged, eq. 2) of largest displacement [m] (signed).
        max_lipm_zmp_minor, max_lipm_zmp_major: the same for the generated CoG's LIPM ZMP [m].
        n3_lower_bound: eq. 22, y0 + ydot0 / omega_c [m].
        min_zmp_margin: smallest predicted ZMP distance inside the double-support polygon [m].
        predicted_stop_time: when the predicted CoG speed falls below settle_speed [s after start].
        crouch: the stop crouches; crouch_height: the final CoG height [m].
        feasible: predicted feasible (ZMP margin and final posture); fallback: "" or the fallback run.
        final_com: the planned final CoG [m] (3,), world.
        reason: why infeasible / refused / yielded, or "".
        frame_origin: world xy of the stop frame's origin [m] (2,); major_axis: its unit Major axis (2,).
        feet_frame_origin, feet_major_axis: the same frame carried onto the measured feet at the stop's start
            (:func:`measured_sole_centers`, ``StopFrame.moved`` by ``PlanarMotion.between_feet``): the frame the
            result's figures are measured in (the robot may have yawed / drifted off its pattern).
        feet_support_polygon: the stop's double-support polygon carried the same way [m] ((k, 2) as a tuple).
        feet_yaw_off_pattern: that motion's yaw [rad] (measured feet minus the pattern's).
        align_start_time, align_end_time: sim time the alignment step started / ended [s] (NaN: none).
        align_swing: the side that steps ("" none); align_offset: its planned offset from side by side along the
            feet's heading at the start [m] (signed, behind < 0).
        com_ref, com_velocity_ref, zmp_ref: this tick's references of the stop [m, m/s, m] (3,), world
            (NaN when not playing a plan): what plan-vs-measured plots read from a bag.
    """

    stamp_ns: int = 0
    state: str = EstopState.IDLE.value
    active: bool = False
    phase_at_trigger: str = ""
    step_at_trigger: int = -1
    phase_fraction_at_trigger: float = math.nan
    trigger_time: float = math.nan
    start_time: float = math.nan
    omega_c: float = math.nan
    alpha: float = math.nan
    beta: float = math.nan
    omega_f: float = math.nan
    gains_minor: tuple = (math.nan,) * 3
    gains_major: tuple = (math.nan,) * 2
    poles_minor_re: tuple = (math.nan,) * 3
    poles_minor_im: tuple = (math.nan,) * 3
    n_major: tuple = (math.nan,) * 3
    n_minor_re: tuple = (math.nan,) * 3
    n_minor_im: tuple = (math.nan,) * 3
    max_zmp_minor: float = math.nan
    max_zmp_major: float = math.nan
    max_lipm_zmp_minor: float = math.nan
    max_lipm_zmp_major: float = math.nan
    n3_lower_bound: float = math.nan
    min_zmp_margin: float = math.nan
    predicted_stop_time: float = math.nan
    crouch: bool = False
    crouch_height: float = math.nan
    feasible: bool = False
    fallback: str = ""
    final_com: tuple = (math.nan,) * 3
    reason: str = ""
    frame_origin: tuple = (math.nan,) * 2
    major_axis: tuple = (math.nan,) * 2
    feet_frame_origin: tuple = (math.nan,) * 2
    feet_major_axis: tuple = (math.nan,) * 2
    feet_support_polygon: tuple = ()
    feet_yaw_off_pattern: float = math.nan
    align_start_time: float = math.nan
    align_end_time: float = math.nan
    align_swing: str = ""
    align_offset: float = math.nan
    com_ref: tuple = (math.nan,) * 3
    com_velocity_ref: tuple = (math.nan,) * 3
    zmp_ref: tuple = (math.nan,) * 3


@dataclasses.dataclass(frozen=True)
class TopicEvent:
    """One message of an event topic (``estop``, ``estop/release``): ``count`` numbers them [1, 2, ...].

    The node converts every message to a new count, so a second ``humfall estop`` after a release is a
    new trigger even though the latched topic's value never changes.
    """

    count: int


def status_from_plan(plan: StopPlan) -> dict:
    """The plan's fields of :class:`EstopStatus` (a dict for ``dataclasses.replace``)."""
    mi, ma = plan.minor, plan.major
    return {
        "omega_c": plan.omega_c, "alpha": plan.alpha, "beta": plan.beta, "omega_f": plan.omega_f,
        "gains_minor": tuple(float(k) for k in mi.gains), "gains_major": tuple(float(k) for k in ma.gains),
        "poles_minor_re": tuple(float(p.real) for p in mi.poles),
        "poles_minor_im": tuple(float(p.imag) for p in mi.poles),
        "n_major": tuple(float(n) for n in ma.n), "n_minor_re": tuple(float(n.real) for n in mi.n),
        "n_minor_im": tuple(float(n.imag) for n in mi.n), "max_zmp_minor": mi.max_zmp, "max_zmp_major": ma.max_zmp,
        "max_lipm_zmp_minor": mi.max_lipm_zmp, "max_lipm_zmp_major": ma.max_lipm_zmp,
        "n3_lower_bound": ma.lower_bound, "min_zmp_margin": plan.min_zmp_margin,
        "predicted_stop_time": plan.stop_time, "crouch": plan.crouch is not None,
        "crouch_height": plan.crouch.end_height if plan.crouch else plan.state.cog_height,
        "feasible": plan.feasible, "fallback": plan.fallback,
        "final_com": tuple(float(c) for c in plan.final_com), "reason": plan.reason,
        "frame_origin": tuple(float(c) for c in plan.frame.origin),
        "major_axis": tuple(float(c) for c in plan.frame.major)}


# ---------------------------------------------------------------------- pattern-state adapters
def _sole_to_ankle(model: HumanoidModel) -> dict[str, pin.SE3]:
    """The fixed transform sole frame -> ankle (foot_link) frame per side."""
    d = model.model.createData()
    pin.framesForwardKinematics(model.model, d, model.neutral())
    return {s: d.oMf[model.frame_ids[model.sole_frame[s]]].inverse() * d.oMf[model.frame_ids[model.foot_link[s]]]
            for s in SIDES}


def _yaw_matrix(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def feet_from_soles(model: HumanoidModel, soles: dict, offsets: dict | None = None) -> dict[str, FootPose]:
    """Ankle-frame :class:`FootPose` per side from flat sole poses ``(x, y, z [m], yaw [rad])``."""
    offsets = offsets or _sole_to_ankle(model)
    out = {}
    for s in SIDES:
        x, y, z, yaw = (float(v) for v in soles[s])
        M = pin.SE3(_yaw_matrix(yaw), np.array([x, y, z])) * offsets[s]
        out[s] = FootPose(M.translation.copy(), M.rotation.copy())
    return out


def feet_from_joints(model: HumanoidModel, joints, feet_center_xy, heading: float = 0.0,
                     imu_orientation=None) -> dict[str, FootPose]:
    """Flat feet on z = 0 from measured joints: mean sole yaw ``heading``, ankles' mid-point at ``feet_center_xy``.

    With ``imu_orientation`` (xyzw) the heading is the soles' mean yaw in the world instead: the trunk's IMU
    orientation through the waist kinematics, as the estimator places the feet (a robot that has turned stops in
    its own frame, not in the world's x)."""
    d = model.model.createData()
    q = model.configuration([0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0], np.asarray(joints, float))
    pin.framesForwardKinematics(model.model, d, q)
    soles = {s: d.oMf[model.frame_ids[model.sole_frame[s]]] for s in SIDES}
    if imu_orientation is not None:
        R_base = base_rotation_from_imu(model, d, imu_orientation)
        x_axes = sum(R_base @ soles[s].rotation[:, 0] for s in SIDES)
        heading = math.atan2(float(x_axes[1]), float(x_axes[0]))
    ankles = {s: d.oMf[model.frame_ids[model.foot_link[s]]] for s in SIDES}
    yaw = {s: math.atan2(soles[s].rotation[1, 0], soles[s].rotation[0, 0]) for s in SIDES}
    mean_yaw = 0.5 * (yaw["l"] + yaw["r"])
    R = _yaw_matrix(heading - mean_yaw)
    mid = 0.5 * (ankles["l"].translation + ankles["r"].translation)
    soles_flat = {}
    for s in SIDES:
        rel = R @ (soles[s].translation - mid)
        soles_flat[s] = (float(feet_center_xy[0] + rel[0]), float(feet_center_xy[1] + rel[1]), 0.0,
                         yaw[s] + heading - mean_yaw)
    return feet_from_soles(model, soles_flat)


def measured_sole_centers(model: HumanoidModel, joints, feet_center, imu_orientation=None,
                          q_fallback: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Sole centres [m] (3,) per side in the estimator's world, as ``centroidal_state`` measures the feet.

    The estimator's own construction (humfall_ros.model.estimation): the measured joints, the base orientation
    from the IMU through the waist kinematics (``imu_orientation`` xyzw; without it, that of ``q_fallback``, or
    identity), and the ankles' mid-point placed at the estimated ``feet_center`` (leg odometry: the feet drift with
    the CoG estimate, so figures relative to them do not)."""
    d = model.model.createData()
    q = model.configuration([0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0], np.asarray(joints, float))
    pin.framesForwardKinematics(model.model, d, q)
    if imu_orientation is not None:
        R = base_rotation_from_imu(model, d, imu_orientation)
    elif q_fallback is not None:
        R = _base_rotation(q_fallback)
    else:
        R = np.eye(3)
    ankles = [R @ d.oMf[model.frame_ids[model.foot_link[s]]].translation for s in SIDES]
    shift = np.asarray(feet_center, float) - 0.5 * (ankles[0] + ankles[1])
    out = {}
    for s in SIDES:
        M = d.oMf[model.frame_ids[model.foot_link[s]]]
        out[s] = FootPose(R @ M.translation + shift, R @ M.rotation).sole_center(model, s)
    return out


def pattern_state_from_walking(model: HumanoidModel, ws, offsets: dict | None = None) -> PatternState:
    """The planner's input from a ``WalkingState`` (fields in the module docstring)."""
    feet = feet_from_soles(model, {"l": ws.left_foot, "r": ws.right_foot}, offsets)
    ground = 0.5 * (float(ws.left_foot[2]) + float(ws.right_foot[2]))
    com = np.asarray(ws.com_ref, float).copy()
    return PatternState(com, np.asarray(ws.com_velocity_ref, float).copy(), np.asarray(ws.zmp_ref, float).copy(),
                        feet, float(com[2] - ground))


def _base_rotation(q: np.ndarray) -> np.ndarray:
    """World rotation of the free-flyer of ``q`` (quaternion x, y, z, w at q[3:7])."""
    x, y, z, w = (float(v) for v in q[3:7])
    return pin.Quaternion(w, x, y, z).normalized().toRotationMatrix()


def _truthy(x) -> bool:
    if x is None:
        return False
    if hasattr(x, "active"):
        return bool(x.active)
    return bool(x)


_NAN3 = (math.nan,) * 3


class EstopController:
    """The e-stop source (module docstring).

    Args:
        model: the robot model.
        config: the node's parameters.
        dt: control period [s] (the IK step).
    """

    source = "estop"

    def __init__(self, model: HumanoidModel, config: EstopConfig | None = None, dt: float = 0.002):
        self.m = model
        self.cfg = config or EstopConfig.defaults()
        self.dt = float(dt)
        self.planner = EstopPlanner(model, self.cfg)
        self.ik = WholeBodyIK(model)
        self._offsets = _sole_to_ankle(model)
        self._sole_ankle = self._offsets                 # sole frame -> ankle frame per side
        names = model.joint_names
        self._legs = np.array([n[:2] in ("l_", "r_") and any(k in n for k in ("hip", "knee", "ankle"))
                               for n in names])
        self._posture_weight = np.where(self._legs, 1e-4, 10.0)
        self._pitch = [model.joint_index(f"{s}_ankle_pitch") for s in SIDES]
        self._roll = [model.joint_index(f"{s}_ankle_roll") for s in SIDES]
        c = self.cfg
        # walking's stabiliser with only its stance loops for the stop's double support: foot force difference control
        # (loop 4 with forces, foot_force_gain) and per-foot CoP damping (loop 5, foot_cop_gain; 0 = off)
        self._foot_cop = WalkingStabilizer(model, self.dt, 0.0, 0.0, 0.0, c.foot_cop_time_constant,
                                           c.ankle_max_offset, cop_time_constant_ds=c.foot_cop_time_constant,
                                           foot_cop_gain=c.foot_cop_gain, foot_cop_min_force=c.foot_cop_min_force,
                                           foot_force_gain=c.foot_force_gain,
                                           foot_height_time_constant=c.foot_height_time_constant,
                                           foot_height_max=c.foot_height_max)
        self._sole_stiffness, self._sole_damping = sole_contact(model)
        self._fk = model.model.createData()     # one Data for the per-tick forward kinematics (no allocation per tick)
        self._weight = model.total_mass * GRAVITY
        home = getattr(model, "standing_posture", None)
        self._home = model.joint_vector(home) if isinstance(home, dict) else None
        self._phase: TriggerPhase = self.cfg.phase
        self.messages: list[str] = []
        # the last estop / estop/release TopicEvent acted on: kept across reset() (sim time going back), so a
        # message still latched in the node from before is not acted on again
        self._trigger_count = 0
        self._release_count = 0
        self.reset()

    # ------------------------------------------------------------------ contract
    def reset(self) -> None:
        self.state = EstopState.IDLE
        self.status = EstopStatus()
        self.plan: StopPlan | None = None
        self.pending = False            # a trigger waiting for a known state or a double support
        self.taken_over = False
        self.q_ik: np.ndarray | None = None
        self.last_targets: JointTargets | None = None
        self._trigger_seen = False      # edge detection of the latched trigger input (a level)
        self._scheduled_done = False
        self._t_start = math.nan
        self._t_stopped = math.nan
        self._offset0 = np.zeros(3)
        self._trunk0 = np.eye(3)
        self._hold_feet = None
        self._sink0 = {s: 0.0 for s in SIDES}
        self._plan_centres = None           # the plan's sole centres (x, y) per side, for the sinkage
        self._com_integral = np.zeros(3)
        self._sole_flat = {s: np.zeros(2) for s in SIDES}   # (pitch, roll) ankle offsets of the sole-flat loop
        self._foot_cop.reset()
        self._upper0 = None
        self._upper_v0 = None
        self._t_b = 0.0
        self._prev_ws = None
        self.now = 0.0
        self._obs_state = None
        self._rest_com = None
        self.feet_frame = None          # the stop frame on the measured feet (set at the stop's start)
        self.feet_polygon = None
        self.align: AlignPlan | None = None
        self._t_align = math.nan
        self._align_wait_logged = False

    def run_metrics(self) -> dict:
        """The run's e-stop outcome for the in-process loop's metrics (``estop_*`` keys; campaigns)."""
        st = self.status
        return {"estop_state": st.state, "estop_feasible": bool(st.feasible), "estop_crouch": bool(st.crouch),
                "estop_fallback": st.fallback or None, "estop_phase_at_trigger": st.phase_at_trigger or None,
                "estop_trigger_time_s": None if math.isnan(st.trigger_time) else float(st.trigger_time),
                "estop_n3_m": None if math.isnan(st.n_major[2]) else float(st.n_major[2]),
                "estop_min_zmp_margin_m": None if math.isnan(st.min_zmp_margin) else float(st.min_zmp_margin),
                "estop_reason": st.reason or None}

    def request_trigger(self) -> None:
        """Trigger from code (what the ``estop`` topic does)."""
        self._trigger_seen = False
        self.pending = True

    def _log(self, text: str) -> str:
        self.messages.append(text)
        return text

    def _set(self, state: EstopState, stamp_ns: int, **fields) -> None:
        if state != self.state:
            self._log(f"estop: {self.state.value} -> {state.value}" + (f" ({fields['reason']})"
                                                                       if fields.get("reason") else ""))
        self.state = state
        self.status = dataclasses.replace(self.status, stamp_ns=stamp_ns, state=state.value,
                                          active=self.taken_over, **fields)

    # ------------------------------------------------------------------ step
    def step(self, observation: Observation) -> JointTargets | None:
        inp = observation.inputs
        ws = inp.get("walking/state")
        stamp = observation.stamp_ns
        triggered = self._trigger_edge(inp.get("estop"), observation, ws)
        falling = _truthy(inp.get("fall_event"))
        release = self._release(inp.get("estop_release"))
        self.status = dataclasses.replace(self.status, stamp_ns=stamp, active=self.taken_over, com_ref=_NAN3,
                                          com_velocity_ref=_NAN3, zmp_ref=_NAN3)
        out: JointTargets | None
        if falling and self.state != EstopState.YIELDED and (self.taken_over or self.pending or triggered):
            self.pending = False
            self._set(EstopState.YIELDED, stamp, reason="fall event: safe-fall has priority")
            triggered = False
        if self.state == EstopState.YIELDED:
            out = self.last_targets if self.taken_over else None
            if release and not self.taken_over:
                self._set(EstopState.IDLE, stamp, reason="")
            self._prev_ws = ws
            return out
        if self.state in (EstopState.IDLE, EstopState.REFUSED):
            if release and self.state == EstopState.REFUSED:
                self._set(EstopState.IDLE, stamp, reason="")
            if triggered:
                self.pending = True
                self.status = dataclasses.replace(self.status, trigger_time=observation.time)
            if self.pending:
                self._begin(observation, ws)
        elif triggered:
            self._log(f"estop: trigger ignored: already {self.state.value}")
        if self.state == EstopState.WAITING and ws is not None and ws.support == "double":
            self._start(observation, ws)
        if self.state in (EstopState.STOPPING, EstopState.STOPPED, EstopState.ALIGNING, EstopState.HOLDING):
            out = self._play(observation)
            if release:
                speed = float(np.hypot(*observation.state.com_velocity_fused[:2]))
                if self.state == EstopState.HOLDING and speed < self.cfg.settle_speed:
                    self.taken_over = False
                    self._set(EstopState.IDLE, stamp, reason="")
                    self._log("estop: released; walking takes the robot back from the measured posture")
                    out = None
                else:
                    self._log(f"estop: release refused: {self.state.value}, CoG speed {speed:.3f} m/s "
                              f"(needs holding and < {self.cfg.settle_speed} m/s)")
        else:
            out = None
        self._prev_ws = ws
        self.last_targets = out if out is not None else self.last_targets
        return out

    # ------------------------------------------------------------------ triggers
    def _trigger_edge(self, x, observation: Observation, ws) -> bool:
        """A new trigger this tick: the latched input's rising edge or the scheduled tick."""
        c = self.cfg
        if isinstance(x, TopicEvent):          # a message of the estop topic: each new count is a trigger
            edge = x.count > self._trigger_count
            self._trigger_count = max(self._trigger_count, x.count)
        else:                                  # a level (in-process callers): its rising edge
            now = _truthy(x)
            edge = now and not self._trigger_seen
            self._trigger_seen = now
        due = (c.trigger_time >= 0 and observation.stamp_ns >= stamp_ns_of(c.trigger_time)) or (
            c.trigger_step >= 0 and ws is not None and self._at_phase(ws))
        if due and not self._scheduled_done:
            self._scheduled_done = True
            edge = True
        return edge

    def _release(self, x) -> bool:
        """A release this tick: a new ``estop/release`` message (acted on once), or a truthy level."""
        if isinstance(x, TopicEvent):
            new = x.count > self._release_count
            self._release_count = max(self._release_count, x.count)
            return new
        return _truthy(x)

    def _at_phase(self, ws) -> bool:
        """This tick is the configured gait phase of step ``trigger_step`` (first tick that qualifies).

        Step K is the scenario's (humfall_ros.walking.scenario): the K-th swing (0 = the first) with the
        double support before it. ``walking/state.step_index`` is j during swing j (1 = the first) and in
        the double support after it, so step K's double support shows step_index K and its single
        support step_index K + 1.
        """
        ph = self._phase
        k = self.cfg.trigger_step + (1 if ph.kind == "ss" else 0)
        if not getattr(ws, "walking", True) or int(ws.step_index) != k:
            return False
        frac = float(ws.phase_fraction)
        if ph.kind == "ds_start":
            return ws.support == "double"
        if ph.kind == "ds_mid":
            return ws.support == "double" and frac >= 0.5
        return ws.support.startswith("single") and frac >= ph.fraction

    # ------------------------------------------------------------------ planning
    def _pattern_state(self, observation: Observation, ws) -> PatternState | None:
        """Walking's pattern state, or the centroidal one when standing; None if unknown."""
        if ws is not None and getattr(ws, "walking", False):
            return pattern_state_from_walking(self.m, ws, self._offsets)
        st = observation.state
        if st is None or not np.all(np.isfinite(st.com)) or st.normal_force <= 0:
            return None
        if ws is not None and np.any(np.asarray(ws.left_foot, float) != 0):
            feet = feet_from_soles(self.m, {"l": ws.left_foot, "r": ws.right_foot}, self._offsets)
        else:
            imu = observation.inputs.get("imu")
            feet = feet_from_joints(self.m, observation.joint_position, st.feet_center[:2],
                                    imu_orientation=None if imu is None else imu[0])
        ground = float(np.mean([feet[s].sole_corners(self.m, s)[:, 2].mean() for s in SIDES]))
        return PatternState(np.asarray(st.com, float).copy(), np.asarray(st.com_velocity_fused, float).copy(),
                            np.asarray(st.cop, float).copy(), feet, float(st.com[2] - ground))

    def _begin(self, observation: Observation, ws) -> None:
        """A pending trigger: wait for double support, or start, or stay pending if the state is unknown."""
        walking = ws is not None and getattr(ws, "walking", False)
        phase = ws.support if walking else "standing"
        self.status = dataclasses.replace(
            self.status, phase_at_trigger=phase, step_at_trigger=int(ws.step_index) if walking else -1,
            phase_fraction_at_trigger=float(ws.phase_fraction) if walking else math.nan)
        if walking and ws.support != "double":
            self.pending = False
            self._set(EstopState.WAITING, observation.stamp_ns, reason="")
            return
        self._start(observation, ws)

    def _start(self, observation: Observation, ws) -> None:
        state = self._pattern_state(observation, ws)
        if state is None:
            if self.state != EstopState.WAITING:
                self.pending = True
                self._log("estop: trigger pending: the state is not known yet")
            return
        self.pending = False
        feet_side = "r" if ws is None or not getattr(ws, "walking", False) else (
            "l" if np.dot(state.feet["l"].position[:2] - state.feet["r"].position[:2],
                          np.asarray(state.com_velocity[:2], float)) < 0 else "r")   # the rear foot
        # bumpless: start from the joint targets in force if the loop gives them (a position-servoed
        # joint sags under load, so commanding the measured posture would relax every loaded joint)
        targets = observation.joint_targets
        joints = np.asarray(targets if targets is not None else observation.joint_position, float)
        q_seed = configuration_from_feet(self.m, joints, state.feet, feet_side)
        upper = ~self._legs
        upper0 = np.asarray(observation.joint_position, float)[upper].copy()
        upper_v0 = np.asarray(observation.joint_velocity, float)[upper].copy()
        lim = self.m.limits
        t_b = stop_duration_within_limits(upper0, upper_v0, lim.lower[upper], lim.upper[upper],
                                          self.cfg.joint_stop_time)
        # the final-posture check holds the upper body where eq. 23 stops it, as the stop will
        q_check = q_seed.copy()
        q_check[7:][upper] = return_home(upper0, upper_v0, t_b, t_b)[0]
        try:
            plan = self.planner.plan_with_posture(state, q_check)
        except EstopInputError as e:
            self._set(EstopState.REFUSED, observation.stamp_ns, reason=f"refused: {e}")
            return
        self.plan = plan
        self.align = None
        self._align_wait_logged = False
        self.taken_over = True
        self._t_start = observation.time
        self.q_ik = q_seed
        # the feet are held where the applied targets put them (the rear foot at its pattern pose, the other where
        # walking's sole sinkage, foot height and ankle offsets have it): holding the pattern's flat, unsunk poses
        # instead steps every leg by millimetres in one tick (measured at 1.8 km/h: both soles unloaded for 40 ms)
        self._hold_feet = self._feet_of(q_seed)
        self._plan_centres = None
        self._sink0 = self._sinkage(0.0)
        self._com_integral = np.zeros(3)
        self._offset0 = self.m.com(q_seed) - plan.sample(0.0).com
        self._trunk0 = _base_rotation(q_seed)
        self._upper0, self._upper_v0, self._t_b = upper0, upper_v0, t_b
        if not plan.feasible:
            self._log(f"estop: predicted infeasible: {plan.reason}")
        self._set(EstopState.STOPPING, observation.stamp_ns, start_time=observation.time, **status_from_plan(plan),
                  **self._feet_frame_fields(observation, plan, q_seed))

    def _feet_frame_fields(self, observation: Observation, plan: StopPlan, q_seed: np.ndarray) -> dict:
        """The stop frame and polygon carried from the pattern's feet onto the measured ones (status fields)."""
        st = observation.state
        imu = observation.inputs.get("imu")
        try:
            meas = measured_sole_centers(self.m, observation.joint_position, st.feet_center,
                                         None if imu is None else imu[0], q_seed)
            pat = {s: plan.state.feet[s].sole_center(self.m, s) for s in SIDES}
            mo = PlanarMotion.between_feet(pat["l"], pat["r"], meas["l"], meas["r"])
        except (ValueError, TypeError, AttributeError) as e:        # no usable measurement: the pattern's frame
            self._log(f"estop: measured feet unknown ({e}); the result uses the pattern's frame")
            mo = PlanarMotion(np.eye(2), np.zeros(2))
        if not (np.all(np.isfinite(mo.rotation)) and np.all(np.isfinite(mo.translation))):
            mo = PlanarMotion(np.eye(2), np.zeros(2))
        fr = plan.frame.moved(mo)
        self.feet_frame = fr
        self.feet_polygon = mo.apply(plan.support_polygon)
        return {"feet_frame_origin": tuple(float(c) for c in fr.origin),
                "feet_major_axis": tuple(float(c) for c in fr.major),
                "feet_support_polygon": tuple(tuple(float(c) for c in p) for p in self.feet_polygon),
                "feet_yaw_off_pattern": mo.yaw}

    # ------------------------------------------------------------------ execution
    def _sinkage(self, t: float, zmp=None) -> dict:
        """side -> the sinkage [m] of the stop's planned load at ``t`` on the URDF sole contact (walking/compliance.py:
        its ZMP reference split between the two soles of the plan, the damper's lead from the next tick's);
        ``zmp``: the plan's ZMP at ``t`` when the caller has it."""
        if self.cfg.sole_sinkage_gain <= 0 or self._sole_stiffness <= 0:
            return {s: 0.0 for s in SIDES}
        if self._plan_centres is None:
            feet = self.plan.state.feet
            self._plan_centres = {s: np.asarray(feet[s].sole_center(self.m, s), float)[:2] for s in SIDES}
        centres = self._plan_centres
        f = planned_loads(self.plan.sample(t).zmp if zmp is None else zmp, centres, None, self._weight)
        f_next = planned_loads(self.plan.sample(t + self.dt).zmp, centres, None, self._weight)
        return sole_sinkage(f, f_next, self.dt, self._sole_stiffness, self._sole_damping)

    def _held_feet(self, t: float, zmp=None) -> dict:
        """The held ankle placements at ``t``: as at the start, turned flat over the start blend (``flatten_held_feet``:
        the start's held poses carry walking's ankle offsets), and each pressed in by the change of its sole's planned
        sinkage since then (``sole_sinkage_gain``; the feet were held with the trigger tick's sinkage in them), so
        the load moves between the soles as the plan's ZMP does, without the robot rocking on its stiff soles."""
        g = self.cfg.sole_sinkage_gain
        hold = self._hold_feet
        if self.cfg.flatten_held_feet:
            w = self._blend_done(t)
            hold = {s: pin.SE3(h.rotation @ pin.exp3(w * pin.log3(h.rotation.T @ _yaw_matrix(
                math.atan2(h.rotation[1, 0], h.rotation[0, 0])))), h.translation) for s, h in hold.items()}
        if g <= 0:
            return hold
        sink = self._sinkage(t, zmp)
        return {s: pin.SE3(h.rotation, h.translation - np.array([0.0, 0.0, g * (sink[s] - self._sink0[s])]))
                for s, h in hold.items()}

    def _blend_done(self, t: float) -> float:
        """How far the start blend is at ``t`` [0, 1] (``blend_profile`` over ``BLEND_TIME``)."""
        u = min(max(t / BLEND_TIME, 0.0), 1.0)
        return u if self.cfg.blend_profile == "linear" else min_jerk(u)[0]

    def _feet_of(self, q: np.ndarray) -> dict[str, pin.SE3]:
        """The ankle-frame (``foot_link``) placements of configuration ``q`` per side."""
        d = self.m.model.createData()
        pin.framesForwardKinematics(self.m.model, d, q)
        return {s: d.oMf[self.m.frame_ids[self.m.foot_link[s]]].copy() for s in SIDES}

    def _yaw_off(self, imu, q: np.ndarray) -> float:
        """The measured IMU yaw minus the IMU yaw of configuration ``q`` [rad] (0 without an IMU input)."""
        if imu is None:
            return 0.0
        d = self._fk
        pin.framesForwardKinematics(self.m.model, d, q)
        R_ik = d.oMf[self.m.frame_ids[self.m.imu_frame]].rotation
        R = quat_matrix(np.asarray(imu[0], float))
        return math.remainder(math.atan2(R[1, 0], R[0, 0]) - math.atan2(R_ik[1, 0], R_ik[0, 0]), math.tau)

    def _upper_targets(self, t: float) -> np.ndarray:
        """Upper-body joints: eq. 23 stop over T_b, then (when stopped) a smooth move home."""
        pos, _ = return_home(self._upper0, self._upper_v0, self._t_b, t)
        if self.state in (EstopState.STOPPED, EstopState.ALIGNING, EstopState.HOLDING) and self._home is not None:
            s = min(max((self.now - self._t_stopped) / self.cfg.home_duration, 0.0), 1.0)
            pos = pos + min_jerk(s)[0] * (self._home[~self._legs] - pos)
            if s >= 1.0 and self.state == EstopState.STOPPED:
                self._home_reached()
        elif self.state == EstopState.STOPPED:
            self._home_reached()
        return pos

    def _home_reached(self) -> None:
        """Upper body home: align the feet by a step (§V step 3) when asked and needed, else hold."""
        c = self.cfg
        if not c.align_feet or self.align is not None:
            self._set(EstopState.HOLDING, self.status.stamp_ns, reason=self.status.reason)
            return
        speed = float(np.hypot(*self._obs_state.com_velocity_fused[:2])) if self._obs_state is not None else 0.0
        if speed >= c.align_max_speed:
            if not self._align_wait_logged:
                self._align_wait_logged = True
                self._log(f"estop: the feet step waits: CoG speed {speed:.3f} m/s >= {c.align_max_speed} m/s")
            return
        d = self.m.model.createData()
        pin.framesForwardKinematics(self.m.model, d, self.q_ik)
        soles = {s: d.oMf[self.m.frame_ids[self.m.sole_frame[s]]].copy() for s in SIDES}
        ankles = {s: d.oMf[self.m.frame_ids[self.m.foot_link[s]]] for s in SIDES}
        centers = {s: FootPose(ankles[s].translation.copy(), ankles[s].rotation.copy()).sole_center(self.m, s)
                   for s in SIDES}
        settings = AlignSettings(shift_time=c.align_shift_time, swing_time=c.align_swing_time, apex=c.align_apex,
                                 width_offset=c.align_width_offset, min_offset=c.align_min_offset)
        try:
            plan = plan_alignment(self.m, soles, centers, self._rest_com, self.dt, settings)
        except ValueError as e:
            self._log(f"estop: no feet step: {e}")
            plan = None
        if plan is None:
            self._set(EstopState.HOLDING, self.status.stamp_ns, reason=self.status.reason)
            return
        self.align = plan
        self._t_align = self.now
        self._align_stance_ankle = ankles[plan.stance].copy()
        self._log(f"estop: feet step: {plan.swing} foot {plan.offset_before:+.3f} m along, "
                  f"{plan.lateral_before:+.3f} m across from beside the {plan.stance} foot")
        self._set(EstopState.ALIGNING, self.status.stamp_ns, reason=self.status.reason, align_start_time=self.now,
                  align_swing=plan.swing, align_offset=plan.offset_before)

    def _play(self, observation: Observation) -> JointTargets:
        plan = self.plan
        self.now = observation.time
        self._obs_state = observation.state
        t = observation.time - self._t_start
        ref = plan.sample(t)
        self._rest_com = ref.com.copy()
        if ref.done and self.state == EstopState.STOPPING:
            self._t_stopped = observation.time
            self._set(EstopState.STOPPED, observation.stamp_ns, reason=self.status.reason)
        blend = 1.0 - self._blend_done(t)
        posture = self.q_ik[7:].copy()
        posture[~self._legs] = self._upper_targets(t)      # may start the feet step (home reached)
        feet = plan.state.feet
        yaw = math.atan2(*(sum(feet[s].rotation[:2, 0] for s in SIDES)[::-1]))
        tasks = None                            # the held feet, below (the feet step has its own)
        ankle_weight = {s: 1.0 for s in SIDES}
        ref_mid = 0.5 * (feet["l"].position + feet["r"].position)
        if self.align is not None:              # return home, step 3: the feet step (estop/align.py)
            a = self.align.sample(observation.time - self._t_align)
            ref = dataclasses.replace(ref, com=a.com, com_velocity=a.com_velocity, zmp=a.zmp_ref, done=a.done)
            sw = self.align.swing
            tasks = [FrameTask(self.m.foot_link[self.align.stance], self._align_stance_ankle, hard=True),
                     FrameTask(self.m.sole_frame[sw], a.swing, hard=True)]
            ankle_weight = {self.align.stance: 1.0, sw: self.align.swing_ankle_weight(observation.time - self._t_align)}
            swing_ankle = a.swing * self._sole_ankle[sw]
            ref_mid = 0.5 * (self._align_stance_ankle.translation + swing_ankle.translation)
            if a.done and self.state == EstopState.ALIGNING:
                self._set(EstopState.HOLDING, observation.stamp_ns, reason=self.status.reason,
                          align_end_time=observation.time)
        c = self.cfg
        stab = None
        if c.foot_cop_gain > 0 or c.foot_force_gain > 0:    # walking's loops 4 (forces) and 5 in double support
            stab = self._foot_cop_output(observation.state, ref, ref_mid, feet, yaw)
        if tasks is None:
            held = self._held_feet(t, ref.zmp)
            if stab is not None:
                held = {s: pin.SE3(h.rotation, h.translation + np.array([0.0, 0.0, stab.foot_z[s]]))
                        for s, h in held.items()}
            tasks = [FrameTask(self.m.foot_link[s], held[s], hard=True) for s in SIDES]
        self.status = dataclasses.replace(self.status, com_ref=tuple(map(float, ref.com)),
                                          com_velocity_ref=tuple(map(float, ref.com_velocity)),
                                          zmp_ref=tuple(map(float, ref.zmp)))
        target = ref.com + blend * self._offset0 + self._com_integral
        upright = _yaw_matrix(yaw)        # the trunk goes upright from where it was, over BLEND_TIME too
        trunk = self._trunk0 @ pin.exp3((1.0 - blend) * pin.log3(self._trunk0.T @ upright))
        tasks += [ComTask(target, weight=1000.0, velocity=None if ref.done else ref.com_velocity),
                  OrientationTask(self.m.root_link, trunk, weight=10.0),
                  PostureTask(posture, weight=self._posture_weight)]
        r = self.ik.solve(self.q_ik, tasks, self.dt)
        self.q_ik = r.q
        q = r.q[7:].copy()
        # ankle strategy on the measured CoG relative to the feet (the stabiliser of the executed stop)
        st = observation.state
        mid = ref_mid
        # the measured vectors are in the estimator's world, the reference in the pattern's: turn the measured
        # ones by the robot's yaw off its kinematic model (IMU yaw - the IK's IMU yaw; at 1.8 km/h the robot has
        # yawed 11-17 deg off its pattern, which read the CoG 0.2 m from the feet centre as 4-6 cm of error)
        Ry = _yaw_matrix(-self._yaw_off(observation.inputs.get("imu"), r.q))
        err = Ry @ (np.asarray(st.com, float) - np.asarray(st.feet_center, float)) - (ref.com - mid)
        verr = Ry @ np.asarray(st.com_velocity_fused, float) - ref.com_velocity
        R = _yaw_matrix(yaw)
        e_l, v_l = R.T @ err, R.T @ verr                      # in the feet's heading frame
        d_pitch = float(np.clip(c.ankle_kp * e_l[0] + c.ankle_kd * v_l[0], -c.ankle_max_offset, c.ankle_max_offset))
        d_roll = float(np.clip(-(c.ankle_kp * e_l[1] + c.ankle_kd * v_l[1]), -c.ankle_max_offset,
                               c.ankle_max_offset))
        # from the predicted stop time on: the integral of the horizontal CoG error relative to the feet moves the
        # IK's CoG target against it (the servos sag under the crouched load; a P-only ankle strategy leaves it)
        if t >= plan.stop_time and c.com_integral_gain > 0 and self.align is None:
            self._com_integral[:2] -= c.com_integral_gain * self.dt * err[:2]
            n = float(np.hypot(*self._com_integral[:2]))
            if n > c.com_integral_max:
                self._com_integral[:2] *= c.com_integral_max / n
        for i, s in enumerate(SIDES):            # in the feet step's single support: the stance ankle only
            q[self._pitch[i]] += ankle_weight[s] * d_pitch
            q[self._roll[i]] += ankle_weight[s] * d_roll
        if stab is not None:
            q = self._foot_cop.apply(q, stab)
        if c.sole_flat_gain > 0:
            self._update_sole_flat(observation)
            for i, s in enumerate(SIDES):
                q[self._pitch[i]] += self._sole_flat[s][0]
                q[self._roll[i]] += self._sole_flat[s][1]
        q = np.clip(q, self.m.limits.lower, self.m.limits.upper)
        return JointTargets(q, r.v[6:].copy())

    def _update_sole_flat(self, observation: Observation) -> None:
        """The sole-flat loop (``sole_flat_gain``): each ankle's (pitch, roll) offset integrates minus its sole's
        measured tilt to the ground, the soles placed by the measured joints under the IMU's trunk orientation (the
        estimator's construction). The loaded servos sag by a few mrad along each leg, which tips a held sole onto
        one edge (measured at 1.35 km/h: both soles 3.4 mrad toe-down, their heels 0.7 mm up), and a stance on two
        edges rocks the load from one sole to the other. In the feet step (its swing foot follows its own sole
        task) the offsets leak out over ``foot_cop_time_constant``; otherwise over ``sole_flat_time_constant`` (a
        loaded sole flat on the ground still tilts by its contact's elastic give, which must not be integrated)."""
        c = self.cfg
        imu = observation.inputs.get("imu")
        if self.align is not None or imu is None:
            for s in SIDES:
                self._sole_flat[s] *= max(0.0, 1.0 - self.dt / c.foot_cop_time_constant)
            return
        d = self._fk
        q = self.m.configuration([0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0],
                                 np.asarray(observation.joint_position, float))
        pin.framesForwardKinematics(self.m.model, d, q)
        R_base = base_rotation_from_imu(self.m, d, imu[0])
        forces = observation.state.foot_normal_forces
        for s in SIDES:
            up = (R_base @ d.oMf[self.m.frame_ids[self.m.foot_link[s]]].rotation).T[:, 2]   # world z in the sole
            tilt = np.array([math.asin(float(np.clip(-up[0], -1.0, 1.0))),      # pitch, > 0: toes down
                             math.asin(float(np.clip(up[1], -1.0, 1.0)))])      # roll, > 0: +y edge up
            loaded = float(forces[s]) > c.sole_flat_min_force
            rate = -(c.sole_flat_gain if loaded else 0.0) * tilt - self._sole_flat[s] / c.sole_flat_time_constant
            self._sole_flat[s] = np.clip(self._sole_flat[s] + self.dt * rate, -c.sole_flat_max, c.sole_flat_max)

    def _foot_cop_output(self, st, ref, ref_mid, feet, yaw: float):
        """Per-foot CoP damping of the stop (walking's loop 5): each loaded sole's ankle towards its share of the
        stop's ZMP reference, relative to the feet's mid-point ``ref_mid``; leaks during the feet step (its feet are
        not the held pair)."""
        both = self.align is None
        centres = {s: np.asarray(feet[s].sole_center(self.m, s), float)[:2] for s in SIDES} if both else None
        return self._foot_cop.update(st.capture_point_fused, st.cop, st.feet_center, ref.com[:2], ref.zmp,
                                     ref_mid, None, yaw, centres, None, foot_forces=st.foot_normal_forces if both
                                     else None, foot_cops=st.foot_cops, contacts=st.contacts)


__all__ = [
    "BLEND_TIME",
    "TRANSITIONS",
    "EstopController",
    "EstopState",
    "EstopStatus",
    "TopicEvent",
    "feet_from_joints",
    "feet_from_soles",
    "measured_sole_centers",
    "pattern_state_from_walking",
    "status_from_plan",
]
