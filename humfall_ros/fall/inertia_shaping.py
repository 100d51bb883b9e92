"""Whole-body inertia shaping of paper 1 §IV (eq. 11-14), from swing touchdown on.

* eq. 11-12: with the robot a reaction-mass pendulum on its CoP P, V_G = omega x PG; to move G
  away from the target T the desired angular velocity is omega_d = -unit(z x PT).
* desired locked inertia: I_d = R I R^T with R = exp([sign * gain * omega_d]x) (the exponential map,
  ``pinocchio.exp3``); ``gain`` [rad per tick] is how far the desired inertia turns each tick.
  **The sign.** The toppling robot pivots passively on P: no ground torque about P, so the
  angular momentum about P, L_P = m PG x V_G + k_G, changes only by gravity over a tick. Joint
  motion that turns the CRB inertia (the body's shape) about omega_d creates centroidal momentum
  k_G along omega_d, and L_P being unchanged, m PG x V_G changes by -k_G: the CoM is sent *towards*
  T. To send it away the shape must turn about -omega_d (``sign = -1``, our default; e.g. for a
  target ahead the hips flex and the trunk pikes forward, which drives the hips and CoM back).
  Measured on standing_push (docs/safe_fall.md): sign +1 gives alpha2 40-46 deg (worse than the
  step alone, 115 deg), sign -1 with the pitch joints 162 deg.
* eq. 13: the CRB-inertia Jacobian J_I (6 x n) maps joint changes to changes of the six unique
  elements of the centroidal composite-rigid-body inertia (``crb_inertia_vector`` order
  Ixx, Iyy, Izz, Ixy, Ixz, Iyz). We build it from the same body inertias pinocchio's CCRBA sums
  (I_G = sum_b R_b I_b R_b^T + m_b (|r_b|^2 1 - r_b r_b^T), r_b = c_b - G) and the joint
  Jacobians: a joint j turns each body below it by a_j and moves its CoM by the column of the
  body's WORLD Jacobian; ``test_fall_inertia`` checks it against finite differences of
  ``HumanoidModel.crb_inertia`` (CCRBA).
* eq. 14: theta' = J_I^# (I_d - I) / dt, the pseudo-inverse over the recruited joints, within
  the joint speed limits and with joints at a position limit (moving outward) dropped and the
  rest re-solved.
* **limb-sweep guard** (ours; the paper shapes blind to where the limbs go): eq. 14's joint motion
  swings whole limbs, and on walking_push the hips it recruited threw the legs into the target the
  step had turned the fall away from. Each limb point off the ground (sole corners of an unloaded
  foot, knees, elbows, hands) is moved by the shaping, relative to the CoM (linear momentum is
  unchanged by joint motion), at v = (J_p - J_G) theta'. If that motion held for ``sweep_horizon_s``
  would bring the point within ``sweep_clearance_m`` of a box to keep clear of, and closer than it is,
  the joints that carry it towards the box are dropped and the rest re-solved, like a joint at its limit.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pinocchio as pin

from humfall_ros.model.humanoid import HumanoidModel

SHAPING_DIRECTIONS = ("away", "turn")   # eq. 12's V_d: -PT (the paper) or the turn about the fall (ours)
_IDX = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))
_GEN = np.array([[[0, 0, 0], [0, 0, -1], [0, 1, 0]], [[0, 0, 1], [0, 0, 0], [-1, 0, 0]],
                 [[0, -1, 0], [1, 0, 0], [0, 0, 0]]], float)   # [e_a]x


def crb_inertia_vector(inertia: np.ndarray) -> np.ndarray:
    """The six unique elements (Ixx, Iyy, Izz, Ixy, Ixz, Iyz) of a symmetric 3 x 3 inertia [kg m^2]."""
    return np.array([inertia[i, j] for i, j in _IDX])


def crb_inertia_and_jacobian(model: HumanoidModel, q) -> tuple[np.ndarray, np.ndarray]:
    """(I_G (3 x 3) [kg m^2], J_I (6 x njoints) [kg m^2 / rad]) at configuration ``q`` (eq. 13)."""
    I, J_I, _ = _crb_inertia_jacobian_com(model, q)
    return I, J_I


def _crb_inertia_jacobian_com(model: HumanoidModel, q) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """I_G, J_I and d G / d theta (3 x njoints); leaves ``model.data``'s joint Jacobians computed at ``q``."""
    m, d = model.model, model.data
    pin.computeJointJacobians(m, d, q)
    com = pin.centerOfMass(m, d, q, False)
    nb = m.njoints - 1
    n = model.njoints
    masses = np.empty(nb)
    cb = np.empty((nb, 3))
    Iw = np.empty((nb, 3, 3))
    Js = np.empty((nb, 6, n))
    for k in range(nb):
        Y = m.inertias[k + 1]
        M = d.oMi[k + 1]
        R = M.rotation
        masses[k] = Y.mass
        cb[k] = M.act(Y.lever)
        Iw[k] = R @ Y.inertia @ R.T
        Js[k] = pin.getJointJacobian(m, d, k + 1, pin.ReferenceFrame.WORLD)[:, 6:]
    w = Js[:, 3:]
    # velocity of each body's CoM per joint column: v_origin + omega x c
    c = cb[:, :, None]
    dc = Js[:, :3] + np.stack([w[:, 1] * c[:, 2] - w[:, 2] * c[:, 1], w[:, 2] * c[:, 0] - w[:, 0] * c[:, 2],
                               w[:, 0] * c[:, 1] - w[:, 1] * c[:, 0]], axis=1)
    total = masses.sum()
    r = cb - com
    I = np.einsum("k,kij->ij", masses, np.einsum("ki,ki->k", r, r)[:, None, None] * np.eye(3)
                  - np.einsum("ki,kj->kij", r, r)) + Iw.sum(axis=0)
    dcom = np.einsum("k,kin->in", masses, dc) / total
    dr = dc - dcom[None]
    # rotational part per column: sum_k [w_k]x Iw_k - Iw_k [w_k]x = sum_k,a w_ka (E_a Iw_k - Iw_k E_a)
    B = np.einsum("aij,kjl->kail", _GEN, Iw) - np.einsum("kij,ajl->kail", Iw, _GEN)   # (nb, 3, 3, 3)
    rot = (w.reshape(nb * 3, n).T @ B.reshape(nb * 3, 9)).reshape(n, 3, 3)
    mdr = dr * masses[:, None, None]                                                   # (nb, 3, n)
    outer = np.tensordot(mdr, r, axes=([0], [0]))                                      # (3, n, 3): sum m dr_i r_j
    outer = outer.transpose(1, 0, 2)
    trace = np.einsum("kin,ki->n", mdr, r)
    par = 2 * trace[:, None, None] * np.eye(3) - outer - outer.transpose(0, 2, 1)
    dI = rot + par                                   # (n, 3, 3)
    J_I = np.stack([dI[:, i, j] for i, j in _IDX])   # (6, n)
    return I, J_I, dcom


