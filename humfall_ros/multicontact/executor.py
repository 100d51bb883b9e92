"""multicontact_executor: a plan of the planar fall planner executed on the 3-D robot
(issue 14; paper 2 only re-simulated its plans in its own planar model).

A controller under the contract (``humfall_ros.control.contract``), source
``"multicontact"``: from its first tick it tracks the plan's sagittal joint
trajectories (the planar model's joints: hip pitch, knee, ankle pitch, shoulder
pitch, elbow of both sides, by name in the 3-D model's joint order) with
position and velocity targets from the plan's splines (cubic Hermite on (q, q̇)
between knots, eq. 7); every other joint is held where it was at the first tick.
Segments follow each other at their planned durations, with the **contact events**
of the feet as the switch when the centroidal state sees them: a transition that
lands a foot ends early when that foot is loaded before its planned end, and its
last knot is held (up to ``landing_wait``) while the foot is still in the air at
its planned end. Hands have no contact flag in the observation, so hand landings
switch at their planned times. After the last segment the final posture is held.

**Task-space swing** (ours, ``ExecutorConfig.swing_control`` "task", the default since session 26): a plan's
protective step (a foot released, then landed again) is not tracked joint by joint: from the release to the landing
both legs follow paper 1's step controller (``control.step_control``: the stance sole held where it is measured, the
swing sole on a world trajectory to the plan's landing relative to the stance sole, at the plan's touchdown time),
with the base held upright at the plan's pitch; tracked joint by joint the swing foot never left the ground (a
planar plan has no lateral weight transfer). The arms track the plan.

**Base pitch feedback** (ours; the paper re-simulates its plans in the planar model, open loop): the
base is unactuated, so joint tracking alone leaves its pitch to the 3-D contacts. Executed open loop,
the soles roll onto their toes (the planar feet are flat) and the base pitch runs ahead of the plan
(+0.2 rad at 0.55 s in the 20 J hand plan; the hands land 23 cm short and the robot pitches over
them onto its head). Each stance leg's hip pitch target (a foot in the segment's contact mode; a swinging
leg tracks its plan) gets ``base_pitch_gain`` x (theta - theta_plan(t)), theta the
base pitch estimated from the IMU and the joints (``base_pitch_from_imu``, no ground truth) and
theta_plan the plan's root pitch (the planar state's third coordinate, eq. 7's spline) at the same
plan time. The hip pitch axis is the base's pitch axis (y), so with the thighs held an offset of +d
pitches the pelvis by -d: a gain of 1 takes the whole error out at the hips.

**Stop balance** (ours, ``ExecutorConfig.stop_balance``, the default since session 41): after the plan's last foot
landing the plan's stop is not tracked; from the touchdown the safe fall's capture balance
(``fall.capture_balance``: a settle posture with both soles flat and the CoM over the point of the soles' segment
nearest the capture point, the ankle strategy, a hip strategy and the lateral balance) stops the robot, and once
it has stopped a second settle posture moves the CoM to the soles' middle. The planar stop brakes with contact
forces and whole-body momentum the position servos do not reproduce: tracked, it left the executed CoM ~10 cm ahead
of the plan's and the robot turned over the front foot (docs/multicontact.md "Session 40", "Session 41").
"""
from __future__ import annotations

import dataclasses
import math
from typing import Callable

import numpy as np
import pinocchio as pin
from scipy.spatial.transform import Rotation

from humfall_ros import params
from humfall_ros.control.contract import JointTargets, Observation
from humfall_ros.control.standing import lateral_roll_sensed
from humfall_ros.control.step_control import StepControlConfig, StepController, configuration_from_sensors
from humfall_ros.fall.capture_balance import CaptureBalance, CaptureBalanceConfig
from humfall_ros.model.ik import OrientationTask
from humfall_ros.model.humanoid import base_rotation_from_imu, imu_quaternion
from humfall_ros.multicontact.collocation import Segment, hermite_eval
from humfall_ros.multicontact.model import FEET
from humfall_ros.multicontact.modes import is_foot_landing


