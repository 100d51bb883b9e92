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

from humfall_ros import params as params_mod
from humfall_ros.dynamics.pendulum import GRAVITY, capture_point, lean_angle
from humfall_ros.model.humanoid import (SIDES, HumanoidModel, base_angular_velocity_from_imu, base_rotation_from_imu,
                                        cop_from_wrenches, cross3, point_in_polygon_margin, quat_matrix,
                                        support_polygon)


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
    feet_center: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(3))  # mid-point of the ankles
    # per foot, from that ankle's wrench alone (foot force difference control, walking/stabilizer.py loop 4):
    foot_normal_force: dict = dataclasses.field(default_factory=lambda: {s: 0.0 for s in SIDES})  # side -> N
    foot_cop: dict = dataclasses.field(default_factory=lambda: {s: np.zeros(3) for s in SIDES})   # side -> m, z = 0
    # the complementary filter's velocity and its capture point (``_fuse_com_velocity``; the kinematic ones when
    # it is off): ``update`` always fills them
    com_velocity_fused: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(3))
    capture_point_fused: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(3))


class CentroidalEstimator:
    """Leg-odometry floating-base estimator feeding the centroidal quantities."""

    def __init__(self, model: HumanoidModel, contact_force: float | None = None, corner_tolerance: float = 0.004,
                 edge_margin: float = 0.005, initial_xy=(0.0, 0.0), com_velocity_time_constant: float | None = None,
                 com_velocity_band: float | None = None):
        """``contact_force``, ``com_velocity_time_constant``, ``com_velocity_band``: None is the declared default of
        config/state_estimator.yaml (one place); ``com_velocity_time_constant=0`` turns the fusion off."""
        declared = params_mod.defaults("state_estimator")
        contact_force = declared["contact_force"] if contact_force is None else contact_force
        if com_velocity_time_constant is None:
            com_velocity_time_constant = declared["com_velocity_time_constant"]
        if com_velocity_band is None:
            com_velocity_band = declared["com_velocity_band"]
        self.m = model
        # s; > 0: the CoM velocity fuses the ground reaction (Newton) with kinematics (``_fuse_com_velocity``)
        self.com_velocity_time_constant = float(com_velocity_time_constant)
        # m/s; > 0: the fused velocity stays within this distance of the kinematic one (``_fuse_com_velocity``)
        self.com_velocity_band = float(com_velocity_band)
        self.contact_force = contact_force        # N: a foot with less is in the air
        self.corner_tolerance = corner_tolerance  # m: corners this close to the lowest one touch
        self.edge_margin = edge_margin            # m: CoP this close to the hull boundary is "on the edge"
        self.initial_xy = np.asarray(initial_xy, float).copy()
        self.reset()
        pin_model = model.model
        self._corner_ids = {s: [model.frame_ids[c] for c in model.corner_frames[s]] for s in SIDES}
        self._data = pin_model.createData()

    def reset(self) -> None:
        """Forget the odometry (a new run: the robot stands at ``initial_xy`` again)."""
        self.anchors: dict[str, np.ndarray] = {}  # corner frame -> anchored world xy
        self.base_xy = self.initial_xy.copy()
        self.last: CentroidalEstimate | None = None

    # --------------------------------------------------------------- helpers
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
        else:
            q, v = self._odometry(t, q_joints, v_joints, imu_quat, imu_gyro, contacts)
        # one pass: CCRBA runs the forward kinematics the frames below need
        pin.ccrba(m, d, q, v)
        pin.updateFramePlacements(m, d)
        com = d.com[0].copy()
        com_vel = d.hg.linear / self.m.total_mass
        ang_mom = d.hg.angular.copy()
        world_wrenches = []
        feet_center = np.zeros(3)
        foot_fz, foot_cop = {}, {}
        for s in SIDES:
            M = d.oMf[self.m.frame_ids[self.m.foot_link[s]]]
            feet_center += M.translation / len(SIDES)
            f, tq = wrenches[s]
            R = M.rotation
            w = (M.translation, R @ np.asarray(f, float), R @ np.asarray(tq, float))
            world_wrenches.append(w)
            # the foot's own CoP and normal force (the same formula on its wrench alone); unloaded: below its ankle
            p_s, foot_fz[s] = cop_from_wrenches([w])
            foot_cop[s] = p_s if p_s is not None else np.array([M.translation[0], M.translation[1], 0.0])
        cop, fz = cop_from_wrenches(world_wrenches)
        # two velocities: the kinematic one (no lag: the fall trigger and the safe fall) and the fused one
        com_vel_fused = com_vel if base_truth is not None else self._fuse_com_velocity(t, com_vel, world_wrenches)
        touching = self._touching({n: d.oMf[fid].translation for n, fid in self._candidates(contacts)})
        poly = support_polygon(list(touching.values())) if touching else np.zeros((0, 2))
        if cop is None:  # airborne or unloaded: fall back to the CoM projection
            cop = np.array([com[0], com[1], 0.0])
        cp = capture_point(com, com_vel)
        cp_fused = cp if com_vel_fused is com_vel else capture_point(com, com_vel_fused)
        lean, heading = lean_angle(com, cop)
        on_edge = len(poly) > 0 and point_in_polygon_margin(cop, poly) < self.edge_margin
        est = CentroidalEstimate(t, q, v, com, com_vel, ang_mom, cop, cp, poly, lean, heading, fz, contacts,
                                 bool(on_edge), feet_center, foot_fz, foot_cop, com_vel_fused.copy(), cp_fused.copy())
        self.last = est
        return est

    def _fuse_com_velocity(self, t: float, kinematic: np.ndarray, world_wrenches: list) -> np.ndarray:
        """The CoM velocity by a complementary filter: Newton on the measured ground reaction, kinematics below 1/tau.

        Leg odometry holds the corners in contact still; a stance foot that slides (about 40 mm/s at the end
        of a 1.35 km/h single support, measured) or an impact breaks that for tens of milliseconds, and the
        capture point moves by the velocity error over omega. The ankle wrenches integrate to the CoM velocity
        without the assumption (m c'' = sum f + m g): exact at high frequencies, but drifting with a force
        bias or with contacts the ankles do not see (hands, knees) and, above all, behind a push: an external
        force the ankles do not measure reaches the fused velocity only at 1/tau. First order:
        v = v_pred + dt / (tau + dt) (v_kin - v_pred), v_pred = v_last + (sum f / m + g) dt.

        With ``com_velocity_band`` b > 0 the result is then held within b of the kinematic velocity
        (``v = v_kin + b (v - v_kin) / |v - v_kin|`` when farther; the state carries the held value): the slip the
        filter is for is a few cm/s, a push makes the two differ by its whole velocity change. So slips are
        filtered as without the band, while a push (or a force bias, or an unmeasured hand contact) leaves the
        fused velocity at most b behind the odometry, the capture point at most b / omega.
        """
        tau, last = self.com_velocity_time_constant, self.last
        if tau <= 0.0 or last is None:
            return kinematic
        dt = t - last.time
        if dt == 0.0:  # the same tick again (a retransmission): the same answer
            return last.com_velocity_fused.copy()
        if not 0.0 < dt <= 0.05:  # a gap or time going back: start again from kinematics
            return kinematic
        force = np.sum([w[1] for w in world_wrenches], axis=0)
        predicted = last.com_velocity_fused + (force / self.m.total_mass + np.array([0.0, 0.0, -GRAVITY])) * dt
        fused = predicted + dt / (tau + dt) * (kinematic - predicted)
        band = self.com_velocity_band
        if band > 0.0:
            off = fused - kinematic
            n = float(np.linalg.norm(off))
            if n > band:
                fused = kinematic + off * (band / n)
        return fused

    def _candidates(self, contacts: dict) -> list[tuple[str, int]]:
        """(name, frame id) of the sole corners of the feet that carry load."""
        return [(name, fid) for s in SIDES if contacts[s]
                for name, fid in zip(self.m.corner_frames[s], self._corner_ids[s])]

    def _touching(self, positions: dict) -> dict:
        """The corners (name -> position) within ``corner_tolerance`` of the lowest one."""
        if not positions:
            return {}
        zmin = min(p[2] for p in positions.values())
        return {n: p for n, p in positions.items() if p[2] <= zmin + self.corner_tolerance}

    def _odometry(self, t, q_joints, v_joints, imu_quat, imu_gyro, contacts):
        """Base pose and twist from the IMU and the corners in contact (paper-free leg odometry).

        One kinematics pass with the base at the origin gives every frame relative
        to the waist; the IMU then orients it and the contact corners place it.
        """
        m, d = self.m.model, self._data
        q_rel = self.m.configuration([0, 0, 0], [0, 0, 0, 1], q_joints)
        v_rel = np.zeros(m.nv)
        v_rel[6:] = v_joints
        pin.forwardKinematics(m, d, q_rel, v_rel)
        pin.updateFramePlacements(m, d)
        R_base = base_rotation_from_imu(self.m, d, imu_quat)
        omega = base_angular_velocity_from_imu(self.m, d, imu_quat, imu_gyro)
        quat = pin.Quaternion(R_base).coeffs()  # x, y, z, w
        cand = self._candidates(contacts)
        rel = {n: R_base @ d.oMf[fid].translation for n, fid in cand}  # corner - base, world axes
        touching = self._touching(rel)
        if touching:
            z = -min(p[2] for p in touching.values())
            anchored = [n for n in touching if n in self.anchors]
            if anchored:
                self.base_xy = np.mean([self.anchors[n] - touching[n][:2] for n in anchored], axis=0)
            # corners that just touched down, or lifted, update the anchor set
            self.anchors = {n: (self.anchors[n] if n in self.anchors else self.base_xy + touching[n][:2])
                            for n in touching}
            # the contact corners do not move: v_base + omega x r + R v_rel = 0, averaged
            ids = dict(cand)
            vels = [cross3(omega, touching[n]) + R_base @ pin.getFrameVelocity(
                m, d, ids[n], pin.ReferenceFrame.LOCAL_WORLD_ALIGNED).linear for n in touching]
            v_base = -np.mean(vels, axis=0)
            base_pos = np.array([self.base_xy[0], self.base_xy[1], z])
        else:
            # airborne: ballistic prediction from the last estimate
            self.anchors = {}
            if self.last is None:  # no history: assume the lowest sole corner is on the ground
                zmin = min((R_base @ d.oMf[fid].translation)[2] for s in SIDES for fid in self._corner_ids[s])
                base_pos, v_base = np.array([*self.base_xy, -zmin]), np.zeros(3)
            else:
                dt = max(t - self.last.time, 0.0)
                v_prev = quat_matrix(self.last.q[3:7]) @ self.last.v[:3]
                v_base = v_prev + np.array([0, 0, -GRAVITY]) * dt
                base_pos = self.last.q[:3] + v_prev * dt
            self.base_xy = base_pos[:2].copy()
        q = self.m.configuration(base_pos, quat, q_joints)
        v = np.empty(m.nv)
        v[:3] = R_base.T @ v_base
        v[3:6] = R_base.T @ omega
        v[6:] = v_joints
        return q, v