def desired_angular_velocity(cop, target, com=None, mode: str = "away") -> np.ndarray:
    """Eq. 12: omega_d = unit(z x V_d) [-], (3,), the pendulum rotation that moves G along V_d (eq. 11).

    ``mode``:

    * ``away`` (the paper): V_d = -PT, so omega_d = -unit(z x PT); zero when T is over P.
    * ``turn`` (ours): V_d = the part of -PT perpendicular to PG (ground projections): it turns the
      fall direction PG away from T (raises the avoidance angle at first order) instead of speeding
      the fall up along -PT; when PG is within 6 deg of PT or of -PT (that part vanishes) or ``com`` is
      None, the paper's. The paper's V_d has the component (PT . PG) along the fall, which for a robot
      already falling away (alpha > 90 deg) mostly shortens the time left to turn.
    """
    pt = np.array([target[0] - cop[0], target[1] - cop[1], 0.0])
    vd = -pt
    if mode == "turn" and com is not None:
        u = np.array([com[0] - cop[0], com[1] - cop[1], 0.0])
        nu, npt = float(np.linalg.norm(u)), float(np.linalg.norm(pt))
        if nu > 1e-6 and npt > 1e-9:
            u /= nu
            perp = vd - u * float(vd @ u)
            if float(np.linalg.norm(perp)) > 0.1 * npt:
                vd = perp
    elif mode not in SHAPING_DIRECTIONS:
        raise ValueError(f"shaping direction must be one of {', '.join(SHAPING_DIRECTIONS)}, got {mode!r}")
    axis = np.cross([0.0, 0.0, 1.0], vd)
    n = float(np.linalg.norm(axis))
    return axis / n if n > 1e-9 else np.zeros(3)


