"""LocomotionController: stands, and walks on a walking command (controller contract, source "locomotion").

No rclpy, no simulator. Standing is :class:`humfall_ros.control.standing.StandingController`
(the ankle strategy, with its bumpless hand-back). A walking command (``set_walk_command`` or
``observation.inputs["cmd_walk"]``, a :class:`WalkCommand` or ``(speed [m/s], yaw_rate [rad/s][, n_steps])``,
acted on when a new object arrives)
starts a walk: the command is checked (finite; speed and turn rate clamped to their limits with a
warning; the kinematics checked on a short offline rehearsal before the first step) and a
:class:`WalkingPattern` is started from the measured posture. Each tick: pattern step (preview
control), optional multi-body correction, stabiliser (measured capture point and CoP), whole-body
IK (both soles hard, CoM, trunk orientation, posture) -> joint targets with velocities. A zero
command plans the stop; when the stop has settled the robot stands where it stopped.

``observation.inputs.get("fall_event")`` (truthy) or an active ``inputs.get("estop")`` (truthy, or
an object whose ``active`` is true) releases the robot (``step`` returns None) and drops the
pattern; when they clear, or when ``observation.active_source`` shows another source drove the
robot, the standing controller resumes from the measured posture. Log lines for the node (warnings,
refusals with their reasons) are appended to ``messages``; :attr:`state` is the
:class:`WalkingState` of the last tick (the ``walking/state`` message).
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pinocchio as pin

from humfall_ros.control.contract import JointTargets, Observation
from humfall_ros.control.standing import StandingController
from humfall_ros.dynamics.pendulum import GRAVITY
from humfall_ros.model.humanoid import SIDES, HumanoidModel, base_rotation_from_imu, imu_quaternion, quat_matrix
from humfall_ros.model.ik import (
    ComTask,
    FrameTask,
    OrientationTask,
    PostureTask,
    WholeBodyIK,
)
from humfall_ros.walking.compliance import planned_loads, sole_contact, sole_sinkage
from humfall_ros.walking.config import LocomotionConfig
from humfall_ros.walking.footsteps import Footstep, WalkCommand, step_width
from humfall_ros.walking.multibody import MomentumZmp, MultiBodyCorrection
from humfall_ros.walking.pattern import PatternSample, SupportPhase, WalkingPattern
from humfall_ros.walking.stabilizer import WalkingStabilizer


@dataclasses.dataclass
class WalkingState:
    """What ``walking/state`` carries every tick (pattern world frame = the estimator's world, z up).

    Attributes:
        stamp_ns: the tick [ns].
        walking: a walk pattern is running (False: standing or released).
        released: the controller has released the robot (fall event / e-stop).
        support: "double", "single_left" or "single_right".
        phase_fraction: elapsed fraction of the current support phase [0, 1).
        step_index: 0 before the first swing, j during and after step j.
        com_ref: reference CoM [m] (3,); com_velocity_ref [m/s] (3,).
        zmp_ref: reference ZMP [m] (3,), z = 0.
        capture_point_ref: reference capture point [m] (3,), z = 0.
        multibody_zmp: ZMP of the planned whole-body motion [m] (3,) (NaN when not computed).
        left_foot, right_foot: current reference sole poses (x, y, z [m], yaw [rad]).
        next_footsteps: upcoming footsteps, (side "l"/"r", x [m], y [m], yaw [rad], index, stop), in flight first.
        speed, yaw_rate: the command in force [m/s], [rad/s].
    """

    stamp_ns: int = 0
    walking: bool = False
    released: bool = False
    support: str = "double"
    phase_fraction: float = 0.0
    step_index: int = 0
    com_ref: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(3))
    com_velocity_ref: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(3))
    zmp_ref: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(3))
    capture_point_ref: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(3))
    multibody_zmp: np.ndarray = dataclasses.field(default_factory=lambda: np.full(3, np.nan))
    left_foot: tuple = (0.0, 0.0, 0.0, 0.0)
    right_foot: tuple = (0.0, 0.0, 0.0, 0.0)
    next_footsteps: list = dataclasses.field(default_factory=list)
    speed: float = 0.0
    yaw_rate: float = 0.0


def _estop_active(x) -> bool:
    if x is None:
        return False
    if hasattr(x, "active"):
        return bool(x.active)
    return bool(x)


def yaw_of(R: np.ndarray) -> float:
    return math.atan2(R[1, 0], R[0, 0])


def rot_z(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


class LocomotionController:
    """Stand and walk (module docstring). ``dt`` is the control period [s]."""

    source = "locomotion"

    def __init__(self, model: HumanoidModel, config: LocomotionConfig | None = None, dt: float = 0.002,
                 schedule: list[tuple[float, WalkCommand]] | None = None):
        self.m = model
        self.schedule = sorted(schedule or [], key=lambda e: e[0])  # (sim time [s], command), e.g. a scenario's
        self.cfg = config or LocomotionConfig.from_params()
        self.dt = float(dt)
        c = self.cfg
        self.standing_posture = model.joint_vector(model.standing_posture)
        # posture weights: the upper body is held (the CoM is moved by the base and legs, not by
        # flinging the arms); the legs are fixed by the hard sole tasks anyway
        legs = np.array([n[:2] in ("l_", "r_") and any(k in n for k in ("hip", "knee", "ankle"))
                         for n in model.joint_names])
        self.posture_weight = np.where(legs, 1e-4, 0.05)
        self.ik = WholeBodyIK(model, velocity_fraction=c.velocity_fraction)
        self.width = step_width(model) + c.step_width_offset
        corners = model.sole_corners_local["l"]
        self.zmp_offset_x = float(0.5 * (corners[:, 0].max() + corners[:, 0].min()))
        self.stabilizer = WalkingStabilizer(model, dt, c.dcm_gain, c.com_feedback_max, c.cop_damping_gain,
                                            c.cop_damping_time_constant, c.walk_ankle_max_offset,
                                            c.zmp_integral_gain, c.zmp_integral_max, c.foot_height_gain,
                                            c.foot_height_time_constant, c.foot_height_max,
                                            c.cop_damping_time_constant_ds, c.foot_force_gain, c.foot_cop_gain,
                                            c.foot_cop_min_force)
        self.sole_stiffness, self.sole_damping = sole_contact(model)
        self._leg_columns = {s: model.leg_joint_indices(s) for s in SIDES}
        self.weight = model.total_mass * GRAVITY
        self.messages: list[str] = []
        self.reset()

    # ------------------------------------------------------------------ contract
    def reset(self) -> None:
        self.standing = self._new_standing(self.m.standing_posture)
        self.pattern: WalkingPattern | None = None
        self.correction: MultiBodyCorrection | None = None
        self.momentum_zmp = MomentumZmp(self.m, self.dt)
        self.q_ik: np.ndarray | None = None
        self.sample: PatternSample | None = None
        self.command = WalkCommand()
        self.pending: WalkCommand | None = None
        self.n_steps: int | None = None
        self.released = False
        self.heading = 0.0          # the feet's yaw in the estimator's world (the observation has no yaw)
        self.state = WalkingState()
        self._last_input = None
        self._schedule_i = 0
        self.stabilizer.reset()
        self.last_stabilizer = None
        self.drift_yaw = 0.0        # low-passed IMU yaw - the IK's IMU yaw [rad] (the feet's yaw drift)
        self.walk_origin = None     # (feet centre xy [m], heading [rad]) at the walk start, straight walks
        self._last_stance: str | None = None   # the stance foot of the last single support (swing tilt compensation)
        self.last_swing_tilt = None

    def set_walk_command(self, speed: float, yaw_rate: float = 0.0, n_steps: int | None = None) -> str | None:
        """Ask for a walk [m/s, rad/s]; ``n_steps`` walks that many steps then stops. Returns the reason
        if refused (also logged to ``messages``); a clamp is a warning, not a refusal."""
        if not (math.isfinite(speed) and math.isfinite(yaw_rate)):
            return self._log(f"walk command refused: non-finite speed {speed!r} or yaw rate {yaw_rate!r}")
        if speed < 0:
            return self._log(f"walk command refused: backward walking ({speed:.3f} m/s) is not supported")
        if n_steps is not None and n_steps < 1:
            return self._log(f"walk command refused: n_steps {n_steps} < 1")
        if self.released:
            return self._log("walk command ignored: the robot is released (fall event or e-stop)")
        c = self.cfg
        if speed > c.max_speed + 1e-9:
            self._log(f"walk speed {speed * 3.6:.2f} km/h clamped to {c.max_speed_kmh:.2f} km/h")
            speed = c.max_speed
        if abs(yaw_rate) > c.max_turn_rate + 1e-9:
            self._log(f"yaw rate {math.degrees(yaw_rate):.1f} deg/s clamped to {c.max_turn_rate_deg_s:.1f} deg/s")
            yaw_rate = math.copysign(c.max_turn_rate, yaw_rate)
        cmd = WalkCommand(speed, yaw_rate)
        if not cmd.is_zero:
            reason = self.check_feasibility(cmd)
            if reason:
                return self._log(f"walk command refused: {reason}")
        self.pending = cmd
        self.n_steps = n_steps
        return None

    def _log(self, text: str) -> str:
        self.messages.append(text)
        return text

    def step(self, observation: Observation) -> JointTargets | None:
        inp = observation.inputs
        if inp.get("fall_event") or _estop_active(inp.get("estop")):
            if not self.released:
                self._log("released: " + ("fall event" if inp.get("fall_event") else "e-stop"))
            self.released = True
            self._drop_walk()
            self.state = dataclasses.replace(WalkingState(), stamp_ns=observation.stamp_ns, released=True)
            return None
        if self.released:  # control comes back: stand from the measured posture
            self.released = False
            self._resume_standing(observation)
        while self._schedule_i < len(self.schedule) and self.schedule[self._schedule_i][0] <= observation.time + 1e-9:
            cmd = self.schedule[self._schedule_i][1]
            self._schedule_i += 1
            self.set_walk_command(cmd.speed, cmd.yaw_rate, cmd.n_steps)
        cmd_in = inp.get("cmd_walk")
        if cmd_in is not None and cmd_in is not self._last_input:
            self._last_input = cmd_in
            if isinstance(cmd_in, WalkCommand):
                self.set_walk_command(cmd_in.speed, cmd_in.yaw_rate, cmd_in.n_steps)
            else:  # (speed, yaw_rate) or (speed, yaw_rate, n_steps)
                n = int(cmd_in[2]) if len(cmd_in) > 2 and cmd_in[2] is not None else None
                self.set_walk_command(float(cmd_in[0]), float(cmd_in[1]), n)
        active = observation.active_source
        if self.pattern is not None and active not in ("", "none", self.source):
            self._log(f"walk stopped: {active} drives the robot")
            self._drop_walk()
        if self.pending is not None:
            cmd, self.pending = self.pending, None
            if self.pattern is None:
                if not cmd.is_zero:
                    self._start_walk(observation, cmd)
            else:
                self.pattern.set_command(cmd)
            self.command = cmd
        if self.pattern is None:
            out = self.standing.step(observation)
            self.state = WalkingState(stamp_ns=observation.stamp_ns)
            return out
        return self._walk_tick(observation)

    # ------------------------------------------------------------------ walking
    def _drop_walk(self) -> None:
        self.pattern = None
        self.correction = None
        self.q_ik = None
        self.command = WalkCommand()
        self.pending = None
        self.stabilizer.reset()

    def _resume_standing(self, observation: Observation) -> None:
        """Control comes back (a fall event cleared, an e-stop released): stand from the measured posture.

        ``resume_stance`` "feet" (default): on the first tick this controller drives again, the standing
        posture becomes :meth:`stance_posture` of that tick's measurement (where the feet are) and the
        command blends into it over ``resume_time``, then keeps that stance; "standard": blends joint-wise to
        the standard standing posture (with a staggered stance that drags the feet: 0.35 m apart after a
        captured step). Until it drives, it tracks the servos' targets (``resume_from_targets``) or the
        measured joints, so the hand-back is bumpless."""
        self.standing = self._new_standing(self.m.standing_posture)
        # as if another source had driven: it starts from the measured posture and blends back
        self.standing.step(dataclasses.replace(observation, active_source="other"))

    def _new_standing(self, posture: dict) -> StandingController:
        """The standing balance about ``posture``; when another source has driven, it resumes where the feet are
        (``resume_stance`` "feet": :meth:`stance_posture`) from the servos' targets (``resume_from_targets``)."""
        c = self.cfg
        return StandingController(self.m, posture, c.ankle_kp, c.ankle_kd, c.ankle_max_offset, c.resume_time,
                                  self.source, resume_target=self.stance_posture if c.resume_stance == "feet" else None,
                                  resume_from_targets=c.resume_from_targets)

    def world_heading(self, observation: Observation) -> float:
        """The soles' mean yaw in the world [rad]: from the IMU and the joints (the observation has no yaw), else
        the controller's ``heading``."""
        quat = imu_quaternion(observation.inputs.get("imu"))
        if quat is None:
            return self.heading
        m = self.m
        q = m.configuration([0, 0, 0], [0, 0, 0, 1], observation.joint_position)
        m.forward(q)
        R_wb = base_rotation_from_imu(m, m.data, quat / np.linalg.norm(quat))
        yaws = [yaw_of(R_wb @ m.frame_placement(m.sole_frame[s]).rotation) for s in SIDES]
        return math.atan2(sum(map(math.sin, yaws)), sum(map(math.cos, yaws)))

    def stance_posture(self, observation: Observation):
        """A standing posture where the feet are (the shared IK, ``model.ik``) and its CoM reference.

        The measured joints with the soles flat on the ground (their relative placement is the joints'),
        at the world heading (:meth:`world_heading`) and the measured ankles' mid-point; then the IK to
        convergence: both soles hard where they are (x, y, yaw, flat, z = 0), the CoM over the middle of the
        two soles (the mean of their eight corners) at its present height, the trunk upright with the soles'
        mean yaw, the measured joints as the posture (a small weight). Returns (joints (njoints,), CoM reference
        relative to the ankles' mid-point (2,), world axes, what ``StandingBalance`` holds), or (None, None)
        (logged) when the IK does not get there: the standard posture is then used."""
        m = self.m
        heading = self.world_heading(observation)
        joints = np.asarray(observation.joint_position, float)
        q = self.reference_configuration(joints, heading, np.asarray(observation.state.feet_center, float)[:2])
        m.forward(q)
        tasks = []
        for sd in SIDES:
            M = m.frame_placement(m.sole_frame[sd])
            tasks.append(FrameTask(m.sole_frame[sd], pin.SE3(rot_z(yaw_of(M.rotation)),
                                                             np.array([M.translation[0], M.translation[1], 0.0])),
                                   hard=True))
        mid = np.vstack([m.sole_corners(sd)[:, :2] for sd in SIDES]).mean(axis=0)
        com = m.com(q)
        tasks += [ComTask(np.array([mid[0], mid[1], com[2]]), weight=10.0),
                  OrientationTask(m.trunk_link, rot_z(heading), weight=1.0),
                  PostureTask(joints, weight=1e-3)]
        r = self.ik.solve_to_convergence(q, tasks, dt=0.05, max_iterations=100, tolerance=1e-3)
        if not r.converged and max(r.errors[:3]) > 0.01:
            self._log(f"resume: no standing posture where the feet are (IK errors {np.round(r.errors, 4).tolist()}):"
                      " the standard standing posture")
            return None, None
        m.forward(r.q)
        ankles = 0.5 * (m.frame_position(m.foot_link["l"]) + m.frame_position(m.foot_link["r"]))
        ref = m.com(r.q)[:2] - ankles[:2]
        self.heading = heading
        self._log(f"resume: standing where the feet are (soles {np.round(mid, 3).tolist()} mid, heading "
                  f"{math.degrees(heading):.1f} deg), CoM over their middle")
        return np.clip(r.q[7:], m.limits.lower, m.limits.upper), ref

    def stance_offset(self, joints) -> float:
        """How far the feet stand from the standard stance [m]: the other sole's placement in the left sole's
        frame against the standard posture's (x, y, and yaw counted 0.2 m per rad), the largest of the three."""
        m = self.m

        def rel(j):
            m.forward(m.configuration([0, 0, 0], [0, 0, 0, 1], j))
            M = m.frame_placement(m.sole_frame["l"]).inverse() * m.frame_placement(m.sole_frame["r"])
            return np.array([M.translation[0], M.translation[1], 0.2 * yaw_of(M.rotation)])

        return float(np.max(np.abs(rel(np.asarray(joints, float)) - rel(self.standing_posture))))

    def reference_configuration(self, joints, heading: float, feet_center_xy) -> np.ndarray:
        """Full configuration (nq,) for measured ``joints`` with the soles flat on z = 0, their mean
        yaw ``heading`` [rad] and the ankles' mid-point at ``feet_center_xy`` [m]."""
        m = self.m
        q = m.configuration([0, 0, 0], [0, 0, 0, 1], joints)
        m.forward(q)
        Rl = m.frame_placement(m.sole_frame["l"]).rotation
        Rr = m.frame_placement(m.sole_frame["r"]).rotation
        # base rotation that makes the mean sole orientation flat with the given yaw
        R_mean = pin.exp3(0.5 * pin.log3(Rl.T @ Rr))
        R_sole = Rl @ R_mean
        R_base = rot_z(heading) @ R_sole.T
        q = m.configuration([0, 0, 0], pin.Quaternion(R_base).coeffs(), joints)
        m.forward(q)
        ankles = 0.5 * (m.frame_position(m.foot_link["l"]) + m.frame_position(m.foot_link["r"]))
        soles_z = 0.5 * (m.frame_position(m.sole_frame["l"])[2] + m.frame_position(m.sole_frame["r"])[2])
        q[0] = feet_center_xy[0] - ankles[0]
        q[1] = feet_center_xy[1] - ankles[1]
        q[2] = -soles_z
        return q

    def _feet_of(self, q) -> dict:
        m = self.m
        m.forward(q)
        out = {}
        for s in SIDES:
            M = m.frame_placement(m.sole_frame[s])
            out[s] = Footstep(s, float(M.translation[0]), float(M.translation[1]), yaw_of(M.rotation))
        return out

    def _start_walk(self, observation: Observation, cmd: WalkCommand) -> None:
        off = self.stance_offset(observation.joint_position)
        if off > self.cfg.walk_stance_tolerance:
            self._log(f"walk command refused: the feet stand {off:.3f} m off the standard stance (tolerance "
                      f"{self.cfg.walk_stance_tolerance:.3f} m; e.g. after a captured protective step): the pattern's "
                      "first steps assume it, and stepping back to it is not built")
            return
        q = self.reference_configuration(observation.joint_position, self.heading, observation.state.feet_center)
        feet = self._feet_of(q)
        com = self.m.com(q)
        self.q_ik = q
        self.pattern = WalkingPattern(self.cfg, self.dt, self.width, self.zmp_offset_x, feet, com, cmd, self.n_steps)
        self.correction = None
        if self.cfg.multibody_correction:
            lookahead = max(1, round(self.cfg.multibody_horizon / self.dt))
            pattern = self.pattern
            self.correction = MultiBodyCorrection(self.m, pattern, q, lambda s: self.tasks(s, pattern=pattern),
                                                  lookahead,
                                                  WholeBodyIK(self.m, velocity_fraction=1.0))
        self.momentum_zmp.reset()
        self.stabilizer.reset()
        self._last_stance = None
        self.drift_yaw = 0.0
        self.walk_origin = (np.asarray(observation.state.feet_center, float)[:2].copy(), self.heading)
        self._log(f"walk started: {cmd.speed * 3.6:.2f} km/h, {math.degrees(cmd.yaw_rate):.1f} deg/s"
                  + (f", {self.n_steps} steps" if self.n_steps else ""))

    def _sole_centres(self, sample: PatternSample) -> dict:
        """side -> the sample's sole centre (x, y) [m] (the ZMP reference point of a sole)."""
        return {s: sample.feet[s].position[:2] + self.zmp_offset_x * np.array(
            [math.cos(sample.feet[s].yaw), math.sin(sample.feet[s].yaw)]) for s in SIDES}

    def sinkage(self, sample: PatternSample, pattern: WalkingPattern | None = None) -> dict:
        """side -> how far the sole's target is pressed into the ground [m] (walking/compliance.py): the planned
        load of the sample's reference ZMP on the URDF sole contact, times ``sole_sinkage_gain``; the damper's lead
        needs the next tick's reference, from ``pattern`` (without it, none)."""
        g = self.cfg.sole_sinkage_gain
        if g <= 0 or self.sole_stiffness <= 0:
            return {s: 0.0 for s in SIDES}
        stance = {SupportPhase.SINGLE_LEFT: "l", SupportPhase.SINGLE_RIGHT: "r"}.get(sample.support)
        centres = self._sole_centres(sample)
        f = planned_loads(sample.zmp, centres, stance, self.weight)
        f_next = f if stance is not None or pattern is None else \
            planned_loads(pattern.zmp_reference(sample.tick + 1), centres, None, self.weight)
        damping = self.sole_damping if self.cfg.sole_sinkage_damping else 0.0
        return {s: g * d for s, d in sole_sinkage(f, f_next, self.dt, self.sole_stiffness, damping).items()}

    def tasks(self, sample: PatternSample, com_target=None, pattern: WalkingPattern | None = None,
              foot_z: dict | None = None) -> list:
        """IK tasks of a pattern sample: both soles hard (pressed in by their planned sinkage), CoM, trunk yaw,
        posture. ``pattern``: the sample's pattern (the sinkage's damper lead reads its next ZMP reference);
        ``foot_z``: side -> the stabiliser's sole height offsets [m]."""
        tasks = []
        sink = self.sinkage(sample, pattern)
        for s in SIDES:
            f = sample.feet[s]
            # the targets are the references at the end of this step (dead-beat): no feed-forward
            p = f.position - np.array([0.0, 0.0, sink[s] - (foot_z[s] if foot_z else 0.0)])
            tasks.append(FrameTask(self.m.sole_frame[s], pin.SE3(rot_z(f.yaw), p), hard=True))
        yaw = math.atan2(math.sin(sample.feet["l"].yaw) + math.sin(sample.feet["r"].yaw),
                         math.cos(sample.feet["l"].yaw) + math.cos(sample.feet["r"].yaw))
        tasks.append(ComTask(sample.com if com_target is None else com_target, weight=100.0))
        tasks.append(OrientationTask(self.m.trunk_link, rot_z(yaw), weight=1.0))
        tasks.append(PostureTask(self.standing_posture, weight=self.posture_weight))
        return tasks

    def _steer(self, observation: Observation) -> None:
        """Footstep steering from the IMU: the heading drift ``psi_d`` = measured IMU yaw - the IK's IMU
        yaw (the joints track the IK, so the difference is how far the whole robot has yawed off the
        pattern, e.g. by the stance foot's yaw slip) and, while every command has been straight, the
        lateral drift ``e`` of the measured feet centre off the start line. The steps not yet planned
        get a total path heading correction ``-psi_d - k e`` (``WalkingPattern.steer_target``, rate
        limited per step). Without an IMU input, or with an unusable one (NaN, not a quaternion), nothing
        this tick."""
        c = self.cfg
        quat = imu_quaternion(observation.inputs.get("imu"))
        if quat is None or not c.steer_enabled or self.q_ik is None:   # an unusable reading steers nothing
            return
        R = quat_matrix(quat)
        self.m.forward(self.q_ik)
        R_ik = self.m.frame_placement(self.m.imu_frame).rotation
        d = math.remainder(yaw_of(R) - yaw_of(R_ik), math.tau)
        self.drift_yaw += min(1.0, self.dt / c.steer_filter_time) * (d - self.drift_yaw)
        target = -self.drift_yaw
        if self.walk_origin is not None and abs(self.command.yaw_rate) < 1e-9:
            o, h = self.walk_origin
            e = np.asarray(observation.state.feet_center, float)[:2] - o
            lateral = -math.sin(h) * e[0] + math.cos(h) * e[1]
            target -= c.heading_lateral_gain * lateral
        else:
            self.walk_origin = None   # a turn: no straight line to hold any more
        self.pattern.steer_target = target

    def _walk_tick(self, observation: Observation) -> JointTargets:
        self._steer(observation)
        if self.correction is not None:
            cs = self.correction.step()
            sample = cs.sample
        else:
            sample = self.pattern.step()
        self.sample = sample
        s = observation.state
        stance = None
        if sample.support == SupportPhase.SINGLE_LEFT:
            stance = "l"
        elif sample.support == SupportPhase.SINGLE_RIGHT:
            stance = "r"
        ref_feet_center = 0.5 * (sample.feet["l"].position + sample.feet["r"].position)
        stance_yaw = sample.feet[stance].yaw if stance else 0.5 * (sample.feet["l"].yaw + sample.feet["r"].yaw)
        centres = self._sole_centres(sample)
        transfer_to = None
        if stance is None:   # double support: the foot the ZMP reference moves onto, if it moves
            v = self.pattern.zmp_reference(sample.tick + 1) - sample.zmp[:2]
            if float(np.linalg.norm(v)) > 1e-7:
                transfer_to = max(SIDES, key=lambda side: float((centres[side] - sample.zmp[:2]) @ v))
        st = self.stabilizer.update(s.capture_point_fused, s.cop, s.feet_center, sample.capture_point, sample.zmp,
                                    ref_feet_center, stance, stance_yaw, centres, transfer_to,
                                    swing_loaded=stance is not None and bool(s.contacts["r" if stance == "l" else "l"]),
                                    **self._foot_measurements(s))
        self.last_stabilizer = st
        r = self.ik.solve(self.q_ik, self.tasks(sample, sample.com + st.com_offset, self.pattern, st.foot_z),
                          self.dt)
        self.q_ik = r.q
        q_cmd = self.stabilizer.apply(r.q[7:], st)
        if self.cfg.swing_tilt_compensation and self.pattern.command.speed * 3.6 > self.cfg.swing_tilt_min_speed_kmh:
            q_cmd = self._swing_tilt_compensation(r.q, q_cmd, sample, stance)
        if stance is not None:
            self._last_stance = stance
        p_mb = self.momentum_zmp.update(r.q, r.v)
        self.state = self._state(observation.stamp_ns, sample)
        if p_mb is not None:
            self.state.multibody_zmp = p_mb
        if sample.finished:
            self._finish_walk(observation, r.q)
        return JointTargets(q_cmd, r.v[6:].copy())

    def _foot_measurements(self, s) -> dict:
        """The estimator's per-foot normal forces, CoPs and contacts for the stabiliser's loops 4 (forces) and 5,
        in walks up to ``foot_force_max_speed_kmh`` (faster: none, the CoP-based loop 4 and no loop 5)."""
        speed = self.pattern.command.speed if self.pattern is not None else self.command.speed
        if speed * 3.6 > self.cfg.foot_force_max_speed_kmh + 1e-9:
            return {}
        return {"foot_forces": s.foot_normal_forces, "foot_cops": s.foot_cops, "contacts": s.contacts}

    def _swing_tilt_compensation(self, q_ik: np.ndarray, q_cmd: np.ndarray, sample: PatternSample,
                                 stance: str | None) -> np.ndarray:
        """Keep the swing foot on its planned path under the stabiliser's ankle offsets (a copy of ``q_cmd``).

        The ankle damping offset of the stance ankle (loop 2 of walking/stabilizer.py) cannot turn the
        stance sole, which lies flat on the ground: it turns the whole robot above the ankle instead (that is
        how it moves the CoP), and with it the swing foot, whose sole then no longer follows its planned
        path (measured at 1.8 km/h: 2.5 mrad of stance ankle pitch at the end of the single support lift the
        landing foot 0.3-0.7 mm, and it touches down 30-46 ms late, halfway into the double support). With
        the base sole ``b`` held at its IK placement ``M_b`` (flat on the ground), the other sole of the
        commanded joints sits at ``M_o' = M_b (M_b^c)^-1 M_o^c`` (``^c``: forward kinematics of the commanded
        joints); one Gauss-Newton step on that leg's six joints, ``dq = J_o^-1 log6((M_o')^-1 M_o)`` (local
        frame Jacobian of the sole w.r.t. its own leg's joints), brings it back to its IK placement ``M_o``.
        The base is the stance foot in single support (ramped in over ``swing_tilt_ramp`` at the lift-off);
        in the double support after a swing, the previous stance foot, with the correction of the landing
        foot faded out linearly over the double support, or (``swing_tilt_ds_hold``) held: the feet's relative
        poses then stay the planned ones while the rear ankle's offset leaks (``cop_damping_time_constant_ds``),
        and the correction goes to 0 with it, not by moving the landing foot against the ground."""
        m = self.m
        if stance is not None:
            base, other_ = stance, ("r" if stance == "l" else "l")
            speed = self.pattern.command.speed if self.pattern is not None else self.command.speed
            t_in = sample.phase_fraction * self.cfg.single_support_for(speed)
            w = min(1.0, t_in / self.cfg.swing_tilt_ramp) if self.cfg.swing_tilt_ramp > 0 else 1.0
        elif self._last_stance is not None:
            base, other_ = self._last_stance, ("r" if self._last_stance == "l" else "l")
            w = 1.0 if self.cfg.swing_tilt_ds_hold else 1.0 - sample.phase_fraction
        else:
            return q_cmd
        if w <= 0.0:
            return q_cmd
        m.forward(q_ik)
        M_b = m.frame_placement(m.sole_frame[base]).copy()
        M_o = m.frame_placement(m.sole_frame[other_]).copy()
        q = q_ik.copy()
        q[7:] = q_cmd
        if self.cfg.swing_tilt_pitch_only:   # correct for the ankle pitch offsets only (the rolls left as they are)
            rolls = [self.stabilizer.roll_index[s] for s in SIDES]
            q[7:][rolls] = q_ik[7:][rolls]
        m.forward(q)
        M_bc = m.frame_placement(m.sole_frame[base])
        # re-base: the commanded robot with its base sole where the IK has it
        T = M_b * M_bc.inverse()
        B = T * pin.XYZQUATToSE3(q[:7])
        q[:7] = pin.SE3ToXYZQUAT(B)
        m.forward(q)
        M_oc = m.frame_placement(m.sole_frame[other_]).copy()
        err = pin.log6(M_oc.inverse() * M_o).vector
        J = pin.computeFrameJacobian(m.model, m.data, q, m.frame_ids[m.sole_frame[other_]], pin.ReferenceFrame.LOCAL)
        cols = self._leg_columns[other_]
        dq = np.linalg.solve(J[:, [6 + j for j in cols]], err)
        out = np.array(q_cmd, float)
        out[cols] += w * dq
        self.last_swing_tilt = (other_, w, err.copy())
        return out

    def _finish_walk(self, observation: Observation, q_final: np.ndarray) -> None:
        """The stop has settled: stand in the posture the walk ended in (bumpless)."""
        feet = self.sample.feet
        self.heading = 0.5 * (feet["l"].yaw + feet["r"].yaw)
        posture = dict(zip(self.m.joint_names, q_final[7:]))
        self.standing = self._new_standing(posture)
        self._log(f"walk finished after {self.pattern.step_count} steps")
        self.pattern = None
        self.correction = None
        self.q_ik = None
        self.command = WalkCommand()

    def _state(self, stamp_ns: int, sample: PatternSample) -> WalkingState:
        f = sample.feet
        return WalkingState(
            stamp_ns=stamp_ns, walking=True, released=False, support=sample.support.value,
            phase_fraction=float(sample.phase_fraction), step_index=int(sample.step_index),
            com_ref=sample.com.copy(), com_velocity_ref=sample.com_velocity.copy(), zmp_ref=sample.zmp.copy(),
            capture_point_ref=sample.capture_point.copy(),
            left_foot=(*map(float, f["l"].position), float(f["l"].yaw)),
            right_foot=(*map(float, f["r"].position), float(f["r"].yaw)),
            next_footsteps=[(n.side, n.x, n.y, n.yaw, n.index, n.stop) for n in sample.next_footsteps],
            speed=self.command.speed, yaw_rate=self.command.yaw_rate)

    # ------------------------------------------------------------------ feasibility
    def check_feasibility(self, cmd: WalkCommand, n_steps: int = 3, dt: float = 0.02) -> str | None:
        """Rehearse ``n_steps`` of the command (start and stop included) on the kinematic model with the
        IK at ``dt`` [s]; the reason the kinematics cannot do it, or None. Checks the knee margin, the
        hip extension limit, joint speeds (the IK bounds them: a foot or the CoM falling behind its
        reference by more than 5 mm / 1 cm is the symptom) and the other joint limits."""
        m, c = self.m, self.cfg
        q = self.reference_configuration(self.standing_posture, 0.0, (0.0, 0.0))
        feet = self._feet_of(q)
        # the rehearsal starts at the walking height: settle the IK there first
        com = m.com(q)
        com[2] = c.com_height
        pat = WalkingPattern(c, dt, self.width, self.zmp_offset_x, feet, com, cmd, n_steps)
        conv = self.ik.solve_to_convergence(q, self.tasks(pat.sample(), pattern=pat), dt=0.05, tolerance=1e-3)
        if not conv.converged:
            return f"the walking CoM height {c.com_height:.3f} m is out of reach (errors {np.round(conv.errors, 4)})"
        q = conv.q
        knees = [m.joint_index(f"{s}_knee") for s in SIDES]
        hips = [m.joint_index(f"{s}_hip_pitch") for s in SIDES]
        worst_knee, worst_hip, worst_speed = math.inf, -math.inf, 0.0
        ik = WholeBodyIK(m, velocity_fraction=c.velocity_fraction)
        while True:
            smp = pat.step()
            r = ik.solve(q, self.tasks(smp, pattern=pat), dt)
            q = r.q
            err = ik.task_errors(q, self.tasks(smp, pattern=pat)[:3])
            if max(err[:2]) > 0.005 or err[2] > 0.01:
                speed = np.abs(r.v[6:]) / m.limits.velocity
                j = int(np.argmax(speed))
                return (f"at t={smp.time:.2f} s of the rehearsal the IK falls behind (feet {max(err[:2]) * 1e3:.1f} mm,"
                        f" CoM {err[2] * 1e3:.1f} mm); fastest joint {m.joint_names[j]} at {speed[j]:.2f} of its"
                        f" limit, knee {min(q[7:][knees]):.3f} rad, hip pitch {max(q[7:][hips]):.3f} rad")
            worst_knee = min(worst_knee, float(min(q[7:][knees])))
            worst_hip = max(worst_hip, float(max(q[7:][hips])))
            worst_speed = max(worst_speed, float(np.max(np.abs(r.v[6:]) / m.limits.velocity)))
            if smp.finished:
                break
        if worst_knee < c.knee_margin:
            return f"a knee straightens to {worst_knee:.3f} rad (margin {c.knee_margin} rad)"
        hip_lim = float(m.limits.upper[hips[0]]) - c.hip_extension_margin
        if worst_hip > hip_lim:
            return f"a hip extends to {worst_hip:.3f} rad (limit {hip_lim:.3f} rad with its margin)"
        if worst_speed > c.velocity_fraction + 1e-6:
            return f"a joint needs {worst_speed:.2f} of its speed limit"
        self.last_feasibility = {"knee_min": worst_knee, "hip_pitch_max": worst_hip, "speed_ratio_max": worst_speed}
        return None


def from_scenario(sc: dict, model: HumanoidModel, params: dict | None = None) -> LocomotionController:
    """The locomotion controller of scenario ``sc`` (what the ``locomotion`` node builds when its
    ``scenario`` parameter names ``sc``): settings from :func:`walking_config` (``params``: the
    node's declared values, default the declared defaults with the scenario's ``params.locomotion``),
    the scenario's control period and its walk schedule."""
    from humfall_ros.walking import scenario as walk_scenario

    return LocomotionController(model, walk_scenario.walking_config(sc, params), walk_scenario.control_period(sc),
                                walk_scenario.walk_schedule(sc))


__all__ = ["LocomotionController", "WalkingState", "from_scenario", "rot_z", "yaw_of"]