@dataclasses.dataclass(frozen=True)
class ExecutorConfig:
    """Attributes:
        landing_wait: longest hold of a foot landing's last knot waiting for touchdown [s].
        early_switch: a foot touchdown this close to the planned end (or later) may end the segment [s].
        start_time: sim time from which the executor takes over [s]; before it, it releases.
        hold: the joints the planar model does not have: ``"planar"`` holds them at the value the
            planar model locks them at (0 rad: the plan's mass distribution), ``"measured"`` where
            the servos tracked them at the take-over tick.
        both_hands: when the plan lands one hand only, the other arm tracks the landing arm's joints
            (the planar model has both hands in one plane; on the 3-D robot one hand beside two feet
            leaves the centre of mass outside the support triangle, so it rolls over that edge).
        velocity_feedforward: send the plan's joint velocities as velocity targets (else 0: the servos
            then act as a damped position loop on the plan's positions).
        blend_time: the sagittal targets go linearly from the servos' targets at the take-over to the
            plan's over this time [s] (0: the plan from the first tick).
        base_pitch_gain: the stance legs' hip pitch targets get this times the base pitch error (measured
            minus planned) [rad/rad]; 0: open loop (the executor of sessions 5-23). Needs the executor's
            ``model`` and the IMU in the observation (``inputs["imu"]``); without either, open loop.
        base_pitch_correction_max: bound on that hip offset [rad], and the offset targets stay within the
            URDF's hip limits. Runs that ended at rest saw errors <= 0.13 rad (session 24); a robot that
            has already fallen (errors of 1 rad and more) would otherwise have its hips driven to their
            stops, also after the plan's end, where the feedback keeps acting on the final posture.
        lateral_gain, lateral_damping, lateral_max: the lateral balance (ours; :meth:`MulticontactExecutor._lateral`):
            in a segment whose mode is both feet and nothing else, once the plan has landed a foot, both ankle
            rolls get d = -clip(lateral_gain e + lateral_damping e', lateral_max) and both hip rolls -d, e the
            CoM's sideways offset from the segment between the soles' centres [rad/m, rad s/m, rad]; 0 gain: the
            rolls held as ``hold`` says. A planar plan keeps the CoM between the feet; after a 0.5 m step that is
            outside the hull's diagonal side, and every executed step plan toppled sideways over it (session 39).
        swing_control: how a protective step's swing leg is driven. ``"joints"``: it tracks the plan's joints
            like every other joint (sessions 5-25). ``"task"`` (ours, default since session 26): from the
            release of a foot that the plan lands again, both legs follow the shared IK of paper 1's step controller
            (``control.step_control.StepController``: stance sole held where it is measured, swing sole on a world
            trajectory to the plan's landing placement relative to the stance sole, flat, at the plan's
            touchdown time; the stance leg's posture reference is the plan's joints of the tick); the planar plan
            has no lateral coordinate, and tracked joint by joint its swing foot never left the ground on the 3-D
            robot (session 24). Needs ``model`` and the IMU; the plan's hand plans have no foot landing and are
            tracked as before.
        swing_over_release: the task-space swing starts with the release segment (True) or with the landing
            segment (False, the release's joints tracked as planned).
        swing_clearance: the task-space swing's lift at mid-swing [m].
        landing_blend_time: after a task-space swing, the legs' targets go from the last IK command to the
            plan's over this time [s].
        swing_attitude_weight: IK weight of the base's orientation during a task-space swing (upright in roll,
            the plan's pitch; ``_attitude_task``) [-]; 0: none (the stance leg then holds the plan's joints).
        swing_attitude_gain, swing_posture_gain: per-tick gains of the task-space swing's attitude and posture
            tasks (the IK asks for gain x error / tick; 1 corrects the whole error in one tick) [-]. Session 26
            had both at 1: at the take-over the plan's posture is 0.01-0.04 rad off the measured joints (the
            projection to the two-foot mode) and the base 0.03 rad ahead of the plan's pitch, and the IK drove the
            stance leg's joints at their speed limits in the first tick, which threw the robot off the ground for
            ~0.1 s at the lift-off (docs/multicontact.md "Session 27").
        stop_balance: the stop after the plan's last foot landing is the safe fall's capture balance
            (:class:`humfall_ros.fall.capture_balance.CaptureBalance`; :meth:`MulticontactExecutor._stop_balance_due`),
            not the plan's stop (session 41). Needs ``model`` (and the task-space swing's IK, ``swing_control``
            "task"); hand plans, and plans that add a hand after their last step, are tracked to their end.
        stop_settle_s, stop_settle_target, stop_balance_kp, stop_balance_kd, stop_balance_max_offset: the capture
            balance's settle blend [s], where it holds the CoM ("spine": the point of the segment between the
            soles' centres nearest the capture point at the touchdown; "middle": the soles' middle) and its ankle
            strategy [rad/m, rad s/m, rad] (``CaptureBalanceConfig``; its lateral balance is this executor's
            ``lateral_*``).
        stop_hip_flex_rad, stop_hip_rise_s, stop_hip_hold_s, stop_hip_release_s: its hip strategy: both hips flex
            by this much from the touchdown (rise, hold, release) [rad, s]; 0: the ankle strategy alone.
        stop_shift_s, stop_shift_speed: once the hip strategy is over and the CoM is slower than
            ``stop_shift_speed`` [m/s], a second capture balance moves the CoM to the soles' middle over
            ``stop_shift_s`` [s]: the first holds it over the front sole, where the rear sole cannot reach the ground
            with the legs straight (measured: the rear foot 1-3 cm up, the robot at rest on the front foot alone);
            0: no shift.
    """

    landing_wait: float = 0.2
    early_switch: float = 0.15
    start_time: float = 0.0
    hold: str = "planar"
    both_hands: bool = True
    velocity_feedforward: bool = True
    blend_time: float = 0.0
    base_pitch_gain: float = 1.0
    base_pitch_correction_max: float = 0.3
    swing_control: str = "task"
    swing_over_release: bool = True
    swing_clearance: float = 0.1
    landing_blend_time: float = 0.1
    swing_attitude_weight: float = 100.0
    swing_attitude_gain: float = 0.2
    swing_posture_gain: float = 0.05
    lateral_gain: float = 1.5
    lateral_damping: float = 0.2
    lateral_max: float = 0.2
    stop_balance: bool = True
    stop_settle_s: float = 1.0
    stop_settle_target: str = "spine"
    stop_balance_kp: float = 0.3
    stop_balance_kd: float = 0.1
    stop_balance_max_offset: float = 0.12
    stop_hip_flex_rad: float = 0.3
    stop_hip_rise_s: float = 0.15
    stop_hip_hold_s: float = 0.6
    stop_hip_release_s: float = 1.0
    stop_shift_s: float = 1.0
    stop_shift_speed: float = 0.05

    def __post_init__(self):
        # every field is a declared parameter of config/multicontact_executor.yaml: its type, range and choices are
        # the declaration's (one place; in-process users such as multicontact_run build this dataclass directly)
        params.check_overrides("multicontact_executor", dataclasses.asdict(self), "ExecutorConfig.")

    @property
    def stop_balance_config(self) -> CaptureBalanceConfig:
        """The stop balance's capture balance (its lateral balance is this executor's ``lateral_*``)."""
        return CaptureBalanceConfig(settle_s=self.stop_settle_s, settle_target=self.stop_settle_target,
                                    kp=self.stop_balance_kp, kd=self.stop_balance_kd,
                                    max_offset=self.stop_balance_max_offset, hip_flex_rad=self.stop_hip_flex_rad,
                                    hip_rise_s=self.stop_hip_rise_s, hip_hold_s=self.stop_hip_hold_s,
                                    hip_release_s=self.stop_hip_release_s, hip_margin_m=0.0,
                                    lateral_gain=self.lateral_gain, lateral_damping=self.lateral_damping,
                                    lateral_max=self.lateral_max)

    @staticmethod
    def from_params(d: dict) -> ExecutorConfig:
        """From ExecutorConfig field names (e.g. the node's declared values); unknown keys are refused."""
        return params.config_from(ExecutorConfig, d)


