"""The shared whole-body inverse kinematics (differential IK as a small QP). No rclpy, no simulator.

Used by the walking pattern (``humfall_ros.walking``), the safe-fall step controller
(paper 1, eq. 10: a foot placed while the stance foot is held) and the e-stop's final-posture
feasibility check (paper 3 §V: can the robot reach the stopped posture?).

Model
-----
Configuration ``q`` (nq = 7 + 22) and tangent velocity ``v`` (nv = 6 + 22) in the pinocchio
free-flyer convention of :mod:`humfall_ros.model.humanoid`. One call of :meth:`WholeBodyIK.solve`
finds the velocity ``v`` of one time step ``dt`` [s]::

    minimise    sum_i || W_i^(1/2) (J_i v - xdot_i) ||^2  +  damping ||v||^2
    subject to  J_h v = xdot_h                                 (hard frame tasks: a fixed foot)
                max(-s v_max, (q_min - q)/dt) <= v_j <= min(s v_max, (q_max - q)/dt)   (joints)

with ``xdot_i = feedforward_i + gain_i * error_i / dt`` per task, and returns
``q_next = integrate(q, v dt)``. ``s`` is ``velocity_fraction`` (keep commanded speeds a margin
under the URDF velocity limits the simulator enforces). Tasks (shapes of ``J_i`` in brackets):

* :class:`ComTask` -- whole-body centre of mass [3 x nv] (pinocchio ``jacobianCenterOfMass``),
* :class:`FrameTask` -- a frame's 6-D pose [6 x nv] (``LOCAL_WORLD_ALIGNED``: linear rows in
  world axes at the frame origin, then angular rows in world axes); ``hard=True`` makes it an
  equality constraint (the way to *fix a foot*),
* :class:`OrientationTask` -- a frame's orientation only [3 x nv] (the trunk),
* :class:`PostureTask` -- joint positions [22 x nv] (regularises the null space: arms, waist).

Weights are per task, scalar or per row (e.g. ``(1, 1, 1, 0.1, 0.1, 0.1)``; a zero row drops it).
``fixed_base=True`` freezes the free-flyer (the base is the reference, e.g. a pinned waist);
with the free-flyer free (default), a hard foot task makes that support foot the base.

Why our own QP and not pink's ``solve_ik``: pink (pin-pink 4.4 with daqp) solves the same soft
problem in 0.32 ms median here, but it has no equality constraints (a foot held exactly, which
the step controller and the e-stop need), and this module needs only one jacobian pass per
call. The QP is solved with daqp (a dual active-set solver: exact bounds, warm-startable);
measured times are in docs/walking.md (``benchmarks/bench_walking.py``).
"""
from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Sequence

import daqp
import numpy as np
import pinocchio as pin

from humfall_ros.model.humanoid import HumanoidModel

_INF = 1e20  # daqp reads |bounds| >= 1e20 as unbounded


class IKError(RuntimeError):
    """A task names an unknown frame or has the wrong shape."""


def _weights(w, n: int) -> np.ndarray:
    if isinstance(w, (int, float)):
        if not 0.0 <= w < math.inf:
            raise IKError(f"task weights must be finite and >= 0, got {w}")
        return np.full(n, float(w))
    w = np.broadcast_to(np.asarray(w, float), (n,)).copy()
    if np.any(w < 0) or not np.all(np.isfinite(w)):
        raise IKError(f"task weights must be finite and >= 0, got {w}")
    return w


def _norm(e: np.ndarray, w: np.ndarray) -> float:
    e = e[w > 0]
    return math.sqrt(float(e @ e))


@dataclasses.dataclass
class ComTask:
    """Whole-body CoM at ``target`` [m] (world, (3,)); ``velocity`` [m/s] is a feed-forward."""

    target: np.ndarray
    weight: float | Sequence[float] = 10.0
    gain: float = 1.0
    velocity: np.ndarray | None = None


@dataclasses.dataclass
class FrameTask:
    """Frame ``frame`` at ``target`` (pin.SE3, world). ``twist`` [m/s, rad/s] (6,) is a feed-forward
    in LOCAL_WORLD_ALIGNED (linear, angular). ``hard`` makes it an equality constraint."""

    frame: str
    target: pin.SE3
    weight: float | Sequence[float] = 100.0
    gain: float = 1.0
    twist: np.ndarray | None = None
    hard: bool = False


@dataclasses.dataclass
class OrientationTask:
    """Frame ``frame`` with world rotation ``rotation`` (3 x 3); the position is free."""

    frame: str
    rotation: np.ndarray
    weight: float | Sequence[float] = 1.0
    gain: float = 1.0


@dataclasses.dataclass
class PostureTask:
    """Joints (model order, (22,)) at ``joints`` [rad]."""

    joints: np.ndarray
    weight: float | Sequence[float] = 1e-4
    gain: float = 1.0


Task = ComTask | FrameTask | OrientationTask | PostureTask


