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

import contextlib
import os
import sys
import time

import numpy as np
import pinocchio as pin

from humfall_ros.multicontact import contacts as C
from humfall_ros.multicontact.collocation import Segment
from humfall_ros.multicontact.model import PlanarModel
from humfall_ros.multicontact.modes import Environment

# pinocchio frames standing for the planar contact points
_PIN_FRAME = {"LF_toe": "l_sole_toe_left", "LF_heel": "l_sole_heel_left",
              "RF_toe": "r_sole_toe_left", "RF_heel": "r_sole_heel_left",
              "LH": "l_hand", "RH": "r_hand"}


def dense_check(model: PlanarModel, seg: Segment, env: Environment, samples_per_interval: int = 10) -> dict:
    """Eq. 1 and the contacts (eq. 3-4) between the knots: the plan's splines sampled
    ``samples_per_interval`` times per knot interval, the residual tau(q, v, a) - B u - J^T lambda
    with pinocchio's rnea and the contact rows' position and velocity errors."""
    dyn = _BatchDynamics(model, seg, env)
    ts = np.linspace(seg.time[0], seg.time[-1], (len(seg.time) - 1) * samples_per_interval + 1)
    q, v, u, lam, a = dyn._plan(ts, acceleration=True)
    pm, pd = dyn.pm, dyn.pd
    res = np.array([pin.rnea(pm, pd, q[i], v[i], a[i]) for i in range(len(ts))]) - u @ model.B.T
    worst_pos = worst_vel = 0.0
    if len(seg.rows):
        val, J, _ = dyn._rows(q, v)
        res -= (np.swapaxes(J, 1, 2) @ lam[:, :, None])[:, :, 0]
        worst_pos = float(np.abs(val - dyn.anchors).max())
        worst_vel = float(np.abs((J @ v[:, :, None])[:, :, 0]).max())
    worst_dyn = float(np.abs(res).max())
    mg = model.total_mass * 9.81
    return {"dyn_residual_max_Nm": worst_dyn, "dyn_residual_rel_mg": worst_dyn / mg,
            "contact_pos_max_m": worst_pos, "contact_vel_max_mps": worst_vel}


