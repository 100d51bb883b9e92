"""Step controller for a toppling robot, paper 1 §III-D (eq. 9-10).

Shared by the safe fall (``fall.controller``) and the multi-contact executor's task-space swing
(``multicontact.executor``).

The stance foot is not flat: the robot rotates about the CoP on its sole's edge or corner, a
passive joint we cannot actuate. So

* the configuration is rebuilt every tick from the joint encoders and the trunk IMU (the
  stance foot's rotation is the mismatch between the IMU's trunk orientation and the one the
  joint kinematics give, :func:`configuration_from_sensors`), never from ground truth;
* eq. 9: the landing pose is expressed relative to the stance foot, T_n^s = (T_s^0)^-1 T_n^0.
  At the decision, T_s^0 is the *predicted landed* stance foot (the pendulum's rotation about
  the pivot at touchdown, :func:`predicted_stance_placement`) and the shared IK checks that the
  legs reach T_n^s there; during the swing T_s^0 is the measured stance foot of the tick, so
  the swing foot follows a world trajectory to the landing pose whatever the passive joint did;
* eq. 10: theta' = J_hat^# (P_R' - P_L'): the damped least-squares step of the shared IK
  (``model.ik.WholeBodyIK``) with the stance sole held (hard task at its measured placement) and
  the swing sole on its trajectory, joint speeds within the URDF limits;
* foot-flat landing: the swing sole's orientation goes to the landing yaw with roll = pitch = 0
  in the world, and it is pressed ``press_depth`` below the ground at the end.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pinocchio as pin

from humfall_ros.model.humanoid import SIDES, HumanoidModel, base_rotation_from_imu, imu_quaternion
from humfall_ros.model.ik import FrameTask, PostureTask, WholeBodyIK


def configuration_from_sensors(model: HumanoidModel, joints, imu_quat_xyzw, com_world) -> np.ndarray:
    """Floating-base configuration (nq,) from encoders, the IMU orientation and the estimated CoM.

    The base orientation is the IMU's world orientation composed with the IMU-in-base rotation of
    the kinematics (as the estimator does); the base position puts the model's CoM on the
    estimator's (so feet and CoM are in the estimator's world frame).
    """
    m, d = model.model, model.data
    q = model.configuration([0, 0, 0], [0, 0, 0, 1], joints)
    pin.framesForwardKinematics(m, d, q)
    R_base = base_rotation_from_imu(model, d, imu_quat_xyzw)
    q[3:7] = pin.Quaternion(R_base).coeffs()
    c = pin.centerOfMass(m, d, q)
    q[:3] = np.asarray(com_world, float) - c
    return q


def sensed_soles(model: HumanoidModel, joints, imu, com_world) -> tuple[np.ndarray, dict] | None:
    """The sensed configuration (:func:`configuration_from_sensors`) and both soles' ground corners in it,
    ``(q, {"l": (4, 2), "r": (4, 2)})`` [m] (touching or not); None without a usable IMU reading
    (``imu``: ``Observation.inputs["imu"]``). ``model``'s kinematics are left at ``q``."""
    quat = imu_quaternion(imu)
    if quat is None:
        return None
    q = configuration_from_sensors(model, joints, quat, com_world)
    model.forward(q)
    return q, {sd: model.sole_corners(sd)[:, :2] for sd in SIDES}


def predicted_stance_placement(stance: pin.SE3, pivot, r0, r1) -> pin.SE3:
    """The stance sole rotated about the pivot like the pendulum P->G from ``r0`` to ``r1`` (minimal rotation)."""
    a = np.asarray(r0, float) / np.linalg.norm(r0)
    b = np.asarray(r1, float) / np.linalg.norm(r1)
    axis = np.cross(a, b)
    s = float(np.linalg.norm(axis))
    R = np.eye(3) if s < 1e-12 else pin.exp3(axis / s * math.atan2(s, float(a @ b)))
    p = np.array([pivot[0], pivot[1], 0.0])
    return pin.SE3(R @ stance.rotation, p + R @ (stance.translation - p))


def minimum_jerk(tau: float) -> tuple[float, float]:
    """s(tau) = 10 tau^3 - 15 tau^4 + 6 tau^5 and ds/dtau on [0, 1]."""
    t = min(max(tau, 0.0), 1.0)
    return 10 * t**3 - 15 * t**4 + 6 * t**5, 30 * t**2 - 60 * t**3 + 30 * t**4


@dataclasses.dataclass(frozen=True)
class StepControlConfig:
    """Parameters (``config/safe_fall_controller.yaml``).

    Attributes:
        clearance: swing sole lift at mid-swing [m].
        press_depth: landing target below the ground [m] (makes sure the sole meets it).
        swing_weight, posture_weight: IK task weights [-].
        swing_gain: IK error gain per tick [-].
        velocity_fraction: joint speeds within this fraction of the URDF limits [-].
        damping: damping of the least squares (eq. 10) [-].
        stance_leg_weight: posture weight of the stance leg's joints [-] (ours: with the posture weight
            alone the IK lifted the swing sole by extending the stance leg, which pushed the CoM up 3 cm
            and forward: the passive pendulum the decision predicted was not what the robot did).
        posture_gain: per-tick gain of the posture task [-] (1: the whole posture error in one tick; the safe
            fall's posture is the configuration at the swing's start, so its error starts at 0; the
            multi-contact executor's is the plan's, which starts off the measured joints).
    """

    clearance: float = 0.05
    press_depth: float = 0.01
    swing_weight: float = 100.0
    posture_weight: float = 1e-3
    swing_gain: float = 0.5
    velocity_fraction: float = 0.95
    damping: float = 1e-6
    stance_leg_weight: float = 10.0
    posture_gain: float = 1.0


