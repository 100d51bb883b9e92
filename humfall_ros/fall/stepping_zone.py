"""Allowable stepping zone of paper 1 §III-C (eq. 5-8), cut by the separatrix and capped by reach.

Eq. 5-7: with both legs' joints theta = [theta_swing, theta_stance] (12,), the swing sole's
velocity relative to the stance sole is ``J_hat theta'`` with the foot-to-foot Jacobian
``J_hat = [J_swing  -J_stance]`` (6 x 12; rows x, y, z, roll, pitch, yaw in world axes).

Eq. 8: the zone's half-extents along k in (x, y, beta = yaw) are
``D_k = dT * sum_i |J_hat_ki| theta'_max,i``. We use the per-joint URDF velocity limits
(the left form of eq. 8) times ``velocity_fraction``; the right form's single gamma is
reported as the equivalent common joint speed ``gamma = D_k / (dT sum_i |J_hat_ki|)`` [rad/s]
(it is the same for x, y and beta only when all limits are equal).

Eq. 8 alone is far beyond the legs (2.1 m x 1.2 m at dT = 0.15 s with our limits), so the
zone is the intersection of

* the eq.-8 box of edges D_x, D_y, D_beta centred on the swing sole (Fig. 6),
* the half-plane ahead of the separatrix: the line through the swing sole perpendicular to
  the fall direction P->Q (paper 1 Fig. 6: a robot falling along PQ cannot put its foot behind),
* the reach disc of the swing leg at the predicted landing posture: the swing hip at the
  predicted CoM (pendulum at touchdown) plus its current offset from the CoM, the ankle at
  most ``reach_fraction`` x (thigh + shank) from it,
* the hip yaw range (beta relative to the stance sole), and beta within ``max_yaw_change`` of the
  swing sole's yaw (ours: turning the swing leg about its hip yaw spins the stance sole, which
  rocks on its toe edge with little yaw friction; measured on ``standing_push``: a 0.6 rad turn
  spun the stance sole by 0.69 rad and the step missed by 0.28 m),
* no overlap with the stance sole and no crossing of the legs (the swing sole stays on its side).
"""
from __future__ import annotations

import dataclasses
import functools
import math

import numpy as np
import pinocchio as pin

from humfall_ros.model.humanoid import HumanoidModel