@dataclasses.dataclass
class IKResult:
    """One IK step.

    Attributes:
        q: the next configuration (nq,).
        v: the tangent velocity of the step [m/s, rad/s] (nv,).
        status: daqp's exit flag (1 = optimal, 2 = soft optimal); <= 0 means the QP failed and
            ``v`` is the damped least-squares solution clipped to the bounds (hard tasks then soft).
        errors: per task, the norm of its weighted-row error *before* the step [m or rad].
        solve_time: wall time of the call [s].
    """

    q: np.ndarray
    v: np.ndarray
    status: int
    errors: list[float]
    solve_time: float

    @property
    def ok(self) -> bool:
        return self.status >= 1


@dataclasses.dataclass
class ConvergenceResult:
    """Outcome of :meth:`WholeBodyIK.solve_to_convergence`.

    Attributes:
        q: final configuration.
        converged: every task error below its tolerance.
        iterations: steps taken.
        errors: per task, the final error norm [m or rad].
        joint_margin: smallest distance of a joint to its position limit [rad] (>= 0 inside).
    """

    q: np.ndarray
    converged: bool
    iterations: int
    errors: list[float]
    joint_margin: float


class WholeBodyIK:
    """Differential whole-body IK on a :class:`HumanoidModel` (see the module docstring).

    Args:
        model: the robot model (its pinocchio model; a private ``Data`` is made here).
        damping: Levenberg-Marquardt style damping on ||v||^2 [1/(s^2)] scaled by dt^2 internally.
        velocity_fraction: joint speeds are bounded by this fraction of the URDF limits.
        fixed_base: freeze the free-flyer (its velocity is 0).
        position_margin: joints stay this far inside their position limits [rad].
    """

    def __init__(self, model: HumanoidModel, damping: float = 1e-6, velocity_fraction: float = 0.95,
                 fixed_base: bool = False, position_margin: float = 0.0):
        self.m = model
        self.model = model.model
        self.data = self.model.createData()
        self.damping = float(damping)
        self.velocity_fraction = float(velocity_fraction)
        self.fixed_base = bool(fixed_base)
        self.position_margin = float(position_margin)
        self.nv = self.model.nv
        self.nj = model.njoints
        self._v_lim = model.limits.velocity
        self._lower = model.limits.lower
        self._upper = model.limits.upper
        self._frame_ids: dict[str, int] = {}
        self._jdiag = (np.arange(6, self.nv), np.arange(6, self.nv))

    def frame_id(self, name: str) -> int:
        fid = self._frame_ids.get(name)
        if fid is None:
            if name not in self.m.frame_ids:
                raise IKError(f"unknown frame {name!r}")
            fid = self._frame_ids[name] = self.m.frame_ids[name]
        return fid

    # ------------------------------------------------------------------ kinematics
    def _kinematics(self, q) -> None:
        pin.computeJointJacobians(self.model, self.data, q)  # runs the forward kinematics
        pin.updateFramePlacements(self.model, self.data)

    def _rows(self, q, task: Task, dt: float):
        """(J, xdot, weights, error norm) of a task at the current kinematics."""
        m, d = self.model, self.data
        if isinstance(task, ComTask):
            J = pin.jacobianCenterOfMass(m, d, False)  # on the joint jacobians of _kinematics
            com = d.com[0]
            err = np.asarray(task.target, float) - com
            xdot = task.gain * err / dt
            if task.velocity is not None:
                xdot = xdot + np.asarray(task.velocity, float)
            w = _weights(task.weight, 3)
            return J, xdot, w, _norm(err, w)
        if isinstance(task, FrameTask):
            fid = self.frame_id(task.frame)
            J = pin.getFrameJacobian(m, d, fid, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED)
            M = d.oMf[fid]
            err = np.empty(6)
            err[:3] = task.target.translation - M.translation
            err[3:] = M.rotation @ pin.log3(M.rotation.T @ task.target.rotation)
            xdot = task.gain * err / dt
            if task.twist is not None:
                xdot = xdot + np.asarray(task.twist, float)
            w = _weights(task.weight, 6)
            return J, xdot, w, _norm(err, w)
        if isinstance(task, OrientationTask):
            fid = self.frame_id(task.frame)
            J = pin.getFrameJacobian(m, d, fid, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED)[3:]
            R = d.oMf[fid].rotation
            err = R @ pin.log3(R.T @ np.asarray(task.rotation, float))
            w = _weights(task.weight, 3)
            return J, task.gain * err / dt, w, _norm(err, w)
        if isinstance(task, PostureTask):
            joints = np.asarray(task.joints, float)
            if joints.shape != (self.nj,):
                raise IKError(f"posture task needs {self.nj} joints, got {joints.shape}")
            err = joints - q[7:]
            w = _weights(task.weight, self.nj)
            return None, task.gain * err / dt, w, _norm(err, w)  # J = [0 I]: added on the diagonal
        raise IKError(f"unknown task type {type(task).__name__}")

    # ------------------------------------------------------------------ solve
    def solve(self, q, tasks: Sequence[Task], dt: float) -> IKResult:
        """One IK step from ``q`` (nq,) over ``dt`` [s]: ``IKResult.q`` is the next configuration."""
        t0 = time.perf_counter()
        q = np.asarray(q, float)
        if dt <= 0:
            raise IKError(f"dt must be > 0, got {dt}")
        self._kinematics(q)
        nv = self.nv
        H = np.zeros((nv, nv))
        f = np.zeros(nv)
        hard_J, hard_b = [], []
        errors = []
        for task in tasks:
            J, xdot, w, e = self._rows(q, task, dt)
            errors.append(e)
            if isinstance(task, FrameTask) and task.hard:
                keep = w > 0
                hard_J.append(J[keep])
                hard_b.append(xdot[keep])
                continue
            if J is None:  # posture: J = [0 I]
                H[self._jdiag] += w
                f[6:] -= w * xdot
                continue
            JW = J.T * w
            H += JW @ J
            f -= JW @ xdot
        H[np.diag_indices(nv)] += self.damping
        lo = np.full(nv, -_INF)
        hi = np.full(nv, _INF)
        qj = q[7:]
        vmax = self.velocity_fraction * self._v_lim
        lo[6:] = np.maximum(-vmax, (self._lower + self.position_margin - qj) / dt)
        hi[6:] = np.minimum(vmax, (self._upper - self.position_margin - qj) / dt)
        # a joint already outside its (margin) limits may move back in: never lo > hi
        bad = lo[6:] > hi[6:]
        if np.any(bad):
            mid = np.clip(0.0, lo[6:], hi[6:])
            lo[6:][bad] = np.minimum(lo[6:][bad], mid[bad])
            hi[6:][bad] = lo[6:][bad]
        if self.fixed_base:
            lo[:6] = hi[:6] = 0.0
        if hard_J:
            A = np.vstack(hard_J)
            b = np.concatenate(hard_b)
            bu = np.concatenate([hi, b])
            bl = np.concatenate([lo, b])
            sense = np.concatenate([np.zeros(nv, np.int32), np.full(len(b), 5, np.int32)])
        else:
            A = np.zeros((0, nv))
            bu, bl, sense = hi, lo, np.zeros(nv, np.int32)
        if self.fixed_base:
            sense[:6] = 5
        v, _, status, _ = daqp.solve(H, f, A, bu, bl, sense)
        status = int(status)
        if status < 1 or not np.all(np.isfinite(v)):
            v = self._fallback(H, f, A, bu[nv:] if hard_J else None, lo, hi)
        q_next = pin.integrate(self.model, q, v * dt)
        return IKResult(q_next, np.asarray(v, float), status, errors, time.perf_counter() - t0)

    def _fallback(self, H, f, A, b, lo, hi) -> np.ndarray:
        """Damped least squares (hard rows weighted 1e4), clipped to the bounds."""
        if b is not None and len(b):
            H = H + 1e4 * A.T @ A
            f = f - 1e4 * A.T @ b
        v = np.linalg.solve(H + 1e-6 * np.eye(len(f)), -f)
        return np.clip(v, lo, hi)

    def solve_to_convergence(self, q, tasks: Sequence[Task], dt: float = 0.05, max_iterations: int = 200,
                             tolerance: float = 1e-4) -> ConvergenceResult:
        """Iterate :meth:`solve` (gain as given) until every task error is below ``tolerance``.

        For static questions (the e-stop's final posture, a landing posture): the velocity limits
        then bound the step per iteration, so ``dt`` sets how far one iteration may move.
        Posture tasks are excluded from the convergence test (they regularise, they are not goals).
        """
        q = np.asarray(q, float).copy()
        goal = [not isinstance(t, PostureTask) for t in tasks]
        errors: list[float] = []
        for it in range(1, max_iterations + 1):
            r = self.solve(q, tasks, dt)
            q = r.q
            errors = self.task_errors(q, tasks)
            if all(e < tolerance for e, g in zip(errors, goal) if g):
                return ConvergenceResult(q, True, it, errors, self.joint_margin(q))
        return ConvergenceResult(q, False, max_iterations, errors, self.joint_margin(q))

    def task_errors(self, q, tasks: Sequence[Task]) -> list[float]:
        """Error norm of each task at ``q`` [m or rad] (weighted rows only)."""
        q = np.asarray(q, float)
        self._kinematics(q)
        return [self._rows(q, t, 1.0)[3] for t in tasks]

    def joint_margin(self, q) -> float:
        """Smallest distance of a joint of ``q`` to its position limits [rad]."""
        qj = np.asarray(q, float)[7:]
        return float(min(np.min(qj - self._lower), np.min(self._upper - qj)))


__all__ = ["ComTask", "ConvergenceResult", "FrameTask", "IKError", "IKResult", "OrientationTask", "PostureTask",
           "Task", "WholeBodyIK"]