@dataclasses.dataclass
class SwingPlan:
    """A swing from the lift-off placement to the landing pose over [start, start + duration] [s]."""

    swing: str
    start_time: float
    duration: float
    lift_off: pin.SE3
    landing: pin.SE3


class StepController:
    """Drives the swing sole to the landing pose (module docstring) through the shared IK."""

    def __init__(self, model: HumanoidModel, config: StepControlConfig | None = None):
        self.m = model
        self.config = config or StepControlConfig()
        c = self.config
        self.ik = WholeBodyIK(model, damping=c.damping, velocity_fraction=c.velocity_fraction, position_margin=0.01)
        self.plan: SwingPlan | None = None
        self.posture: np.ndarray | None = None

    @staticmethod
    def landing_placement(x: float, y: float, yaw: float, z: float = 0.0) -> pin.SE3:
        """A flat sole at (x, y, z) with heading ``yaw``."""
        return pin.SE3(pin.rpy.rpyToMatrix(0.0, 0.0, yaw), np.array([x, y, z]))

    def start(self, q, swing: str, landing: pin.SE3, t: float, duration: float) -> None:
        """Plan the swing from the current placement (q: the measured configuration)."""
        self.m.forward(q)
        lift = self.m.frame_placement(self.m.sole_frame[swing]).copy()
        self.plan = SwingPlan(swing, t, max(duration, 0.05), lift, landing)
        self.posture = np.asarray(q, float)[7:].copy()
        stance = "r" if swing == "l" else "l"
        w = np.full(self.m.njoints, self.config.posture_weight)
        w[self.m.leg_joint_indices(stance)] = self.config.stance_leg_weight
        self.posture_weights = w

    def reachable(self, q, swing: str, stance_landed: pin.SE3, landing: pin.SE3,
                  iterations: int = 60) -> tuple[bool, float]:
        """Eq. 9 check: can the legs put the swing sole at ``landing`` with the stance sole at ``stance_landed``?

        Runs the IK from ``q`` with both soles as tasks (stance hard); returns (reached within 1 cm
        and 3 deg, residual position error [m]).
        """
        stance = "r" if swing == "l" else "l"
        tasks = [FrameTask(self.m.sole_frame[stance], stance_landed, hard=True),
                 FrameTask(self.m.sole_frame[swing], landing, weight=100.0),
                 PostureTask(np.asarray(q, float)[7:], weight=1e-4)]
        r = self.ik.solve_to_convergence(q, tasks, dt=0.05, max_iterations=iterations, tolerance=1e-3)
        self.m.forward(r.q)
        M = self.m.frame_placement(self.m.sole_frame[swing])
        err = M.actInv(landing)
        pos = float(np.linalg.norm(err.translation))
        ang = float(np.linalg.norm(pin.log3(err.rotation)))
        return bool(pos < 0.01 and ang < math.radians(3)), pos

    def desired_swing(self, t: float) -> tuple[pin.SE3, np.ndarray]:
        """The swing sole's world placement and twist (LOCAL_WORLD_ALIGNED) at time t."""
        p = self.plan
        tau = (t - p.start_time) / p.duration
        s, ds = minimum_jerk(tau)
        ds /= p.duration
        a, b = p.lift_off, p.landing
        pos = a.translation + s * (b.translation - a.translation)
        vel = ds * (b.translation - a.translation)
        tc = min(max(tau, 0.0), 1.0)
        lift = self.config.clearance * 4 * tc * (1 - tc)
        pos = pos + np.array([0, 0, lift - self.config.press_depth * s])
        vel = vel + np.array([0, 0, self.config.clearance * 4 * (1 - 2 * tc) / p.duration * (0 < tau < 1)])
        dR = pin.log3(a.rotation.T @ b.rotation)
        R = a.rotation @ pin.exp3(s * dR)
        omega = R @ (ds * dR)
        return pin.SE3(R, pos), np.concatenate([vel, omega])

    def command(self, q, t: float, dt: float, extra_tasks=()) -> tuple[np.ndarray, np.ndarray, float]:
        """One tick: (joint positions [rad], joint velocities [rad/s], swing error [m]); ``extra_tasks``: further
        weighted IK tasks (e.g. a trunk orientation) beside the soles and the posture."""
        p = self.plan
        stance = "r" if p.swing == "l" else "l"
        self.m.forward(q)
        stance_now = self.m.frame_placement(self.m.sole_frame[stance]).copy()
        target, twist = self.desired_swing(t + dt)
        c = self.config
        tasks = [FrameTask(self.m.sole_frame[stance], stance_now, hard=True),
                 FrameTask(self.m.sole_frame[p.swing], target, weight=c.swing_weight, gain=c.swing_gain,
                           twist=twist),
                 PostureTask(self.posture, weight=self.posture_weights, gain=c.posture_gain), *extra_tasks]
        r = self.ik.solve(q, tasks, dt)
        return r.q[7:].copy(), r.v[6:].copy(), float(r.errors[1]) if len(r.errors) > 1 else math.nan


__all__ = ["StepControlConfig", "StepController", "SwingPlan", "configuration_from_sensors", "minimum_jerk",
           "predicted_stance_placement", "sensed_soles"]