PlanSource = Callable[[Observation], "list[Segment] | None"]


class MulticontactExecutor:
    """Tracks a multi-contact plan (``segments``: transitions then the terminal self-motion).

    Args:
        segments: the plan (``FallPlanner.plan(...)["segments"]`` or ``Segment.from_dict``); may be
            empty when ``plan_source`` gives it at the take-over tick.
        planar_joint_names: joint names of the plan's actuated coordinates (``PlanarModel.joint_names``).
        joint_names: the 3-D model's joints in command order (``HumanoidModel.joint_names``).
        cfg: timing and holding options.
        plan_source: called once, at the first tick at or after ``cfg.start_time`` when there are no
            ``segments``, with that tick's observation; returns the plan whose time 0 is that tick, or
            None (no plan: the executor then releases for good, ``reason`` says why). The in-process
            runner plans there with the simulator paused (``humfall_ros.sim.multicontact_run``).
        model: the 3-D robot (``HumanoidModel``, joints in ``joint_names`` order): the base pitch
            feedback estimates the base's pitch from the IMU through it; None: open loop.
    """

    source = "multicontact"

    def __init__(self, segments: list[Segment], planar_joint_names: list[str], joint_names: list[str],
                 cfg: ExecutorConfig | None = None, plan_source: PlanSource | None = None, model=None):
        if not segments and plan_source is None:
            raise ValueError("an empty plan")
        missing = [j for j in planar_joint_names if j not in joint_names]
        if missing:
            raise ValueError(f"plan joints not in the robot: {missing}")
        self._given = list(segments)
        self.cfg = cfg or ExecutorConfig()
        self.plan_source = plan_source
        self.index = np.array([joint_names.index(j) for j in planar_joint_names])
        self.n_joints = len(joint_names)
        self.planar_joint_names = list(planar_joint_names)
        if model is not None and list(model.joint_names) != list(joint_names):
            raise ValueError("the model's joints are not the command's joints")
        self.model = model
        self._data = model.model.createData() if model is not None else None
        # URDF limits of the plan's joints (planar order): the feedback's hip targets stay within them
        self._plan_limits = ((np.asarray(model.limits.lower)[self.index], np.asarray(model.limits.upper)[self.index])
                            if model is not None else (None, None))
        # the plan's hip pitch joints (planar indices) by foot: the base pitch feedback acts on the stance legs'
        self._hips = {("LF" if j.startswith("l_") else "RF"): i for i, j in enumerate(self.planar_joint_names)
                      if j.endswith("hip_pitch")}
        self.stepper = None
        if self.cfg.swing_control == "task" and model is not None:
            # the IK's forward kinematics must not overwrite a shared data
            self.stepper = StepController(model.with_own_data(), StepControlConfig(clearance=self.cfg.swing_clearance,
                                                                 posture_gain=self.cfg.swing_posture_gain))
            self._legs = np.array(model.leg_joint_indices("l") + model.leg_joint_indices("r"))
        self._lateral_model = None
        if self.cfg.lateral_gain > 0 and model is not None:
            self._lateral_model = model.with_own_data()   # the sensed configuration's kinematics
            self._rolls = (np.array([model.joint_index(f"{sd}_ankle_roll") for sd in "lr"]),
                           np.array([model.joint_index(f"{sd}_hip_roll") for sd in "lr"]))
        self.reset()

    def _arm_copy(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(to, from) planar joint indices when ``both_hands`` applies to this plan, else None."""
        if not self.cfg.both_hands:
            return None
        hands = {e for s in self.segments for e in s.target_mode if e in ("LH", "RH")}
        if len(hands) != 1:
            return None
        src = "l_" if hands == {"LH"} else "r_"
        dst = "r_" if src == "l_" else "l_"
        pairs = [(self.planar_joint_names.index(dst + j[2:]), i) for i, j in enumerate(self.planar_joint_names)
                 if j.startswith(src) and ("shoulder" in j or "elbow" in j)
                 and dst + j[2:] in self.planar_joint_names]
        return (np.array([a for a, _ in pairs]), np.array([b for _, b in pairs])) if pairs else None

    def reset(self) -> None:
        self.segments: list[Segment] = list(self._given)
        self._t0: float | None = None
        self._hold: np.ndarray | None = None
        self._seg = 0
        self._seg_start = 0.0
        self.failed = False
        self.reason = ""
        self._copy = None
        self.switches: list[tuple[int, float, str]] = []   # (segment entered, plan time, why)
        self.pitch_error_max = 0.0      # largest |base pitch - plan's| seen [rad]
        self.pitch_feedback_ticks = 0   # ticks with the feedback applied
        self.lateral_ticks = 0          # ticks with the lateral balance applied
        self.lateral_offset_max = 0.0   # largest |roll offset| it gave [rad]
        self._swings: list[tuple[str, int, int]] = []   # (foot, first segment, landing segment) of task swings
        self._swing_started: set[int] = set()           # landing segments whose task swing has started
        self._legs_last: np.ndarray | None = None       # the last IK leg command of a task swing
        self._blend: tuple[float, np.ndarray] | None = None   # (plan time, leg targets) the landing blend starts at
        self._last_time: float | None = None
        self._yaw0: float | None = None
        # per task swing: foot, landing target, start, duration, largest base pitch and heading errors
        self.task_swings: list[dict] = []
        self.stop_balance: CaptureBalance | None = None   # the stop's capture balance (stop_balance), once started
        self.stop_balance_time: float | None = None       # plan time it started [s]
        self.stop_shift: CaptureBalance | None = None     # the shift of the CoM to the soles' middle after it
        self.stop_shift_time: float | None = None         # plan time that started [s]
        self._last_command: np.ndarray | None = None      # the joint targets of the last tick

    @property
    def take_over_time(self) -> float | None:
        """Sim time of the plan's time 0 [s] (None before the take-over)."""
        return self._t0

    @property
    def segment_index(self) -> int:
        return self._seg

    @property
    def mirrored_hand(self) -> str | None:
        """The hand that copies the landing arm (``both_hands`` applied to this plan), else None."""
        if self._copy is None:
            return None
        hands = {e for s in self.segments for e in s.target_mode if e in ("LH", "RH")}
        return "RH" if hands == {"LH"} else "LH"

    # ------------------------------------------------------------------ plan
    @staticmethod
    def planar(seg: Segment, t: float) -> tuple[np.ndarray, np.ndarray]:
        """The plan's whole planar state (root x, z, pitch, then the joints) and its rate in ``seg`` at time ``t``
        from its start (clamped): the cubic Hermite spline between knots (eq. 7)."""
        t = float(np.clip(t, seg.time[0], seg.time[-1]))
        k = int(np.clip(np.searchsorted(seg.time, t, side="right") - 1, 0, len(seg.time) - 2))
        return hermite_eval(seg.time[k], seg.time[k + 1], seg.q[k], seg.v[k], seg.q[k + 1], seg.v[k + 1], t)

    @staticmethod
    def sample(seg: Segment, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Joint positions and velocities of ``seg`` at time ``t`` from its start (clamped)."""
        q, dq = MulticontactExecutor.planar(seg, t)
        return q[3:], dq[3:]

    def _pitch_error(self, observation: Observation, planned_pitch: float) -> float | None:
        """Measured minus planned base pitch [rad], or None (no model, no usable IMU reading)."""
        if self.model is None:
            return None
        theta = base_pitch_from_imu(self.model, self._data, observation.joint_position,
                                    observation.inputs.get("imu"))
        return None if theta is None else theta - planned_pitch

    def _foot_loaded(self, obs: Observation, foot: str) -> bool:
        return bool(obs.state.left_contact if foot == "LF" else obs.state.right_contact)

    def _take_over(self, observation: Observation) -> bool:
        if not self.segments:
            try:
                segs = self.plan_source(observation)
            except Exception as e:  # noqa: BLE001 - a failed plan releases, it never kills the loop
                segs, self.reason = None, f"plan source failed: {e!r}"
            if not segs:
                self.failed = True
                self.reason = self.reason or "no plan"
                return False
            self.segments = list(segs)
        self._copy = self._arm_copy()
        self._swings = self._task_swings()
        self._t0 = observation.time
        if self.cfg.hold == "planar":
            self._hold = np.zeros(self.n_joints)         # the planar model's locked joints are at 0
        else:
            self._hold = self._servo_targets(observation)
        self._start = self._servo_targets(observation)[self.index]
        return True

    def _task_swings(self) -> list[tuple[str, int, int]]:
        """The plan's foot landings that the task-space swing drives (``swing_control`` "task")."""
        if self.stepper is None:
            return []
        out = []
        for i, seg in enumerate(self.segments):
            if not is_foot_landing(seg.change, seg.extremity):
                continue
            prev = self.segments[i - 1] if i > 0 else None
            first = (i - 1 if self.cfg.swing_over_release and prev is not None and prev.change == "remove"
                     and prev.extremity == seg.extremity else i)
            out.append((seg.extremity, first, i))
        return out

    def _plan_configuration(self, seg: Segment, t: float) -> np.ndarray:
        """The 3-D configuration of the plan at ``t`` in ``seg`` (base in the sagittal plane, the joints the
        planar model lacks at 0, as it locks them)."""
        qp, _ = self.planar(seg, t)
        joints = np.zeros(self.n_joints)
        joints[self.index] = qp[3:]
        quat = Rotation.from_euler("y", float(qp[2])).as_quat()
        return self.stepper.m.configuration([qp[0], 0.0, qp[1]], quat, joints)

    def _landing_target(self, q: np.ndarray, foot: str, landing: Segment) -> pin.SE3:
        """The swing sole's landing placement in the measured world: the plan's landing sole relative to its stance
        sole at the landing's last knot (x, z: the planar plan has no lateral offset), from the measured stance sole;
        the swing sole keeps its measured lateral position and heading, and lands flat (paper 1 eq. 9's relative
        landing pose)."""
        m = self.stepper.m
        swing = "l" if foot == "LF" else "r"
        stance = "r" if swing == "l" else "l"
        m.forward(self._plan_configuration(landing, float(landing.time[-1])))
        dx = float(m.frame_placement(m.sole_frame[swing]).translation[0]
                   - m.frame_placement(m.sole_frame[stance]).translation[0])
        m.forward(q)
        st = m.frame_placement(m.sole_frame[stance]).translation
        sw = m.frame_placement(m.sole_frame[swing])
        yaw = math.atan2(sw.rotation[1, 0], sw.rotation[0, 0])
        return self.stepper.landing_placement(float(st[0]) + dx, float(sw.translation[1]), yaw, 0.0)

    def _task_swing(self, observation: Observation, tp: float, posture: np.ndarray,
                    plan_pitch: float) -> tuple[np.ndarray, np.ndarray] | None:
        """Both legs' joint position and velocity targets (``_legs`` order) of a task-space swing at this tick, or
        None (no swing now, or no usable IMU before it started: the plan's joints are tracked). ``posture``: this
        tick's joint targets; ``plan_pitch``: the plan's root pitch at this tick [rad]."""
        active = [(f, a, b) for f, a, b in self._swings if a <= self._seg <= b]
        if not active:
            return None
        foot, _, land = active[0]
        quat = imu_quaternion(observation.inputs.get("imu"))
        if quat is None:
            # no usable IMU: before the swing the plan's joints are tracked; during it the legs hold their last
            # command (a jump to the plan's joints mid-swing would kick the swing foot into the ground)
            return None if self._legs_last is None else (self._legs_last.copy(), np.zeros(len(self._legs)))
        q = configuration_from_sensors(self.stepper.m, observation.joint_position, quat, observation.state.com)
        if land not in self._swing_started:
            # the swing lasts as planned: what is left of this segment and every planned duration up to the landing
            left = float(self.segments[self._seg].time[-1]) - (tp - self._seg_start)
            left += sum(float(self.segments[k].time[-1]) for k in range(self._seg + 1, land + 1))
            target = self._landing_target(q, foot, self.segments[land])
            self.stepper.start(q, "l" if foot == "LF" else "r", target, observation.time, left)
            self._swing_started.add(land)
            self._yaw0 = None
            self.task_swings.append({"foot": foot, "start_plan_time": tp, "duration": left,
                                     "landing": [float(x) for x in target.translation]})
        dt = 0.002 if self._last_time is None else max(observation.time - self._last_time, 1e-4)
        # the IK's posture reference is this tick's plan (the stance leg, its pitch feedback included, follows it;
        # the swing sole's task overrides its own leg)
        self.stepper.posture = np.asarray(posture, float).copy()
        # the base's rotation as the IMU and the joints give it (the root link is the base: the same frame
        # ``base_pitch_from_imu`` reads)
        R = Rotation.from_quat(q[3:7]).as_matrix()
        yaw = math.atan2(R[1, 0], R[0, 0])
        log = self.task_swings[-1]
        log["pitch_error_max"] = max(log.get("pitch_error_max", 0.0), abs(pitch_of(R) - plan_pitch))
        # time with the stance foot unloaded (the estimator's contact flag): the robot off the ground mid-swing
        stance_foot = "RF" if foot == "LF" else "LF"
        log["stance_unloaded_s"] = log.get("stance_unloaded_s", 0.0) + (
            0.0 if self._foot_loaded(observation, stance_foot) else dt)
        # the heading against the swing's start: the swinging leg's momentum about the vertical turns the body
        # about the stance sole (0.1 rad in the 30 J step, 0.6 with foot_cop_margin 0.1), which the planar plan
        # cannot see
        if self._yaw0 is None:
            self._yaw0 = yaw
        log["yaw_error_max"] = max(log.get("yaw_error_max", 0.0), abs(math.remainder(yaw - self._yaw0, math.tau)))
        extra = (self._attitude_task(yaw, plan_pitch),) if self.cfg.swing_attitude_weight > 0 else ()
        pos, vel, _ = self.stepper.command(q, observation.time, dt, extra)
        return pos[self._legs], vel[self._legs]

    def _attitude_task(self, yaw: float, plan_pitch: float) -> OrientationTask:
        """The base (root link) upright in roll, at the plan's pitch of this plan time and at its measured heading
        ``yaw``.

        Through the stance leg (the IK holds the stance sole where it is) this is the hip and ankle strategy of
        the single support: without it the base ran 0.1-0.15 rad ahead of the plan's pitch and rolled 0.2 rad
        toward the swing side by the touchdown (the planar plan has no lateral weight transfer); with weight 100
        the 30 J step kept both within 0.04 rad (docs/multicontact.md "Session 26")."""
        target = Rotation.from_euler("ZY", [yaw, plan_pitch]).as_matrix()
        return OrientationTask(self.stepper.m.root_link, target, weight=self.cfg.swing_attitude_weight,
                               gain=self.cfg.swing_attitude_gain)

    @staticmethod
    def _servo_targets(observation: Observation) -> np.ndarray:
        base = observation.joint_targets if observation.joint_targets is not None else observation.joint_position
        return np.asarray(base, float).copy()

    # ------------------------------------------------------------------ step
    def step(self, observation: Observation) -> JointTargets | None:
        t = observation.time
        if self.failed or t < self.cfg.start_time - 1e-9:
            return None
        if self._t0 is None and not self._take_over(observation):
            return None
        tp = t - self._t0
        while self._seg < len(self.segments) - 1:
            seg = self.segments[self._seg]
            local = tp - self._seg_start
            T = float(seg.time[-1])
            foot_landing = is_foot_landing(seg.change, seg.extremity)
            if foot_landing and local >= T - self.cfg.early_switch and self._foot_loaded(observation, seg.extremity):
                why = "touchdown"
            elif local >= T and not foot_landing:
                why = "planned"
            elif foot_landing and local >= T + self.cfg.landing_wait:
                why = "landing wait over"
            else:
                break
            self._seg += 1
            self._seg_start = tp
            self.switches.append((self._seg, tp, why))
        seg = self.segments[self._seg]
        if self.stop_balance is not None or self._stop_balance_due(seg):
            return self._stop_balance_command(observation, tp)
        plan_q, plan_dq = self.planar(seg, tp - self._seg_start)
        q, dq = plan_q[3:], plan_dq[3:]
        if tp - self._seg_start > float(seg.time[-1]):
            dq = np.zeros_like(dq)      # holding the last knot (plan over, or waiting for a touchdown)
        if self._copy is not None:
            q, dq = q.copy(), dq.copy()
            q[self._copy[0]], dq[self._copy[0]] = q[self._copy[1]], dq[self._copy[1]]
        if self.cfg.blend_time > 0 and tp < self.cfg.blend_time:
            w = tp / self.cfg.blend_time
            q, dq = (1 - w) * self._start + w * q, w * dq
        # only the hips of the legs whose foot is on the ground in this segment: a hip offset pitches the
        # pelvis only when the thigh is held; on a swinging leg it would move the foot instead
        stance = [i for foot, i in self._hips.items() if foot in seg.mode]
        if self.cfg.base_pitch_gain > 0 and stance:
            err = self._pitch_error(observation, float(plan_q[2]))
            if err is not None:
                q = q.copy()
                bound = self.cfg.base_pitch_correction_max
                q[stance] += float(np.clip(self.cfg.base_pitch_gain * err, -bound, bound))
                lo, hi = self._plan_limits
                q[stance] = np.clip(q[stance], lo[stance], hi[stance])
                self.pitch_error_max = max(self.pitch_error_max, abs(err))
                self.pitch_feedback_ticks += 1
        pos = self._hold.copy()
        vel = np.zeros(self.n_joints)
        pos[self.index] = q
        if self.cfg.velocity_feedforward:
            vel[self.index] = dq
        if self.stepper is not None:
            legs = self._task_swing(observation, tp, pos, float(plan_q[2]))
            if legs is not None:
                pos[self._legs], vel[self._legs] = legs
                self._legs_last, self._blend = legs[0], None
            elif self._legs_last is not None and self.cfg.landing_blend_time > 0:
                # after the swing: from the IK's landing posture to the plan's legs
                if self._blend is None:
                    self._blend = (tp, self._legs_last)
                w = min(1.0, (tp - self._blend[0]) / self.cfg.landing_blend_time)
                if w < 1.0:
                    pos[self._legs] = (1 - w) * self._blend[1] + w * pos[self._legs]
                    vel[self._legs] *= w
        if self._lateral_model is not None and self._after_foot_landing(seg):
            d = self._lateral(observation)
            if d is not None:
                ankles, hips = self._rolls
                pos[ankles] += d
                pos[hips] -= d
                self.lateral_ticks += 1
                self.lateral_offset_max = max(self.lateral_offset_max, abs(d))
        self._last_time = observation.time
        self._last_command = pos
        return JointTargets(positions=pos, velocities=vel)

    def _stop_balance_due(self, seg: Segment) -> bool:
        """Does the stop's capture balance take over now (``ExecutorConfig.stop_balance``)? In a segment on both
        feet alone after a foot landing, when the rest of the plan adds no contact (the plan's stop after its last
        step)."""
        if not self.cfg.stop_balance or self.stepper is None or not self._after_foot_landing(seg):
            return False
        return not any(s.change == "add" for s in self.segments[self._seg:])

    def _stop_balance_command(self, observation: Observation, tp: float) -> JointTargets:
        """The capture balance's joint targets (no velocity feed-forward); its first call starts it, from the
        last command this executor sent."""
        c = self.cfg
        if self.stop_balance is None:
            start = self._last_command if self._last_command is not None else self._servo_targets(observation)
            self.stop_balance = CaptureBalance(self.model, c.stop_balance_config, self.stepper, start)
            self.stop_balance_time = tp
        elif (c.stop_shift_s > 0 and self.stop_shift is None and self.stop_balance.over(observation.time)
              and float(np.linalg.norm(np.asarray(observation.state.com_velocity, float)[:2])) < c.stop_shift_speed):
            # stopped over the front sole: a second settle posture moves the CoM to the soles' middle, which puts the
            # rear sole down (the first cannot reach the ground with it)
            cfg = dataclasses.replace(self.stop_balance.config, settle_s=c.stop_shift_s, settle_target="middle",
                                      hip_flex_rad=0.0)
            self.stop_shift = CaptureBalance(self.model, cfg, self.stepper, self._last_command)
            self.stop_shift_time = tp
        self._last_time = observation.time
        pos = (self.stop_shift or self.stop_balance).command(observation)
        self._last_command = pos
        return JointTargets(positions=pos, velocities=np.zeros(self.n_joints))

    def _after_foot_landing(self, seg: Segment) -> bool:
        """Is ``seg`` (the current one) on both feet and nothing else, with a foot landed earlier in the plan?"""
        if set(seg.mode) != set(FEET):
            return False
        return any(is_foot_landing(s.change, s.extremity) for s in self.segments[:self._seg])

    def _lateral(self, observation: Observation) -> float | None:
        """The lateral balance's roll offset [rad] (``ExecutorConfig.lateral_gain``,
        ``control.standing.lateral_roll_sensed``), or None (no usable IMU reading or state)."""
        c = self.cfg
        return lateral_roll_sensed(self._lateral_model, observation, c.lateral_gain, c.lateral_damping, c.lateral_max)


def base_pitch_from_imu(model, data, joint_position, imu) -> float | None:
    """The base's pitch about the world y axis [rad] from an IMU reading and the joints, as the planar
    state measures it (:func:`planar_state`), or None for a missing or unusable reading.

    ``imu``: ``Observation.inputs["imu"]`` (``model.imu_quaternion`` reads it);
    ``data``: a pinocchio data of ``model.model`` (overwritten). The IMU's rotation in the base comes from
    the joints (``model.base_rotation_from_imu``: the estimator's construction)."""
    quat = imu_quaternion(imu)
    joints = np.asarray(joint_position, float).reshape(-1)
    if quat is None or joints.shape != (len(model.joint_names),) or not np.all(np.isfinite(joints)):
        return None
    pin.framesForwardKinematics(model.model, data, model.configuration([0, 0, 0], [0, 0, 0, 1], joints))
    return pitch_of(base_rotation_from_imu(model, data, quat / np.linalg.norm(quat)))


def pitch_of(R) -> float:
    """The planar pitch of a world rotation [rad]: the rotation about the world y axis that the planar model's
    root angle measures (the body's x axis against the world's, in the x-z plane)."""
    return float(np.arctan2(R[0, 2], R[2, 2]))


def planar_state(planar_model, joint_names: list[str], q3, v3) -> tuple[np.ndarray, np.ndarray]:
    """The planar planner's state (x, z, pitch, sagittal joints) of a 3-D free-flyer state.

    ``q3``, ``v3``: pinocchio free-flyer configuration (base position, quaternion xyzw,
    joints in ``joint_names`` order) and velocity (base twist in the base frame, joint
    rates), e.g. ``SimWorld.pinocchio_state()``. The planar root is the same root link
    (a PX-PZ-RY composite joint, so its rates are the world x, z velocities and the
    pitch rate); out-of-plane motion is dropped, not checked.
    """
    q3 = np.asarray(q3, float)
    v3 = np.asarray(v3, float)
    R = Rotation.from_quat(q3[3:7]).as_matrix()
    q = np.zeros(planar_model.n)
    v = np.zeros(planar_model.n)
    q[0], q[1] = q3[0], q3[2]
    q[2] = pitch_of(R)
    lin, ang = R @ v3[:3], R @ v3[3:6]
    v[0], v[1], v[2] = lin[0], lin[2], ang[1]
    for i, j in enumerate(planar_model.joint_names):
        k = joint_names.index(j)
        q[3 + i] = q3[7 + k]
        v[3 + i] = v3[6 + k]
    return q, v


@dataclasses.dataclass(frozen=True)
class ModeProjection:
    """A measured planar state made consistent with a contact mode (:func:`project_to_mode`).

    Attributes:
        q, v: the projected state (the planner's request).
        q_shift: largest change of a coordinate [m or rad].
        gap_before: largest |signed distance| of a contact point of the mode before [m].
        slip_before: largest |J v| of the mode's rows before [m/s].
        ke_before, ke_after: planar kinetic energy before and after [J].
    """

    q: np.ndarray
    v: np.ndarray
    q_shift: float
    gap_before: float
    slip_before: float
    ke_before: float
    ke_after: float


def project_to_mode(planar_model, q, v, mode, env=None, iterations: int = 20, tol: float = 1e-9) -> ModeProjection:
    """The nearest state of ``mode``: contact points on their surfaces, contact velocities zero.

    A pushed 3-D robot is never exactly in a planar contact mode (a heel a few mm up, the soles
    sliding a little); the planner refuses a state whose contacts are off by more than its
    tolerances. Positions: Gauss-Newton on the normal rows' signed distances (eq. 3), each step
    the minimum-norm correction ``-J_n^+ phi``. Velocities: the impact map of eq. 10 with the
    mode's rows (the D-metric projection onto the null space of the contact Jacobian, i.e.
    what a perfectly plastic contact would do; it can only remove energy).
    """
    from humfall_ros.multicontact import contacts as C
    from humfall_ros.multicontact.modes import Environment

    env = env or Environment()
    q0 = np.asarray(q, float)
    v0 = np.asarray(v, float)
    rows = C.contact_rows(mode, env)
    normal = [r for r in rows if r.axis == "n"]

    def gaps(qq):
        return np.array([C.signed_distance(planar_model, r.point, r.surface, env, qq) for r in normal])

    qp = q0.copy()
    gap0 = float(np.abs(gaps(q0)).max()) if normal else 0.0
    for _ in range(iterations):
        phi = gaps(qp)
        if not len(phi) or np.abs(phi).max() < tol:
            break
        J = C.rows_jacobian(planar_model, normal, qp)
        qp = qp - np.linalg.pinv(J) @ phi
    slip0 = float(np.abs(C.rows_jacobian(planar_model, rows, qp) @ v0).max()) if rows else 0.0
    vp = C.impact_map(planar_model, qp, v0, rows)[0] if rows else v0.copy()
    return ModeProjection(q=qp, v=vp, q_shift=float(np.abs(qp - q0).max()), gap_before=gap0, slip_before=slip0,
                          ke_before=float(planar_model.kinetic_energy(q0, v0)),
                          ke_after=float(planar_model.kinetic_energy(qp, vp)))


@dataclasses.dataclass(frozen=True)
class PlannedContact:
    """A contact event of a plan: ``extremity`` lands (``change`` "add") or lifts ("remove").

    Attributes:
        time: plan time of the event [s] (the end of its transition segment).
        position: the extremity's planar point (x, z) at the event [m] (a foot: mean of toe and heel).
    """

    extremity: str
    change: str
    time: float
    position: tuple[float, float]


def planned_contacts(planar_model, segments: list[Segment]) -> list[PlannedContact]:
    """The contact events of a plan at their planned times (transitions end at the event)."""
    out = []
    t = 0.0
    for seg in segments:
        t += float(seg.time[-1])
        if seg.kind != "transition" or not seg.extremity:
            continue
        qe = seg.q[-1]
        if seg.extremity in FEET:
            p = 0.5 * (np.asarray(planar_model.point(f"{seg.extremity}_toe", qe))
                       + np.asarray(planar_model.point(f"{seg.extremity}_heel", qe)))
        else:
            p = np.asarray(planar_model.point(seg.extremity, qe))
        out.append(PlannedContact(seg.extremity, seg.change, t, (float(p[0]), float(p[1]))))
    return out


PLAN_FILE_FORMAT = "humfall_multicontact_plan/1"


@dataclasses.dataclass
class StoredPlan:
    """A plan to execute later (the executor node's ``plan_file``).

    Attributes:
        segments: the plan.
        take_over_time: sim time the plan's time 0 belongs to [s] (the tick it was planned at).
        meta: what it was planned from (scenario, push, planner options, measured state, ...).
    """

    segments: list[Segment]
    take_over_time: float
    meta: dict = dataclasses.field(default_factory=dict)

    def to_dict(self) -> dict:
        return {"format": PLAN_FILE_FORMAT, "take_over_time": self.take_over_time, "meta": self.meta,
                "segments": [s.to_dict() for s in self.segments]}

    @staticmethod
    def from_dict(d: dict) -> StoredPlan:
        if d.get("format") != PLAN_FILE_FORMAT:
            raise ValueError(f"not a plan file of format {PLAN_FILE_FORMAT!r} (format {d.get('format')!r})")
        segs = [Segment.from_dict(x) for x in d["segments"]]
        if not segs:
            raise ValueError("the plan file has no segments")
        return StoredPlan(segs, float(d["take_over_time"]), dict(d.get("meta") or {}))

    def save(self, path) -> None:
        import json
        import pathlib

        pathlib.Path(path).write_text(json.dumps(self.to_dict()))

    @staticmethod
    def load(path) -> StoredPlan:
        import json
        import pathlib

        return StoredPlan.from_dict(json.loads(pathlib.Path(path).read_text()))


__all__ = ["ExecutorConfig", "StoredPlan", "ModeProjection", "MulticontactExecutor", "PlannedContact", "planar_state",
           "planned_contacts", "project_to_mode"]