def desired_inertia(inertia: np.ndarray, omega_d: np.ndarray, gain: float) -> np.ndarray:
    """I_d = R I R^T with R = exp(gain * omega_d) (``pinocchio.exp3``); ``gain`` [rad per tick]."""
    R = pin.exp3(gain * np.asarray(omega_d, float))
    return R @ inertia @ R.T


@dataclasses.dataclass(frozen=True)
class ShapingConfig:
    """Inertia-shaping parameters (``config/safe_fall_controller.yaml``).

    Attributes:
        gain: rotation of the desired inertia per tick [rad].
        sign: +1 rotates the CRB inertia about omega_d (eq. 12 read literally), -1 about -omega_d
            (the reaction sign, module docstring; measured: -1 turns the fall away, +1 towards T).
        damping: damping of the pseudo-inverse [kg^2 m^4] (0: plain pseudo-inverse).
        velocity_fraction: joint speeds within this fraction of the URDF limits [-].
        position_margin: joints stay this far inside their limits [rad].
        direction: V_d of eq. 12: "away" (-PT, the paper) or "turn" (ours, :func:`desired_angular_velocity`).
        sweep_horizon_s: limb-sweep guard (module docstring): how far ahead a limb point's shaping motion is
            followed [s] (0: no guard).
        sweep_clearance_m: the guard keeps limb points this far from the boxes [m].
    """

    gain: float = 0.02
    sign: float = -1.0
    damping: float = 1e-4
    velocity_fraction: float = 1.0
    position_margin: float = 0.02
    direction: str = "away"
    sweep_horizon_s: float = 0.1
    sweep_clearance_m: float = 0.15


@dataclasses.dataclass(frozen=True)
class ClearBox:
    """A box the limbs keep clear of (an obstacle): centre [m] (3,), half sizes [m] (3,), yaw [rad]."""

    center: np.ndarray
    half: np.ndarray
    yaw: float = 0.0


def box_distance(points, box: ClearBox) -> tuple[np.ndarray, np.ndarray]:
    """Distance [m] (k,) from points (k, 3) to a box (0 inside) and the unit direction (k, 3) from the box's
    closest point to each point (the box centre's direction for a point inside)."""
    p = np.atleast_2d(np.asarray(points, float))
    c, s = math.cos(box.yaw), math.sin(box.yaw)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    local = (p - np.asarray(box.center, float)) @ R            # rows: R^T (p - c)
    half = np.asarray(box.half, float)
    off = local - np.clip(local, -half, half)
    dist = np.linalg.norm(off, axis=1)
    inside = dist < 1e-12
    off[inside] = local[inside]
    n = np.linalg.norm(off, axis=1, keepdims=True)
    unit = np.where(n > 1e-12, off / np.maximum(n, 1e-12), np.array([0.0, 0.0, 1.0])) @ R.T
    return dist, unit