def estimate_error(est: CentroidalEstimate, truth: CentroidalEstimate) -> dict:
    """CoM and capture-point errors (m) between two estimates of the same instant.

    In the world frame, and relative to the feet (mid-point of the ankles): leg
    odometry drifts in the world like any odometry, but balance decisions compare
    the CoM and capture point with the support polygon, which drifts with them.
    """
    rel = est.feet_center - truth.feet_center
    return {"com_error": float(np.linalg.norm(est.com - truth.com)),
            "capture_point_error": float(np.linalg.norm(est.capture_point[:2] - truth.capture_point[:2])),
            "com_velocity_error": float(np.linalg.norm(est.com_velocity - truth.com_velocity)),
            "com_error_feet_relative": float(np.linalg.norm(est.com - truth.com - rel)),
            "capture_point_error_feet_relative": float(np.linalg.norm(est.capture_point[:2] - truth.capture_point[:2]
                                                                      - rel[:2])),
            # the complementary filter's (equal to the above when it is off)
            "com_velocity_fused_error": float(np.linalg.norm(est.com_velocity_fused - truth.com_velocity)),
            "capture_point_fused_error_feet_relative": float(np.linalg.norm(
                est.capture_point_fused[:2] - truth.capture_point[:2] - rel[:2]))}


__all__ = ["CentroidalEstimate", "CentroidalEstimator", "estimate_error"]
