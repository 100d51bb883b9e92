"""Standing balance: hold a posture and keep the CoM over the feet (ankle strategy).

The joints are position-controlled by the simulator; on top of the nominal
posture, the ankles are offset in proportion to the CoM error and velocity
relative to a reference over the support polygon. This is a balance
controller, not a fall controller: pushes beyond what the ankles can absorb
are the FTB's and the safe-fall controller's business.
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from humfall_ros.control.contract import JointTargets, Observation
from humfall_ros.control.step_control import sensed_soles
from humfall_ros.model.humanoid import SIDES, HumanoidModel


def hip_flexion_profile(t: float, amplitude: float, rise: float, hold: float, release: float) -> float:
    """The hip strategy's flexion [rad] ``t`` [s] after a touchdown (ours): both hips flex by ``amplitude`` over
    ``rise`` s, stay ``hold`` s, come back over ``release`` s, each ramp a half cosine (0 outside).

    Flexing at the hips turns the trunk forward; its angular momentum is taken from the ground by a backward
    force that slows the CoM at once, beyond what the CoP at the toe can: on scripted touchdowns the ankle balance
    alone stopped the robot from a capture point 1.9-3.5 cm inside the soles' hull, with 0.3 rad held 0.6 s from
    -0.4-0.5 cm (``benchmarks/bench_capture_balance.py --hip-flex``)."""
    if amplitude == 0.0 or t < 0.0:
        return 0.0
    if t < rise:
        a = t / rise
    elif t < rise + hold:
        a = 1.0
    elif release > 0.0 and t < rise + hold + release:
        a = 1.0 - (t - rise - hold) / release
    else:
        return 0.0
    return float(amplitude * (0.5 - 0.5 * np.cos(np.pi * a)))


def lateral_roll(com, com_velocity, left, right, gain: float, damping: float, bound: float) -> float | None:
    """The ankle roll offset [rad] that moves the CoM sideways towards the segment between the soles' centres
    ``left``, ``right`` (x, y) [m] (ours; the hip rolls get its negative): -clip(gain e + damping e', bound).

    p is the segment's point nearest the CoM and n its unit normal; e = (CoM - p)_y, e' = (v . n) n_y: the sideways
    (y) parts, the ones the rolls move. A + y error needs a - roll (``StandingBalance``). None: the soles on top of
    each other."""
    a, b = np.asarray(left, float)[:2], np.asarray(right, float)[:2]
    com, vel = np.asarray(com, float), np.asarray(com_velocity, float)
    e = b - a
    length = float(np.linalg.norm(e))
    if length < 1e-6:
        return None
    t = float(np.clip(np.dot(com[:2] - a, e) / length ** 2, 0.0, 1.0))
    n = np.array([-e[1], e[0]]) / length
    err = float(com[1] - (a[1] + t * e[1]))
    rate = float(np.dot(vel[:2], n) * n[1])
    return float(np.clip(-(gain * err + damping * rate), -bound, bound))


def lateral_roll_sensed(model: HumanoidModel, observation: Observation, gain: float, damping: float,
                        bound: float) -> float | None:
    """:func:`lateral_roll` of an observation: the estimator's CoM and velocity, and the soles' centres of the
    sensed configuration (``step_control.sensed_soles``: the joints, the IMU, the CoM). None: no usable IMU reading
    or state. ``model``'s kinematics are overwritten (give a copy with its own data where that matters)."""
    s = observation.state
    com, vel = np.asarray(s.com, float), np.asarray(s.com_velocity, float)
    if not (np.all(np.isfinite(com)) and np.all(np.isfinite(vel))):
        return None
    sensed = sensed_soles(model, observation.joint_position, observation.inputs.get("imu"), com)
    if sensed is None:
        return None
    left, right = (sensed[1][sd].mean(axis=0) for sd in SIDES)
    return lateral_roll(com, vel, left, right, gain, damping, bound)


class StandingBalance:
    def __init__(self, model: HumanoidModel, posture: dict, kp: float = 0.3, kd: float = 0.05,
                 max_offset: float = 0.12):
        self.m = model
        self.nominal = model.joint_vector(posture)
        self.kp, self.kd, self.max_offset = kp, kd, max_offset
        self.reference = None
        self._pitch = [model.joint_index(f"{s}_ankle_pitch") for s in SIDES]
        self._roll = [model.joint_index(f"{s}_ankle_roll") for s in SIDES]

    def reset(self) -> None:
        self.reference = None

    def command(self, com, com_velocity, support_polygon=None, feet_center=None) -> np.ndarray:
        """Joint position targets (model order).

        With ``feet_center`` (mid-point of the ankles, same frame as ``com``), the CoM is
        held relative to the feet, not at a fixed world point: an estimator's odometry
        drifts in the world, and chasing that drift leant a noisy-sensor robot 1.5 deg
        (0.06 deg relative to the feet).
        """
        com = np.asarray(com, float)
        vel = np.asarray(com_velocity, float)
        if feet_center is not None:
            com = com - np.array([feet_center[0], feet_center[1], 0.0])
        if self.reference is None:
            # hold the CoM where the standing posture put it over the feet: a reference
            # elsewhere would step the stiff ankles on the first tick and jolt the robot
            self.reference = com[:2].copy()
        err = com[:2] - self.reference
        # ankle pitch > 0 turns the toes down: the body is pushed back (+x error -> + pitch)
        d_pitch = np.clip(self.kp * err[0] + self.kd * vel[0], -self.max_offset, self.max_offset)
        # ankle roll > 0 tilts the shank towards +y over a flat sole: a +y error needs a - roll
        d_roll = np.clip(-(self.kp * err[1] + self.kd * vel[1]), -self.max_offset, self.max_offset)
        q = self.nominal.copy()
        q[self._pitch] += d_pitch
        q[self._roll] += d_roll
        return np.clip(q, self.m.limits.lower, self.m.limits.upper)


class StandingController:
    """The standing balance as a contract controller (humfall_ros.control.contract), source "locomotion".

    Bumpless transfer: while another source drives the robot (``observation.active_source``
    is not this source and not "none"), the controller tracks the measured posture, so
    the command it would give equals where the joints are; once it drives again it
    blends its nominal posture from that measured one back to the standing posture
    over ``resume_time`` [s] (a cosine ramp), with the ankle balance on top. At the
    start of a run ("none" active) it starts from the standing posture directly.

    Args:
        model: the robot model.
        posture: joint name -> angle [rad] of the standing posture (``model.standing_posture``).
        kp, kd, max_offset: ankle balance gains (see StandingBalance) [rad/m, rad s/m, rad].
        resume_time: blend time back to the standing posture after regaining control [s].
        source: mux source name.
        resume_target: optional ``observation -> (posture (njoints,), CoM reference relative to the
            feet centre (2,) or None)``, called once, on the first tick this controller drives again:
            the posture to blend to (and then keep) instead of ``posture``, e.g. a standing posture
            where the feet are (the locomotion controller's ``stance_posture``). The CoM reference
            blends with the posture. None (or a None posture): the standard ``posture``.
        resume_from_targets: while another source drives, track the joint targets the servos tracked
            (``observation.joint_targets``, when known) rather than the measured joints: position
            servos sag under load, so taking over at the measured joints relaxes every loaded joint.
    """

    def __init__(self, model: HumanoidModel, posture: dict, kp: float, kd: float, max_offset: float,
                 resume_time: float = 1.0, source: str = "locomotion",
                 resume_target: Callable[[Observation], tuple] | None = None, resume_from_targets: bool = False):
        self.source = source
        self.model = model
        self.balance = StandingBalance(model, posture, kp, kd, max_offset)
        self.standing = self.balance.nominal.copy()
        self.resume_time = float(resume_time)
        self.resume_target = resume_target
        self.resume_from_targets = bool(resume_from_targets)
        self.resume_info: dict | None = None   # what resume_target gave (time, posture, reference), for reports
        self.reset()

    def reset(self) -> None:
        self.balance.reset()
        self.balance.nominal = self.standing.copy()
        self._resume_from: np.ndarray | None = None
        self._resume_start: float | None = None
        self._tracking = False

    def step(self, observation: Observation) -> JointTargets:
        s = observation.state
        active = observation.active_source
        if active not in ("", "none", self.source):
            # someone else drives: follow the measured posture (or the servos' targets), so a hand-back is bumpless
            self._tracking = True
            src = observation.joint_targets if self.resume_from_targets and observation.joint_targets is not None \
                and len(observation.joint_targets) == len(self.standing) else observation.joint_position
            self._resume_from = np.asarray(src, float).copy()
            self.balance.nominal = self._resume_from.copy()
            self.balance.reset()
        elif self._tracking and self._resume_from is not None:
            if self._resume_start is None:
                self._resume_start = observation.time
                self._ref_from = self._ref_to = None
                if self.resume_target is not None:
                    posture, ref = self.resume_target(observation)
                    if posture is not None:
                        self.standing = np.asarray(posture, float).copy()   # kept after the blend: this stance
                        if ref is not None:
                            com = np.asarray(s.com, float)[:2] - np.asarray(s.feet_center, float)[:2]
                            self._ref_from, self._ref_to = com, np.asarray(ref, float)[:2].copy()
                    self.resume_info = {"time": observation.time, "posture": self.standing.copy(),
                                        "reference": None if self._ref_to is None else self._ref_to.copy()}
            a = min(1.0, (observation.time - self._resume_start) / max(self.resume_time, 1e-9))
            w = 0.5 - 0.5 * np.cos(np.pi * a)
            self.balance.nominal = (1.0 - w) * self._resume_from + w * self.standing
            if self._ref_to is not None:
                self.balance.reference = (1.0 - w) * self._ref_from + w * self._ref_to
            if a >= 1.0:
                self._tracking, self._resume_from, self._resume_start = False, None, None
        q = self.balance.command(s.com, s.com_velocity, s.support_polygon, s.feet_center)
        return JointTargets(q)