def _sweep_offenders(model: HumanoidModel, qd: np.ndarray, dcom: np.ndarray, frames, boxes, cfg: ShapingConfig,
                     active: np.ndarray) -> tuple[np.ndarray, list]:
    """Joints (mask) whose shaping motion carries a limb point towards a box it would come within the clearance of.

    Expects ``model.data``'s joint Jacobians at the configuration (``_crb_inertia_jacobian_com``)."""
    m, d = model.model, model.data
    drop = np.zeros_like(active)
    hits = []
    for name in frames:
        fid = model.frame_ids[name]
        pin.updateFramePlacement(m, d, fid)
        p = d.oMf[fid].translation
        Jrel = pin.getFrameJacobian(m, d, fid, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED)[:3, 6:] - dcom
        v = Jrel @ qd
        for b in boxes:
            d_now, _ = box_distance(p, b)
            d_next, unit = box_distance(p + v * cfg.sweep_horizon_s, b)
            if d_next[0] < cfg.sweep_clearance_m and d_next[0] < d_now[0]:
                towards = active & ((unit[0] @ Jrel) * qd < 0.0)   # joint j's share of the motion into the box
                drop |= towards
                hits.append((name, round(float(d_now[0]), 3), round(float(d_next[0]), 3)))
    return drop, hits


def shaping_velocities(model: HumanoidModel, q, cop, target, dt: float, recruit: np.ndarray | None = None,
                       cfg: ShapingConfig | None = None, com=None, keep_clear=(), sweep_frames=()
                       ) -> tuple[np.ndarray, dict]:
    """Eq. 14: joint velocities [rad/s] (njoints,) towards I_d, and diagnostics.

    Args:
        q: configuration (nq,).
        cop: P [m]; target: T [m] (ground, (2,) or (3,)).
        dt: control period [s].
        recruit: mask of the joints that may move (default all).
        com: G [m] (3,) (the ``turn`` direction needs it).
        keep_clear: :class:`ClearBox` es the limb points keep clear of (the limb-sweep guard).
        sweep_frames: model frame names of the limb points the guard follows.
    """
    cfg = cfg or ShapingConfig()
    n = model.njoints
    I, J, dcom = _crb_inertia_jacobian_com(model, q)
    guard = cfg.sweep_horizon_s > 0 and len(keep_clear) > 0 and len(sweep_frames) > 0
    omega_d = desired_angular_velocity(cop, target, com, cfg.direction)
    Id = desired_inertia(I, omega_d, cfg.sign * cfg.gain)
    err = crb_inertia_vector(Id) - crb_inertia_vector(I)
    active = np.ones(n, bool) if recruit is None else np.asarray(recruit, bool).copy()
    qj = np.asarray(q, float)[7:]
    lo = model.limits.lower + cfg.position_margin
    hi = model.limits.upper - cfg.position_margin
    vmax = cfg.velocity_fraction * model.limits.velocity
    qd = np.zeros(n)
    swept = []
    for _ in range(8):  # drop joints that would leave their range or sweep a limb into a box, re-solve with the rest
        Ja = J[:, active]
        if Ja.shape[1] == 0:
            qd = np.zeros(n)
            break
        A = Ja @ Ja.T + cfg.damping * np.eye(6)
        dq = Ja.T @ np.linalg.solve(A, err)
        qd = np.zeros(n)
        qd[active] = dq / dt
        scale = np.max(np.abs(qd) / vmax)
        if scale > 1.0:
            qd /= scale
        nxt = qj + qd * dt
        out = active & (((nxt < lo) & (qd < 0)) | ((nxt > hi) & (qd > 0)))
        if guard:
            drop, hits = _sweep_offenders(model, qd, dcom, sweep_frames, keep_clear, cfg, active)
            out |= drop
            swept += hits
        if not np.any(out):
            break
        active &= ~out
    else:   # still offending after the last re-solve: those joints stand still
        qd[out] = 0.0
    info = {"inertia": I, "desired_inertia": Id, "omega_d": omega_d,
            "residual": float(np.linalg.norm(err - J @ (qd * dt))), "error": float(np.linalg.norm(err)),
            "recruited": int(active.sum()), "swept": swept}
    return qd, info


__all__ = ["SHAPING_DIRECTIONS", "ClearBox", "ShapingConfig", "box_distance", "crb_inertia_and_jacobian",
           "crb_inertia_vector", "desired_angular_velocity", "desired_inertia", "shaping_velocities"]