@dataclasses.dataclass(frozen=True)
class SteppingZone:
    """The allowable stepping zone of one swing foot.

    Attributes:
        swing: "l" or "r".
        center: swing sole at the decision (x, y [m], yaw [rad]).
        half_extent_eq8: half of eq. 8's (D_x [m], D_y [m], D_beta [rad]) (the zone's edges are D, Fig. 6).
        gamma: equivalent common joint speed of eq. 8's right form per row (x, y, beta) [rad/s].
        duration: dT used in eq. 8 [s].
        fall_direction: unit vector of P->Q used for the separatrix [-], (2,).
        hip_xy: predicted swing hip over the ground at touchdown [m], (2,).
        reach_radius: ground radius of the reach disc around ``hip_xy`` [m] (0: unreachable).
        yaw_range: allowed landing yaw (lo, hi) [rad].
        stance_pose: stance sole (x, y, yaw) [m, m, rad].
        x_range, y_range: the box that bounds every constraint [m] (lo, hi) each.
    """

    swing: str
    center: np.ndarray
    half_extent_eq8: np.ndarray
    gamma: np.ndarray
    duration: float
    fall_direction: np.ndarray
    hip_xy: np.ndarray
    reach_radius: float
    yaw_range: tuple[float, float]
    stance_pose: np.ndarray
    x_range: tuple[float, float]
    y_range: tuple[float, float]
    min_lateral: float
    min_longitudinal: float

    @property
    def size(self) -> tuple[float, float]:
        """Extent of the bounding box (x, y) [m]."""
        return (max(0.0, self.x_range[1] - self.x_range[0]), max(0.0, self.y_range[1] - self.y_range[0]))

    def contains(self, xy, yaw) -> np.ndarray:
        """Mask of landing sole poses (xy (n, 2) [m], yaw (n,) [rad]) inside the zone."""
        return self.contains_xy(xy) & self.contains_yaw(yaw)

    def contains_xy(self, xy) -> np.ndarray:
        """The position part of :meth:`contains` (box, separatrix, reach, stance side), (n,) of xy (n, 2) [m]."""
        xy = np.asarray(xy, float).reshape(-1, 2)
        dx, dy = xy[:, 0] - self.center[0], xy[:, 1] - self.center[1]
        ok = (np.abs(dx) <= self.half_extent_eq8[0]) & (np.abs(dy) <= self.half_extent_eq8[1])
        ok &= dx * self.fall_direction[0] + dy * self.fall_direction[1] >= 0.0      # separatrix
        hx, hy = xy[:, 0] - self.hip_xy[0], xy[:, 1] - self.hip_xy[1]
        ok &= hx * hx + hy * hy <= self.reach_radius ** 2                              # reach
        # relative to the stance sole: on the swing side, clear of the stance sole
        c, s = math.cos(self.stance_pose[2]), math.sin(self.stance_pose[2])
        rx, ry = xy[:, 0] - self.stance_pose[0], xy[:, 1] - self.stance_pose[1]
        lon = rx * c + ry * s
        lat = -rx * s + ry * c
        if self.swing != "l":
            lat = -lat
        ok &= lat >= 0.0
        ok &= (lat >= self.min_lateral) | (np.abs(lon) >= self.min_longitudinal)
        return ok

    def contains_yaw(self, yaw) -> np.ndarray:
        """The yaw part of :meth:`contains` (eq.-8 D_beta, hip-yaw range, yaw change), (n,) of yaw (n,) [rad]."""
        yaw = np.asarray(yaw, float).reshape(-1)
        ok = np.abs(_wrap(yaw - self.center[2])) <= self.half_extent_eq8[2]
        ok &= (yaw >= self.yaw_range[0]) & (yaw <= self.yaw_range[1])
        return ok


def _wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


@functools.lru_cache(maxsize=16)
def _leg_joint_indices(model: HumanoidModel, side: str) -> tuple[int, ...]:
    """``HumanoidModel.leg_joint_indices`` cached as a tuple (the zone is computed every decision)."""
    return tuple(model.leg_joint_indices(side))


