"""Independent check of a returned plan with pinocchio (no casadi code involved).

Two checks per segment:

* dense residual: the plan's splines (cubic Hermite for q from (q, qdot), for
  qdot from (qdot, qddot), linear u and lambda) are sampled finely and eq. 1 is
  evaluated with pinocchio's ``rnea`` and frame Jacobians; contact rows are
  checked for position and velocity (eq. 3-4).
* forward re-simulation: RK4 on pinocchio's ``aba`` from the segment's start
  state, driven open loop by the plan's u(t) and lambda(t) applied as
  generalised forces J^T lambda; reports how far the contact points drift and
  how far the end state lands from the plan. Open loop on a falling robot the
  error grows with time, so this is a consistency measure, not a controller.
"""
from __future__ import annotations

import numpy as np
import pinocchio as pin

from humfall_ros.multicontact import contacts as C
from humfall_ros.multicontact.collocation import Segment, hermite_eval
from humfall_ros.multicontact.model import PlanarModel
from humfall_ros.multicontact.modes import Environment

# pinocchio frames standing for the planar contact points
_PIN_FRAME = {"LF_toe": "l_sole_toe_left", "LF_heel": "l_sole_heel_left",
              "RF_toe": "r_sole_toe_left", "RF_heel": "r_sole_heel_left",
              "LH": "l_hand", "RH": "r_hand"}


class PinContacts:
    def __init__(self, model: PlanarModel):
        self.pm = model.pin_model
        self.pd = self.pm.createData()
        self.fid = {k: self.pm.getFrameId(v) for k, v in _PIN_FRAME.items()}

    def rows(self, rows, q, env: Environment):
        """Values and Jacobian of contact rows (and Jdot v is not needed here)."""
        pin.computeJointJacobians(self.pm, self.pd, q)
        pin.updateFramePlacements(self.pm, self.pd)
        val = np.zeros(len(rows))
        J = np.zeros((len(rows), self.pm.nv))
        for i, r in enumerate(rows):
            f = self.fid[r.point]
            p = self.pd.oMf[f].translation
            Jf = pin.getFrameJacobian(self.pm, self.pd, f, pin.LOCAL_WORLD_ALIGNED)
            d = C.row_direction(r)
            val[i] = d[0] * p[0] + d[1] * p[2]
            J[i] = d[0] * Jf[0] + d[1] * Jf[2]
        return val, J


def _interp(seg: Segment, t: float):
    k = int(np.clip(np.searchsorted(seg.time, t, side="right") - 1, 0, len(seg.time) - 2))
    t0, t1 = seg.time[k], seg.time[k + 1]
    q, _ = hermite_eval(t0, t1, seg.q[k], seg.v[k], seg.q[k + 1], seg.v[k + 1], t)
    v, a = hermite_eval(t0, t1, seg.v[k], seg.a[k], seg.v[k + 1], seg.a[k + 1], t)
    s = (t - t0) / (t1 - t0)
    u = (1 - s) * seg.u[k] + s * seg.u[k + 1]
    lam = (1 - s) * seg.lam[k] + s * seg.lam[k + 1]
    return q, v, a, u, lam


def dense_check(model: PlanarModel, seg: Segment, env: Environment, samples_per_interval: int = 10) -> dict:
    pc = PinContacts(model)
    pm, pd = pc.pm, pc.pd
    anchors, _ = pc.rows(seg.rows, seg.q[0], env)
    normals = [i for i, r in enumerate(seg.rows) if r.axis == "n"]
    for i in normals:
        anchors[i] = -env.wall_x if seg.rows[i].surface == "wall" else 0.0
    ts = np.linspace(seg.time[0], seg.time[-1], (len(seg.time) - 1) * samples_per_interval + 1)
    worst_dyn = worst_pos = worst_vel = 0.0
    for t in ts:
        q, v, a, u, lam = _interp(seg, t)
        tau = pin.rnea(pm, pd, q, v, a)
        val, J = pc.rows(seg.rows, q, env)
        res = tau - model.B @ u - J.T @ lam
        worst_dyn = max(worst_dyn, float(np.abs(res).max()))
        if len(seg.rows):
            worst_pos = max(worst_pos, float(np.abs(val - anchors).max()))
            worst_vel = max(worst_vel, float(np.abs(J @ v).max()))
    mg = model.total_mass * 9.81
    return {"dyn_residual_max_Nm": worst_dyn, "dyn_residual_rel_mg": worst_dyn / mg,
            "contact_pos_max_m": worst_pos, "contact_vel_max_mps": worst_vel}


def forward_resim(model: PlanarModel, seg: Segment, env: Environment, dt: float = 1e-3) -> dict:
    """RK4 on pinocchio's ABA with the plan's u and lambda (open loop)."""
    pc = PinContacts(model)
    pm = pc.pm
    pd = pm.createData()
    anchors, _ = pc.rows(seg.rows, seg.q[0], env)
    for i, r in enumerate(seg.rows):
        if r.axis == "n":
            anchors[i] = -env.wall_x if r.surface == "wall" else 0.0

    def f(t, x):
        q, v = x[:model.n], x[model.n:]
        _, _, _, u, lam = _interp(seg, t)
        _, J = pc.rows(seg.rows, q, env)
        tau = model.B @ u + J.T @ lam
        return np.concatenate([v, pin.aba(pm, pd, q, v, tau)])

    x = np.concatenate([seg.q[0], seg.v[0]])
    T = float(seg.time[-1])
    steps = max(1, int(np.ceil(T / dt)))
    h = T / steps
    t = 0.0
    worst_pos = worst_vel = 0.0
    for _ in range(steps):
        k1 = f(t, x)
        k2 = f(t + h / 2, x + h / 2 * k1)
        k3 = f(t + h / 2, x + h / 2 * k2)
        k4 = f(t + h, x + h * k3)
        x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        t += h
        if len(seg.rows):
            val, J = pc.rows(seg.rows, x[:model.n], env)
            worst_pos = max(worst_pos, float(np.abs(val - anchors).max()))
            worst_vel = max(worst_vel, float(np.abs(J @ x[model.n:]).max()))
    q_end, v_end = x[:model.n], x[model.n:]
    return {"contact_drift_max_m": worst_pos, "contact_vel_max_mps": worst_vel,
            "end_q_error_max": float(np.abs(q_end - seg.q[-1]).max()),
            "end_v_error_max": float(np.abs(v_end - seg.v[-1]).max()),
            "end_ke_sim": float(0.5 * v_end @ model.pin_crba(q_end) @ v_end), "end_ke_plan": seg.final_ke,
            "duration_s": T}


def check_segment(model: PlanarModel, seg: Segment, env: Environment) -> dict:
    out = dense_check(model, seg, env)
    out.update({"sim_" + k: v for k, v in forward_resim(model, seg, env).items()})
    return out
