"""A multi-contact plan made at the take-over from the robot's own sensors (ours; paper 2 plans offline).

The executor (``multicontact.executor.MulticontactExecutor``) asks its ``plan_source`` for a plan at the take-over
tick. :class:`SensedPlanSource` answers from that tick's observation, never from the simulator's ground truth:

* the 3-D state from the sensors (:func:`sensed_state`): the base orientation from the IMU through the joint
  kinematics, the base position that puts the model's CoM on the estimator's
  (``step_control.configuration_from_sensors``), the base's angular velocity from the gyro less the waist joints'
  (``base_angular_velocity_from_imu``), and its linear velocity the one that gives the estimator's CoM velocity
  (the CoM Jacobian's base block is the base rotation, so it is solved for exactly);
* the planar state of it (``executor.planar_state``), made consistent with the contact mode the robot is in
  (``executor.project_to_mode``, as the in-process runner does with the ground truth);
* the plan from a ``FallPlanner`` (with a request profile, e.g. "execution": ``planner.PROFILES``; from its library
  in ~0.5 s, else by the tree search). In lockstep the physics waits for the tick's answer, so the plan time is
  wall time only.
"""
from __future__ import annotations

import math
import time

import numpy as np
import pinocchio as pin

from humfall_ros.control.step_control import configuration_from_sensors
from humfall_ros.model.humanoid import HumanoidModel, base_angular_velocity_from_imu, base_rotation_from_imu, \
    imu_quaternion
from humfall_ros.multicontact.executor import planar_state, project_to_mode
from humfall_ros.multicontact.modes import mode_label, parse_mode


def sensed_state(model: HumanoidModel, joints, joint_velocities, imu_quat_xyzw, imu_gyro, com,
                 com_velocity) -> tuple[np.ndarray, np.ndarray]:
    """The free-flyer state (q, v) in pinocchio's convention (base twist in the base frame) from the encoders, the
    IMU and the estimator's CoM and CoM velocity (module doc). ``model``'s data is overwritten."""
    m, d = model.model, model.data
    qj, vj = np.asarray(joints, float), np.asarray(joint_velocities, float)
    q_rel = model.configuration([0, 0, 0], [0, 0, 0, 1], qj)
    v_rel = np.zeros(m.nv)
    v_rel[6:] = vj
    pin.forwardKinematics(m, d, q_rel, v_rel)
    pin.updateFramePlacements(m, d)
    R_base = base_rotation_from_imu(model, d, imu_quat_xyzw)
    omega = base_angular_velocity_from_imu(model, d, imu_quat_xyzw, imu_gyro)
    q = configuration_from_sensors(model, qj, imu_quat_xyzw, com)
    v = np.zeros(m.nv)
    v[3:6] = R_base.T @ omega
    v[6:] = vj
    J = pin.jacobianCenterOfMass(m, d, q)
    v[:3] = np.linalg.solve(J[:, :3], np.asarray(com_velocity, float) - J[:, 3:] @ v[3:])
    return q, v


class SensedPlanSource:
    """``plan_source`` of a ``MulticontactExecutor``: the plan from the take-over tick's sensed state (module doc).

    Args:
        planner: a ``FallPlanner`` (``profile`` picks one of its request profiles; "" itself).
        model: the 3-D robot, joints in the observation's order (the sensed state is computed on data of its own).
        initial_mode: the contact mode the robot is in at the take-over (the state is projected onto it).
        time_budget: the request's budget [s].

    After a call, ``info`` holds the state (planar energies, projection) and the plan's figures, for the log.
    """

    def __init__(self, planner, model: HumanoidModel, initial_mode: str = "LF/RF", profile: str = "",
                 time_budget: float = 30.0):
        self.planner = planner
        self.model = model.with_own_data()
        self.mode = parse_mode(initial_mode)
        self.profile = profile
        self.time_budget = float(time_budget)
        self.info: dict = {}
        planner.profile(profile)   # an unknown profile fails here, at the start, not at the take-over

    def __call__(self, observation):
        s = observation.state
        imu = observation.inputs.get("imu")   # (orientation, gyro), as both loops give it
        quat = imu_quaternion(imu)
        if quat is None or not isinstance(imu, (tuple, list)) or s is None:
            self.info = {"reason": "no IMU reading or state at the take-over: no plan"}
            return None
        gyro = np.asarray(imu[1], float)
        vals = [s.com, s.com_velocity, observation.joint_position, observation.joint_velocity, gyro]
        if not all(np.all(np.isfinite(np.asarray(x, float))) for x in vals):
            self.info = {"reason": "a non-finite sensed state at the take-over: no plan"}
            return None
        q3, v3 = sensed_state(self.model, observation.joint_position, observation.joint_velocity, quat, gyro,
                              s.com, s.com_velocity)
        pm = self.planner.model
        qp, vp = planar_state(pm, list(self.model.joint_names), q3, v3)
        proj = project_to_mode(pm, qp, vp, self.mode)
        t0 = time.perf_counter()
        r = self.planner.plan({"q": proj.q.tolist(), "v": proj.v.tolist(), "initial_mode": mode_label(self.mode),
                               "planner_profile": self.profile, "time_budget": self.time_budget})
        self.info = {"time": observation.time, "ke_planar": proj.ke_before, "ke_planar_projected": proj.ke_after,
                     "projection_q_shift": proj.q_shift, "projection_contact_gap_m": proj.gap_before,
                     "projection_contact_slip_mps": proj.slip_before, "q": proj.q.tolist(), "v": proj.v.tolist(),
                     "success": bool(r["success"]), "reason": r["reason"], "source": r.get("source", ""),
                     "compute_s": time.perf_counter() - t0, "contact_sequence": list(r["contact_sequence"]),
                     "final_ke": _finite_or_none(r.get("final_ke"))}
        return r["segments"] if r["success"] else None


def _finite_or_none(x):
    try:
        return float(x) if math.isfinite(float(x)) else None
    except (TypeError, ValueError):
        return None


__all__ = ["SensedPlanSource", "sensed_state"]