@functools.lru_cache(maxsize=16)
def _leg_limits(model: HumanoidModel, swing: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(swing then stance leg velocity limits (12,), the two legs' Jacobian columns (6,) each): model constants."""
    stance = "r" if swing == "l" else "l"
    idx = _leg_joint_indices(model, swing) + _leg_joint_indices(model, stance)
    vmax = model.limits.velocity[list(idx)].copy()
    cols = np.array([6 + i for i in idx])
    vmax.setflags(write=False)
    cols.setflags(write=False)
    return vmax, cols[:6], cols[6:]


def foot_to_foot_jacobian(model: HumanoidModel, q, swing: str) -> np.ndarray:
    """Eq. 7: J_hat = [J_swing  -J_stance] (6 x 12) of the soles, world axes (LOCAL_WORLD_ALIGNED).

    Columns: the swing leg's six joints, then the stance leg's (``model.humanoid.LEG_JOINTS`` order).
    """
    stance = "r" if swing == "l" else "l"
    m, d = model.model, model.data
    pin.computeJointJacobians(m, d, q)
    pin.updateFramePlacements(m, d)
    rf = pin.ReferenceFrame.LOCAL_WORLD_ALIGNED
    js = pin.getFrameJacobian(m, d, model.frame_ids[model.sole_frame[swing]], rf)
    jt = pin.getFrameJacobian(m, d, model.frame_ids[model.sole_frame[stance]], rf)
    _, cs, ct = _leg_limits(model, swing)
    return np.hstack([js[:, cs], -jt[:, ct]])


@functools.lru_cache(maxsize=8)
def leg_reach(model: HumanoidModel, side: str = "l") -> float:
    """Hip-to-ankle distance with the knee straight: thigh + shank [m] (from the URDF frames)."""
    m = model.model
    d = m.createData()
    q = pin.neutral(m)
    pin.framesForwardKinematics(m, d, q)
    hip = d.oMf[model.frame_ids[f"{side}_hip_pitch"]].translation
    knee = d.oMf[model.frame_ids[f"{side}_knee"]].translation
    ankle = d.oMf[model.frame_ids[f"{side}_ankle_pitch"]].translation
    return float(np.linalg.norm(knee - hip) + np.linalg.norm(ankle - knee))


def sole_pose_2d(placement: pin.SE3) -> np.ndarray:
    """(x, y, yaw) of a sole placement [m, m, rad] (yaw of its x axis over the ground)."""
    R = placement.rotation
    return np.array([placement.translation[0], placement.translation[1], math.atan2(R[1, 0], R[0, 0])])


def stepping_zone(model: HumanoidModel, q, swing: str, duration: float, fall_direction, predicted_com,
                  velocity_fraction: float = 1.0, reach_fraction: float = 0.98, gap: float = 0.02,
                  hip_drop: float = 0.0, max_yaw_change: float = math.inf,
                  yaw_reference: float | None = None) -> SteppingZone:
    """The allowable stepping zone (module docstring) at configuration ``q`` (world placement).

    Args:
        q: configuration (nq,) in the world (base pose included).
        swing: the stepping foot, "l" or "r".
        duration: dT of eq. 8, the swing time [s].
        fall_direction: P->Q over the ground (the separatrix normal), (2,).
        predicted_com: CoM at touchdown by the pendulum [m], (3,).
        velocity_fraction: usable fraction of the URDF joint speed limits [-].
        reach_fraction: usable fraction of thigh + shank [-].
        gap: clearance between the soles [m].
        hip_drop: how far the stance knee may lower the swing hip below the pendulum's prediction [m].
        max_yaw_change: landing yaw within this of ``yaw_reference`` [rad].
        yaw_reference: [rad] (default: the swing sole's yaw now; a re-plan passes the lift-off yaw).
    """
    stance = "r" if swing == "l" else "l"
    J = foot_to_foot_jacobian(model, q, swing)   # also updates the frame placements
    vmax = _leg_limits(model, swing)[0] * velocity_fraction
    rows = J[[0, 1, 5]]
    D = duration * np.abs(rows) @ vmax   # eq. 8: the zone's edge lengths (Fig. 6), centred on the swing sole
    gamma = D / np.maximum(duration * np.sum(np.abs(rows), axis=1), 1e-12)
    half = 0.5 * D
    d = model.data
    sw = sole_pose_2d(d.oMf[model.frame_ids[model.sole_frame[swing]]])
    st = sole_pose_2d(d.oMf[model.frame_ids[model.sole_frame[stance]]])
    com = pin.centerOfMass(model.model, d, q)
    hip = d.oMf[model.frame_ids[f"{swing}_hip_pitch"]].translation
    hip_pred = np.asarray(predicted_com, float) + (hip - com)
    r = reach_fraction * leg_reach(model, swing)
    dz = hip_pred[2] - hip_drop - model.ankle_height
    rho = math.sqrt(r * r - dz * dz) if r > abs(dz) else 0.0
    u = np.asarray(fall_direction, float)[:2]
    u = u / max(float(np.linalg.norm(u)), 1e-12)
    hy = model.joint_index(f"{swing}_hip_yaw")
    yref = sw[2] if yaw_reference is None else float(yaw_reference)
    yaw_lo = max(st[2] + float(model.limits.lower[hy]), yref - max_yaw_change)
    yaw_hi = min(st[2] + float(model.limits.upper[hy]), yref + max_yaw_change)
    x_range = (max(sw[0] - half[0], hip_pred[0] - rho), min(sw[0] + half[0], hip_pred[0] + rho))
    y_range = (max(sw[1] - half[1], hip_pred[1] - rho), min(sw[1] + half[1], hip_pred[1] + rho))
    return SteppingZone(swing, sw, half, gamma, float(duration), u, hip_pred[:2].copy(), float(rho), (yaw_lo, yaw_hi),
                        st, x_range, y_range, model.foot_width + gap, model.foot_length + gap)


__all__ = ["SteppingZone", "foot_to_foot_jacobian", "leg_reach", "sole_pose_2d",
           "stepping_zone"]