class _BatchDynamics:
    """A segment's constrained dynamics (eq. 1 with its contacts held) for a batch of states.

    The knot-to-knot check restarts from every knot, so its intervals are independent: they are
    integrated side by side, one pinocchio pass per state (crba, rnea, frame Jacobians and
    classical accelerations) and the linear algebra stacked over the batch. Why: an evaluation
    is ~15 us of pinocchio and was ~250 us of per-state numpy calls (session 32). The contact
    force is the plan's lambda plus the smallest correction delta that keeps the contacts in
    place (Baumgarte-stabilised): J M^-1 J^T delta = (required contact acceleration) - (contact
    acceleration under the plan's lambda). With several contacts the internal forces are not
    unique, which is why the plan's force is the starting point; |delta| measures how far the
    plan's forces are from holding the contacts (0 for a consistent plan); the minimum-norm
    delta (singular values below 1e-6 of the largest dropped, as a straight leg would otherwise
    ask for absurd forces).
    """

    def __init__(self, model: PlanarModel, seg: Segment, env: Environment, baumgarte=(400.0, 40.0),
                 mu: float = 0.35, feedback_omega: float = 0.0, feedback_zeta: float = 1.0):
        self.model, self.seg = model, seg
        self.pm = model.pin_model
        self.pd, self.pk = self.pm.createData(), self.pm.createData()
        rows = seg.rows
        points = list(dict.fromkeys(r.point for r in rows))
        self.fids = [self.pm.getFrameId(_PIN_FRAME[p]) for p in points]
        self.row_point = np.array([points.index(r.point) for r in rows], int)
        self.row_dir = np.array([C.row_direction(r) for r in rows], float).reshape(-1, 2)
        self.zero = np.zeros(model.n)
        self.anchors = np.zeros(len(rows))
        if rows:
            val, _, _ = self._rows(seg.q[:1], seg.v[:1])
            self.anchors = val[0]
        for i, r in enumerate(rows):
            if r.axis == "n":
                self.anchors[i] = -env.wall_x if r.surface == "wall" else 0.0
        self.groups = C.friction_groups(rows)
        self._h = np.diff(seg.time)
        self._coef = self._spline_coefficients(seg)
        self._lower = np.tril_indices(model.n, -1)
        self.kp, self.kd = baumgarte
        self.mu, self.omega, self.zeta = mu, feedback_omega, feedback_zeta
        self.mg = model.total_mass * 9.81
        self.reset_stats()

    def reset_stats(self):
        self.stats = {"lam_err": 0.0, "unilateral": 0.0, "friction": 0.0, "feedback": 0.0}

    def _rows(self, q, v):
        """Contact rows' values, Jacobians and J-dot v for each state of the batch."""
        pm, pk = self.pm, self.pk
        nb, npts = len(q), len(self.fids)
        P = np.empty((nb, npts, 3))
        Jf = np.empty((nb, npts, 6, self.model.n))
        acc = np.empty((nb, npts, 3))
        for b in range(nb):
            pin.computeJointJacobians(pm, pk, q[b])
            pin.updateFramePlacements(pm, pk)
            for j, f in enumerate(self.fids):
                P[b, j] = pk.oMf[f].translation
                Jf[b, j] = pin.getFrameJacobian(pm, pk, f, pin.LOCAL_WORLD_ALIGNED)
            pin.forwardKinematics(pm, pk, q[b], v[b], self.zero)
            for j, f in enumerate(self.fids):
                acc[b, j] = pin.getFrameClassicalAcceleration(pm, pk, f, pin.LOCAL_WORLD_ALIGNED).linear
        d0, d1, rp = self.row_dir[:, 0], self.row_dir[:, 1], self.row_point
        val = d0 * P[:, rp, 0] + d1 * P[:, rp, 2]
        J = d0[:, None] * Jf[:, rp, 0, :] + d1[:, None] * Jf[:, rp, 2, :]
        dJv = d0 * acc[:, rp, 0] + d1 * acc[:, rp, 2]
        return val, J, dJv

    def _plan(self, t, acceleration: bool = False):
        """The plan at times t: q, v (cubic Hermite splines), u and lambda (linear); with
        ``acceleration`` also the slope of the velocity spline."""
        seg = self.seg
        k = np.clip(np.searchsorted(seg.time, t, side="right") - 1, 0, len(seg.time) - 2)
        s = ((t - seg.time[k]) / self._h[k])[:, None]
        c = self._coef[k]             # (batch, 4, columns): value = c0 + s c1 + s^2 c2 + s^3 c3
        y = c[:, 0] + s * (c[:, 1] + s * (c[:, 2] + s * c[:, 3]))
        n, m = self.model.n, self.model.m
        out = (y[:, :n], y[:, n:2 * n], y[:, 2 * n:2 * n + m], y[:, 2 * n + m:])
        if not acceleration:
            return out
        dv = c[:, 1, n:2 * n] + s * (2 * c[:, 2, n:2 * n] + 3 * s * c[:, 3, n:2 * n])
        return out + (dv / self._h[k][:, None],)

    @staticmethod
    def _spline_coefficients(seg: Segment) -> np.ndarray:
        """Per knot interval, the power-basis coefficients in s = (t - t_k) / h_k of the plan's
        splines: q from (q, v) and v from (v, a) cubic Hermite (as ``collocation.hermite_eval``), u and lambda
        linear; columns [q, v, u, lambda]."""
        h = np.diff(seg.time)[:, None]

        def hermite(y, dy):
            y0, y1, d0, d1 = y[:-1], y[1:], h * dy[:-1], h * dy[1:]
            return np.stack([y0, d0, 3 * (y1 - y0) - 2 * d0 - d1, 2 * (y0 - y1) + d0 + d1], axis=1)

        def linear(y):
            z = np.zeros_like(y[:-1])
            return np.stack([y[:-1], y[1:] - y[:-1], z, z], axis=1)

        return np.concatenate([hermite(seg.q, seg.v), hermite(seg.v, seg.a), linear(seg.u),
                               linear(np.asarray(seg.lam, float).reshape(len(seg.time), len(seg.rows)))], axis=2)

    def __call__(self, t, x):
        """d/dt [q, v] for states x (batch, 2 n) at times t (batch)."""
        model, pm, pd, n = self.model, self.pm, self.pd, self.model.n
        q, v = x[:, :n], x[:, n:]
        q_plan, v_plan, u, lam_plan = self._plan(t)
        M = np.empty((len(x), n, n))
        bias = np.empty((len(x), n))
        for b in range(len(x)):
            M[b] = pin.crba(pm, pd, q[b])
            bias[b] = pin.rnea(pm, pd, q[b], v[b], self.zero)
        lo, hi = self._lower
        M[:, lo, hi] = M[:, hi, lo]          # crba fills the upper triangle
        if self.omega > 0:
            fb = np.diagonal(M, axis1=1, axis2=2)[:, 3:] * (
                self.omega ** 2 * (q_plan[:, 3:] - q[:, 3:]) + 2 * self.zeta * self.omega * (v_plan[:, 3:] - v[:, 3:]))
            self.stats["feedback"] = max(self.stats["feedback"], float(np.max(np.abs(fb) / model.u_max)))
            u = np.clip(u + fb, -model.u_max, model.u_max)
        force = u @ model.B.T - bias
        if not len(self.seg.rows):
            return np.concatenate([v, np.linalg.solve(M, force[:, :, None])[:, :, 0]], axis=1)
        val, J, dJv = self._rows(q, v)
        Jt = np.swapaxes(J, 1, 2)
        want = -dJv - self.kd * (J @ v[:, :, None])[:, :, 0] - self.kp * (val - self.anchors)
        sol = np.linalg.solve(M, np.concatenate([force[:, :, None] + Jt @ lam_plan[:, :, None], Jt], axis=2))
        a_free, MinvJt = sol[:, :, 0], sol[:, :, 1:]
        delta = (np.linalg.pinv(J @ MinvJt, rcond=1e-6) @ (want - (J @ a_free[:, :, None])[:, :, 0])[:, :, None])
        a = a_free + (MinvJt @ delta)[:, :, 0]
        delta = delta[:, :, 0]
        lam = lam_plan + delta
        st, mg = self.stats, self.mg
        st["lam_err"] = max(st["lam_err"], float(np.abs(delta).max()) / mg)
        for ti, ni in self.groups:
            fn = lam[:, ni].sum(axis=1)
            st["unilateral"] = max(st["unilateral"], max(0.0, -float(lam[:, ni].min())) / mg)
            st["friction"] = max(st["friction"], max(0.0, float((np.abs(lam[:, ti]) - self.mu * fn).max())) / mg)
        return np.concatenate([v, a], axis=1)

    def integrate(self, x, t0, t1, dt: float):
        """RK4 from states x at times t0 to t1 (arrays over the batch), steps of at most dt."""
        x, t0, t1 = np.array(x, float), np.asarray(t0, float), np.asarray(t1, float)
        steps = np.maximum(1, np.ceil((t1 - t0) / dt).astype(int))
        for ns in np.unique(steps):   # one group when the knots are uniform (collocation's are)
            g = steps == ns
            xg, t, h = x[g], t0[g].copy(), (t1[g] - t0[g]) / ns
            hc = h[:, None]
            for _ in range(ns):
                k1 = self(t, xg)
                k2 = self(t + h / 2, xg + hc / 2 * k1)
                k3 = self(t + h / 2, xg + hc / 2 * k2)
                k4 = self(t + h, xg + hc * k3)
                xg = xg + hc / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
                t = t + h
            x[g] = xg
        return x


