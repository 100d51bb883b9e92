"""Centroidal state estimation from joint encoders, the trunk IMU and ankle wrenches.

No ground truth: the base orientation comes from the IMU through the waist
kinematics; the base position and velocity from leg odometry on the sole
corners in contact (they neither sink nor slide). That works for flat feet and
for a foot rocking on an edge or corner while the robot topples, which is
exactly when the fall controller needs the CoM and the capture point.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pinocchio as pin

from humfall_ros.dynamics.pendulum import GRAVITY, capture_point, lean_angle
from humfall_ros.model.humanoid import (SIDES, HumanoidModel, cop_from_wrenches, point_in_polygon_margin,
                                        quat_matrix, support_polygon)


@dataclasses.dataclass
class CentroidalEstimate:
    time: float
    q: np.ndarray
    v: np.ndarray
    com: np.ndarray
    com_velocity: np.ndarray
    angular_momentum: np.ndarray
    cop: np.ndarray
    capture_point: np.ndarray
    support_polygon: np.ndarray      # k x 2, counter-clockwise
    lean_angle: float
    lean_direction: float
    normal_force: float
    contacts: dict                    # side -> bool
    cop_on_edge: bool


class CentroidalEstimator:
    """Leg-odometry floating-base estimator feeding the centroidal quantities."""

    def __init__(self, model: HumanoidModel, contact_force: float = 20.0, corner_tolerance: float = 0.004,
                 edge_margin: float = 0.005, initial_xy=(0.0, 0.0)):
        self.m = model
        self.contact_force = contact_force        # N: a foot with less is in the air
        self.corner_tolerance = corner_tolerance  # m: corners this close to the lowest one touch
        self.edge_margin = edge_margin            # m: CoP this close to the hull boundary is "on the edge"
        self.anchors: dict[str, np.ndarray] = {}  # corner frame -> anchored world xy
        self.base_xy = np.asarray(initial_xy, float).copy()
        self.last: CentroidalEstimate | None = None
        pin_model = model.model
        self._corner_ids = {s: [model.frame_ids[c] for c in model.corner_frames[s]] for s in SIDES}
        self._imu_id = model.frame_ids[model.imu_frame]
        self._data = pin_model.createData()

    # --------------------------------------------------------------- helpers
    def _base_orientation(self, q_joints, imu_quat, imu_gyro) -> tuple[np.ndarray, np.ndarray]:
        """Waist rotation and angular velocity (world) from the chest IMU and the waist joints."""
        m, d = self.m.model, self._data
        q = self.m.configuration([0, 0, 0], [0, 0, 0, 1], q_joints)
        pin.framesForwardKinematics(m, d, q)
        R_b_imu = d.oMf[self._imu_id].rotation
        R_imu = quat_matrix(imu_quat)
        R_base = R_imu @ R_b_imu.T
        return R_base, R_imu @ np.asarray(imu_gyro, float)

    def update(self, t: float, q_joints, v_joints, imu_quat, imu_gyro, wrenches: dict,
               base_truth: tuple | None = None) -> CentroidalEstimate:
        """One estimate. ``wrenches[side] = (force, torque)`` at the ankle in foot axes.

        ``base_truth = (position, quat_xyzw, linear_world, angular_world)`` bypasses the
        odometry (for comparing the estimator with ground truth).
        """
        m, d = self.m.model, self._data
        q_joints = np.asarray(q_joints, float)
        v_joints = np.asarray(v_joints, float)
        contacts = {s: float(wrenches[s][0][2]) > self.contact_force for s in SIDES}
        if base_truth is not None:
            pos, quat, lin, ang = (np.asarray(x, float) for x in base_truth)
            q = self.m.configuration(pos, quat, q_joints)
            v = self.m.velocity(lin, ang, quat, v_joints)
            pin.forwardKinematics(m, d, q, v)
            pin.updateFramePlacements(m, d)
            touching = self._touching_corners(contacts)
        else:
            q, v, touching = self._odometry(t, q_joints, v_joints, imu_quat, imu_gyro, contacts)
        pin.ccrba(m, d, q, v)
        com = d.com[0].copy()
        com_vel = d.hg.linear / self.m.total_mass
        ang_mom = d.hg.angular.copy()
        world_wrenches = []
        for s in SIDES:
            M = d.oMf[self.m.frame_ids[self.m.foot_link[s]]]
            f, tq = wrenches[s]
            world_wrenches.append((M.translation, M.rotation @ np.asarray(f, float), M.rotation @ np.asarray(tq, float)))
        cop, fz = cop_from_wrenches(world_wrenches)
        corner_pts = [d.oMf[fid].translation for _, fid in touching]
        poly = support_polygon(corner_pts) if corner_pts else np.zeros((0, 2))
        if cop is None:  # airborne or unloaded: fall back to the CoM projection
            cop = np.array([com[0], com[1], 0.0])
        cp = capture_point(com, com_vel)
        lean, heading = lean_angle(com, cop)
        on_edge = len(poly) > 0 and point_in_polygon_margin(cop, poly) < self.edge_margin
        est = CentroidalEstimate(t, q, v, com, com_vel, ang_mom, cop, cp, poly, lean, heading, fz, contacts,
                                 bool(on_edge))
        self.last = est
        return est

    def _touching_corners(self, contacts: dict) -> list[tuple[str, int]]:
        """(frame name, frame id) of sole corners on the ground, after kinematics are updated."""
        d = self._data
        cand = [(name, fid) for s in SIDES if contacts[s]
                for name, fid in zip(self.m.corner_frames[s], self._corner_ids[s])]
        if not cand:
            return []
        zmin = min(d.oMf[fid].translation[2] for _, fid in cand)
        return [(n, fid) for n, fid in cand if d.oMf[fid].translation[2] <= zmin + self.corner_tolerance]

    def _odometry(self, t, q_joints, v_joints, imu_quat, imu_gyro, contacts):
        m, d = self.m.model, self._data
        R_base, omega = self._base_orientation(q_joints, imu_quat, imu_gyro)
        quat = pin.Quaternion(R_base).coeffs()  # x, y, z, w
        # kinematics with the base at the origin: corner positions relative to the base
        q = self.m.configuration([0, 0, 0], quat, q_joints)
        v = np.zeros(m.nv)
        v[3:6] = R_base.T @ omega
        v[6:] = v_joints
        pin.forwardKinematics(m, d, q, v)
        pin.updateFramePlacements(m, d)
        touching = self._touching_corners(contacts)
        if touching:
            rel = {n: d.oMf[fid].translation.copy() for n, fid in touching}
            z = -min(p[2] for p in rel.values())
            anchored = [n for n in rel if n in self.anchors]
            if anchored:
                self.base_xy = np.mean([self.anchors[n] - rel[n][:2] for n in anchored], axis=0)
            # corners that just touched down, or lifted, update the anchor set
            self.anchors = {n: (self.anchors[n] if n in self.anchors else self.base_xy + rel[n][:2]) for n in rel}
            # contact corners do not move: v_base = -(omega x r + J_rel qdot), averaged
            vels = [pin.getFrameVelocity(m, d, fid, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED).linear
                    for _, fid in touching]
            v_base = -np.mean(vels, axis=0)
            base_pos = np.array([self.base_xy[0], self.base_xy[1], z])
        else:
            # airborne: ballistic prediction from the last estimate
            self.anchors = {}
            if self.last is None:  # no history: assume the lowest sole corner is on the ground
                zmin = min(d.oMf[fid].translation[2] for s in SIDES for fid in self._corner_ids[s])
                base_pos, v_base = np.array([*self.base_xy, -zmin]), np.zeros(3)
            else:
                dt = max(t - self.last.time, 0.0)
                R_prev = quat_matrix(self.last.q[3:7])
                v_prev = R_prev @ self.last.v[:3]
                v_base = v_prev + np.array([0, 0, -GRAVITY]) * dt
                base_pos = self.last.q[:3] + v_prev * dt
            self.base_xy = base_pos[:2].copy()
        q[:3] = base_pos
        v[:3] = R_base.T @ v_base
        pin.forwardKinematics(m, d, q, v)
        pin.updateFramePlacements(m, d)
        return q, v, touching


def estimate_error(est: CentroidalEstimate, truth: CentroidalEstimate) -> dict:
    """CoM and capture-point errors (m) between two estimates of the same instant."""
    return {"com_error": float(np.linalg.norm(est.com - truth.com)),
            "capture_point_error": float(np.linalg.norm(est.capture_point[:2] - truth.capture_point[:2])),
            "com_velocity_error": float(np.linalg.norm(est.com_velocity - truth.com_velocity))}


__all__ = ["CentroidalEstimate", "CentroidalEstimator", "estimate_error"]
