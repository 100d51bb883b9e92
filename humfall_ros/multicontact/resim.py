"""Independent check of a returned plan with pinocchio (no casadi code involved).

Two checks per segment:

* dense residual: the plan's splines (cubic Hermite for q from (q, qdot), for
  qdot from (qdot, qddot), linear u and lambda) are sampled finely and eq. 1 is
  evaluated with pinocchio's ``rnea`` and frame Jacobians; contact rows are
  checked for position and velocity (eq. 3-4).
* forward re-simulation: RK4 on pinocchio's constrained dynamics (crba, rnea,
  frame Jacobians and accelerations), driven by the plan's u(t) and lambda(t),
  with the force correction the simulator needs to hold the contacts reported
  (see ``forward_resim``).
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


def _constrained_accel(model: PlanarModel, pc: PinContacts, pd, M, rows, q, v, u, lam_plan, anchors, env,
                       baumgarte):
    """Forward dynamics with the segment's contacts held (Baumgarte-stabilised).

    The contact force is the plan's lambda plus the smallest correction delta
    that keeps the contacts in place: J M^-1 J^T delta = (required contact
    acceleration) - (contact acceleration under the plan's lambda). With several
    contacts the internal forces are not unique, which is why the plan's force
    is the starting point; |delta| measures how far the plan's forces are from
    holding the contacts (0 for a consistent plan). ``M`` is the joint-space
    inertia at ``q`` (the caller computes it once per evaluation).
    """
    pm = pc.pm
    b = pin.rnea(pm, pd, q, v, np.zeros(model.n))
    tau = model.B @ u
    if not rows:
        return np.linalg.solve(M, tau - b), np.zeros(0), np.zeros(0)
    val, J = pc.rows(rows, q, env)
    pin.forwardKinematics(pm, pc.pd, q, v, np.zeros(model.n))
    dJv = np.zeros(len(rows))
    for i, r in enumerate(rows):
        acc = pin.getFrameClassicalAcceleration(pm, pc.pd, pc.fid[r.point], pin.LOCAL_WORLD_ALIGNED).linear
        d = C.row_direction(r)
        dJv[i] = d[0] * acc[0] + d[1] * acc[2]
    kp, kd = baumgarte
    want = -dJv - kd * (J @ v) - kp * (val - anchors)
    a_free = np.linalg.solve(M, tau - b + J.T @ lam_plan)
    MinvJt = np.linalg.solve(M, J.T)
    A = J @ MinvJt
    # rcond: near-singular rows (a straight leg) would otherwise ask for absurd forces
    delta = np.linalg.lstsq(A, want - J @ a_free, rcond=1e-6)[0]
    return a_free + MinvJt @ delta, lam_plan + delta, delta


def forward_resim(model: PlanarModel, seg: Segment, env: Environment, dt: float = 1e-3,
                  baumgarte=(400.0, 40.0), mu: float = 0.35, open_loop: bool = True,
                  feedback_omega: float = 0.0, feedback_zeta: float = 1.0) -> dict:
    """Re-simulate the segment with RK4 on pinocchio's constrained dynamics.

    The plan's u(t) and lambda(t) drive the robot; the simulator adds the
    smallest contact-force correction that keeps the segment's contacts in
    place (see ``_constrained_accel``) and reports it ("force error"), plus any
    unilateral / friction violation of the resulting forces. Done twice:

    * per interval: restart from the plan at every knot and integrate to the
      next one; the end-state mismatch is the local integration defect of the
      transcription (what the collocation promises);
    * whole segment: integrate from the first knot to the end; a falling robot
      is unstable, so open loop this grows with the duration and is reported
      for information.

    ``feedback_omega`` > 0 adds a joint-level tracking controller to the
    plan's feed-forward torque, as a robot executing the plan would run:
    u = u_plan + D_jj (omega^2 (q_plan - q) + 2 zeta omega (v_plan - v)) per
    actuated joint (D_jj the joint's diagonal of the joint-space inertia, so
    light and heavy links get the same bandwidth), saturated at the URDF
    torque limits. Why: a loaded straight arm (elbow at its limit) buckles
    with an e-folding time of ~15 ms, so open loop even a consistent plan
    drifts radians within one 0.26 s knot interval (measured on the 80 J hand
    support), while a 6 Hz tracking loop holds it with a few per cent of the
    torque limits. ``feedback_max`` reports the largest feedback torque as a
    fraction of the joint's limit: a plan whose feed-forward is wrong needs
    large feedback.
    """
    pc = PinContacts(model)
    pd = pc.pm.createData()
    anchors, _ = pc.rows(seg.rows, seg.q[0], env)
    for i, r in enumerate(seg.rows):
        if r.axis == "n":
            anchors[i] = -env.wall_x if r.surface == "wall" else 0.0
    mg = model.total_mass * 9.81
    stats = {"lam_err": 0.0, "unilateral": 0.0, "friction": 0.0, "feedback": 0.0}
    groups = C.friction_groups(seg.rows)

    def f(t, x):
        q, v = x[:model.n], x[model.n:]
        q_plan, v_plan, _, u, lam_plan = _interp(seg, t)
        M = pin.crba(pc.pm, pd, q)
        M = np.triu(M) + np.triu(M, 1).T
        if feedback_omega > 0:
            fb = np.diag(M)[3:] * (feedback_omega ** 2 * (q_plan[3:] - q[3:])
                                   + 2 * feedback_zeta * feedback_omega * (v_plan[3:] - v[3:]))
            stats["feedback"] = max(stats["feedback"], float(np.max(np.abs(fb) / model.u_max)))
            u = np.clip(u + fb, -model.u_max, model.u_max)
        a, lam, delta = _constrained_accel(model, pc, pd, M, seg.rows, q, v, u, lam_plan, anchors, env, baumgarte)
        if len(lam):
            stats["lam_err"] = max(stats["lam_err"], float(np.abs(delta).max()) / mg)
            for ti, ni in groups:
                fn = sum(lam[i] for i in ni)
                stats["unilateral"] = max(stats["unilateral"], max(0.0, -min(lam[i] for i in ni)) / mg)
                stats["friction"] = max(stats["friction"], max(0.0, abs(lam[ti]) - mu * fn) / mg)
        return np.concatenate([v, a])

    def integrate(x, t0, t1):
        steps = max(1, int(np.ceil((t1 - t0) / dt)))
        h = (t1 - t0) / steps
        t = t0
        for _ in range(steps):
            k1 = f(t, x)
            k2 = f(t + h / 2, x + h / 2 * k1)
            k3 = f(t + h / 2, x + h / 2 * k2)
            k4 = f(t + h, x + h * k3)
            x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
            t += h
        return x

    n = model.n
    local_q = local_v = 0.0
    worst_coord = ""
    for k in range(len(seg.time) - 1):
        x = integrate(np.concatenate([seg.q[k], seg.v[k]]), seg.time[k], seg.time[k + 1])
        err = np.abs(x[:n] - seg.q[k + 1])
        if float(err.max()) > local_q:
            worst_coord = model.coordinate_names[int(np.argmax(err))]
        local_q = max(local_q, float(err.max()))
        local_v = max(local_v, float(np.abs(x[n:] - seg.v[k + 1]).max()))
    local = dict(stats)
    stats.update({"lam_err": 0.0, "unilateral": 0.0, "friction": 0.0, "feedback": 0.0})
    out = {"local_q_error_max": local_q, "local_q_error_coordinate": worst_coord, "local_v_error_max": local_v,
           "local_force_error_max_mg": local["lam_err"], "local_unilateral_violation_mg": local["unilateral"],
           "local_friction_violation_mg": local["friction"], "duration_s": float(seg.time[-1])}
    if feedback_omega > 0:
        out["local_feedback_max"] = local["feedback"]
    if not open_loop:
        return out
    x = integrate(np.concatenate([seg.q[0], seg.v[0]]), seg.time[0], seg.time[-1])
    q_end, v_end = x[:n], x[n:]
    M = model.pin_crba(q_end)
    whole = "tracked" if feedback_omega > 0 else "open_loop"
    out.update({
        f"{whole}_end_q_error_max": float(np.abs(q_end - seg.q[-1]).max()),
        f"{whole}_end_v_error_max": float(np.abs(v_end - seg.v[-1]).max()),
        f"{whole}_end_ke": float(0.5 * v_end @ M @ v_end), "plan_end_ke": seg.final_ke,
        f"{whole}_force_error_max_mg": stats["lam_err"], f"{whole}_unilateral_violation_mg": stats["unilateral"],
    })
    if feedback_omega > 0:
        out["tracked_feedback_max"] = stats["feedback"]
    return out


def check_segment(model: PlanarModel, seg: Segment, env: Environment, feedback_omega: float = 0.0) -> dict:
    """Dense residual, open-loop re-simulation ("sim_") and, with
    ``feedback_omega`` > 0, the re-simulation under joint tracking ("track_")."""
    out = dense_check(model, seg, env)
    out.update({"sim_" + k: v for k, v in forward_resim(model, seg, env).items()})
    if feedback_omega > 0:
        out.update({"track_" + k: v for k, v in
                    forward_resim(model, seg, env, feedback_omega=feedback_omega).items()})
    return out


def _interval_failure(sim: dict, q_error_max: float, force_error_max_mg: float, feedback_max: float) -> str | None:
    what = "tracked knot-to-knot" if "local_feedback_max" in sim else "knot-to-knot"
    if sim["local_q_error_max"] > q_error_max:
        return f"{what} error {sim['local_q_error_max']:.3g} > {q_error_max:g} ({sim['local_q_error_coordinate']})"
    if sim["local_force_error_max_mg"] > force_error_max_mg:
        return f"{what} contact force correction {sim['local_force_error_max_mg']:.3g} M g > {force_error_max_mg:g} M g"
    if sim.get("local_feedback_max", 0.0) > feedback_max:
        return f"tracking needs feedback torque {sim['local_feedback_max']:.3g} of a joint's limit > {feedback_max:g}"
    return None


def plan_check(model: PlanarModel, segments: list, env: Environment, q_error_max: float,
               force_error_max_mg: float, feedback_omega: float = 0.0, feedback_max: float = 0.5) -> str | None:
    """Acceptance test of a candidate plan with the knot-to-knot re-simulation
    (the local part of ``forward_resim``): None when every segment passes, else
    the reason. The tree calls it before it declares a node terminal: with 8
    knots over a long segment the collocation can hide motion the dynamics do
    not produce (measured: an 80 J plan whose last 1.8 s segment re-simulated
    3.5 rad away from its knots, 2.2 M g of contact force correction).

    A segment passes when the open-loop re-simulation reproduces it within
    ``q_error_max`` and ``force_error_max_mg``, or, with ``feedback_omega``
    > 0, when the same holds under the joint tracking controller of
    ``forward_resim`` (a robot executing the plan) with at most
    ``feedback_max`` of any joint's torque limit as feedback. Why both: the
    open-loop check cannot tell a plan the dynamics do not produce from a
    consistent plan through an unstable posture (a loaded straight arm
    buckles within ~15 ms, so open loop it is radians off within one knot
    interval, tracked a few hundredths); tracking is not the only test either,
    because joint feedback that ignores the contacts pushes a plan whose
    centre of pressure sits on a toe edge (which is where the optimum of a
    landing lies) past that edge. Wrong feed-forward torques fail both (the
    test negates u)."""
    for i, seg in enumerate(segments):
        reason = _interval_failure(forward_resim(model, seg, env, open_loop=False),
                                   q_error_max, force_error_max_mg, feedback_max)
        if reason and feedback_omega > 0:
            tracked = _interval_failure(
                forward_resim(model, seg, env, open_loop=False, feedback_omega=feedback_omega),
                q_error_max, force_error_max_mg, feedback_max)
            reason = f"{reason}; {tracked}" if tracked else None
        if reason:
            return f"segment {i} ({seg.kind}) fails the re-simulation: {reason}"
    return None