def forward_resim(model: PlanarModel, seg: Segment, env: Environment, dt: float = 1e-3,
                  baumgarte=(400.0, 40.0), mu: float = 0.35, open_loop: bool = True,
                  feedback_omega: float = 0.0, feedback_zeta: float = 1.0) -> dict:
    """Re-simulate the segment with RK4 on pinocchio's constrained dynamics.

    The plan's u(t) and lambda(t) drive the robot; the simulator adds the
    smallest contact-force correction that keeps the segment's contacts in
    place (see ``_BatchDynamics``) and reports it ("force error"), plus any
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
    dyn = _BatchDynamics(model, seg, env, baumgarte, mu, feedback_omega, feedback_zeta)
    n = model.n
    x = dyn.integrate(np.concatenate([seg.q[:-1], seg.v[:-1]], axis=1), seg.time[:-1], seg.time[1:], dt)
    err = np.abs(x[:, :n] - seg.q[1:])
    local_q = float(err.max())
    worst_coord = model.coordinate_names[int(np.unravel_index(np.argmax(err), err.shape)[1])]
    local_v = float(np.abs(x[:, n:] - seg.v[1:]).max())
    local = dyn.stats
    dyn.reset_stats()
    out = {"local_q_error_max": local_q, "local_q_error_coordinate": worst_coord, "local_v_error_max": local_v,
           "local_force_error_max_mg": local["lam_err"], "local_unilateral_violation_mg": local["unilateral"],
           "local_friction_violation_mg": local["friction"], "duration_s": float(seg.time[-1])}
    if feedback_omega > 0:
        out["local_feedback_max"] = local["feedback"]
    if not open_loop:
        return out
    x = dyn.integrate(np.concatenate([seg.q[0], seg.v[0]])[None], seg.time[:1], seg.time[-1:], dt)
    q_end, v_end = x[0, :n], x[0, n:]
    M = model.pin_crba(q_end)
    whole = "tracked" if feedback_omega > 0 else "open_loop"
    out.update({
        f"{whole}_end_q_error_max": float(np.abs(q_end - seg.q[-1]).max()),
        f"{whole}_end_v_error_max": float(np.abs(v_end - seg.v[-1]).max()),
        f"{whole}_end_ke": float(0.5 * v_end @ M @ v_end), "plan_end_ke": seg.final_ke,
        f"{whole}_force_error_max_mg": dyn.stats["lam_err"],
        f"{whole}_unilateral_violation_mg": dyn.stats["unilateral"],
    })
    if feedback_omega > 0:
        out["tracked_feedback_max"] = dyn.stats["feedback"]
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
        reason = segment_check(model, seg, env, i, q_error_max, force_error_max_mg, feedback_omega, feedback_max)
        if reason:
            return reason
    return None


def segment_check(model: PlanarModel, seg: Segment, env: Environment, index: int, q_error_max: float,
                  force_error_max_mg: float, feedback_omega: float = 0.0, feedback_max: float = 0.5) -> str | None:
    """``plan_check`` of one segment, the ``index``-th of its plan: None when it passes, else the reason."""
    reason = _interval_failure(forward_resim(model, seg, env, open_loop=False),
                               q_error_max, force_error_max_mg, feedback_max)
    if reason and feedback_omega > 0:
        tracked = _interval_failure(
            forward_resim(model, seg, env, open_loop=False, feedback_omega=feedback_omega),
            q_error_max, force_error_max_mg, feedback_max)
        reason = f"{reason}; {tracked}" if tracked else None
    return f"segment {index} ({seg.kind}) fails the re-simulation: {reason}" if reason else None


class SegmentChecks:
    """``plan_check`` of a plan whose segments come one at a time (a library re-plan solves them in
    order): each is checked as it is added, in a worker process when ``pool`` is given, so that the
    check of segment i runs while the caller solves segment i + 1 (session 33: the check was 0.1-0.5 s of
    a 0.5-1 s answer, and IPOPT holds the GIL, so a thread would not overlap). ``result()`` is exactly
    ``plan_check`` of the segments added (the first failing one's reason, in order); a worker that fails
    for any reason of its own is replaced by the check in process."""

    def __init__(self, model: PlanarModel, env: Environment, limits: tuple, pool=None):
        self.model, self.env, self.limits, self.pool = model, env, limits, pool
        self.segments: list[Segment] = []
        self._futures: list = []        # per segment: the worker's future, or None (checked here)
        self._results: dict = {}        # segment index -> its outcome, once known

    def add(self, seg: Segment, in_process: bool = False) -> None:
        """Check ``seg`` (the next segment of the plan): in the worker, or with ``in_process`` here when
        the result is asked for (the last segment: the caller would only wait for the worker)."""
        i = len(self.segments)
        self.segments.append(seg)
        future = None
        if self.pool is not None and not in_process:
            try:
                future = self.pool.submit(_worker_segment_check, self.model.urdf, seg, self.env, i, self.limits)
            except Exception:     # noqa: BLE001 (a broken or shut-down pool: check in process)
                future = None
        self._futures.append(future)

    def _outcome(self, i: int, wait: bool):
        """Segment i's reason or None; ``_PENDING`` when ``wait`` is false and the worker is not done."""
        if i not in self._results:
            f = self._futures[i]
            if f is not None and not wait and not f.done():
                return _PENDING
            try:
                r = f.result() if f is not None else _PENDING
            except Exception:     # noqa: BLE001 (the worker failed on its own: check here)
                r = _PENDING
            self._results[i] = (segment_check(self.model, self.segments[i], self.env, i, *self.limits)
                                if r is _PENDING else r)
        return self._results[i]

    def failed(self) -> str | None:
        """The reason of a segment already known to fail (without waiting for the worker), else None;
        segments checked in process are checked now."""
        for i in range(len(self.segments)):
            r = self._outcome(i, wait=False)
            if r is not _PENDING and r is not None:
                return r
        return None

    def cancel(self) -> None:
        """Drop the checks not started yet (the plan was given up)."""
        for f in self._futures:
            if f is not None:
                f.cancel()

    def result(self) -> str | None:
        """``plan_check`` of the segments added: None when every one passes, else the first failure."""
        # the ones checked here first, while the worker finishes its own
        for i in sorted(range(len(self.segments)), key=lambda i: self._futures[i] is not None):
            self._outcome(i, wait=True)
        return next((self._results[i] for i in range(len(self.segments)) if self._results[i] is not None), None)


class PlanCheck:
    """The re-simulation acceptance test of plans in one environment, with one set of limits
    (``limits``: q_error_max, force_error_max_mg, feedback_omega, feedback_max, as ``plan_check`` takes
    them). Calling it checks a whole plan (``plan_check``: the tree's terminal nodes); ``start()`` gives
    the same test for segments added one at a time (``SegmentChecks``, in the worker process when
    ``workers`` > 0: the library's re-plans)."""

    def __init__(self, model: PlanarModel, env: Environment, limits: tuple, workers: int = 0):
        self.model, self.env, self.limits, self.workers = model, env, tuple(limits), int(workers)

    def __call__(self, segments: list) -> str | None:
        return plan_check(self.model, segments, self.env, *self.limits)

    def start(self) -> SegmentChecks:
        return SegmentChecks(self.model, self.env, self.limits, check_pool() if self.workers > 0 else None)


_PENDING = object()   # a check the worker has not finished


_WORKER_MODELS: dict = {}


def _worker_model(urdf: str) -> PlanarModel:
    """The worker's planar model of ``urdf`` (built once)."""
    model = _WORKER_MODELS.get(urdf)
    if model is None:
        model = _WORKER_MODELS[urdf] = PlanarModel(urdf)
    return model


def _worker_segment_check(urdf: str, seg: Segment, env: Environment, index: int, limits: tuple) -> str | None:
    """``segment_check`` in a worker process."""
    return segment_check(_worker_model(urdf), seg, env, index, *limits)


def _worker_ready(urdf: str) -> int:
    _worker_model(urdf)
    return 0


_POOL = None


def check_pool():
    """The one worker process of this process's parallel checks (``SegmentChecks``), started on first
    use ('spawn': the planner node has threads); stopped by ``shutdown_check_pool`` (also at a normal
    exit), and it leaves by itself when this process is gone (a node killed, or one that leaves without
    its exit handlers)."""
    global _POOL
    if _POOL is None:
        import atexit
        import concurrent.futures
        import multiprocessing
        _POOL = concurrent.futures.ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn"),
                                                       initializer=_watch_parent, initargs=(os.getpid(),))
        atexit.register(shutdown_check_pool)
        with _main_module_hidden():   # the worker process is started by the first submit
            _POOL.submit(int)
    return _POOL


@contextlib.contextmanager
def _main_module_hidden():
    """Keep a spawned worker from importing this process's ``__main__``: 'spawn' re-runs the parent's main
    script in the child, so a user's script without an ``if __name__ == "__main__"`` guard would plan
    again there (multiprocessing refuses it and the pool breaks), and a node started with ``-m`` would
    import rclpy for nothing. The worker needs nothing from it."""
    main = sys.modules.get("__main__")
    saved = {k: main.__dict__[k] for k in ("__file__", "__spec__") if main is not None and k in main.__dict__}
    try:
        main.__dict__.pop("__file__", None)
        if "__spec__" in saved:
            main.__spec__ = None
        yield
    finally:
        main.__dict__.update(saved)


def shutdown_check_pool() -> None:
    """Stop the check's worker (waits for a check it is running, ~0.5 s at most)."""
    global _POOL
    pool, _POOL = _POOL, None
    if pool is not None:
        pool.shutdown(wait=True, cancel_futures=True)


def _watch_parent(parent: int) -> None:
    """In the worker: leave when the process that started it is gone (its pipes would be held open)."""
    import threading

    def watch():
        while os.getppid() == parent:
            time.sleep(0.5)
        os._exit(0)
    threading.Thread(target=watch, daemon=True).start()


def warm_check_pool(urdf: str) -> bool:
    """Start the worker and build its model now (a node's warm-up: ~2 s), not at the first check. False
    when the worker cannot be used (the checks then run in process)."""
    try:
        check_pool().submit(_worker_ready, urdf).result()
        return True
    except Exception:     # noqa: BLE001 (a broken pool: SegmentChecks falls back to the check in process)
        return False
