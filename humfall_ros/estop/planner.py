"""The emergency-stop planner of paper 3 (§III-IV): from the current pattern state to a typed stop plan.

No rclpy, no simulator. :meth:`EstopPlanner.plan` reads **only** the current pattern state
(:class:`PatternState`: reference CoG and its velocity, reference ZMP, the two foot poses, the
CoG height) -- never walking parameters or future footsteps (§III-A) -- and returns a
:class:`StopPlan`:

1. the Major/Minor frame from the feet (Fig. 3, :mod:`humfall_ros.estop.frame`);
2. Minor axis (eq. 3-7): the optimal-regulator poles (computed once at ``lqr_cog_height``)
   re-placed for omega_c at the trigger height (gains by eq. 5 coefficient matching);
3. Major axis (eq. 8-21): alpha = -omega_c (so n1 = 0, eq. 17-18), beta by ``beta_policy``,
   gains by eq. 19-20, n1..n3 of eq. 16, the lower bound of eq. 22;
4. feasibility: the predicted ZMP -- the lagged ``pbar`` the robot is expected to realise and
   the generated CoG's own LIPM ZMP ``p = c - cddot z / (g + zddot)`` (the reference a
   stabiliser is handed) -- inside the double-support polygon by ``zmp_margin`` on a time grid
   (denser near the start, both ends included), plus closed-form per-axis maxima.

The final-posture check (IK, crouch, fallback) is :mod:`humfall_ros.estop.posture`;
:meth:`EstopPlanner.plan_with_posture` chains both. :meth:`StopPlan.sample` gives the
references at time t after the stop's start, back in the world frame; after ``end_time``
(every mode below ``terminal_tolerance``) it is the final point with velocity exactly 0.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from humfall_ros.dynamics.pendulum import GRAVITY
from humfall_ros.estop.config import EstopConfig
from humfall_ros.estop.frame import FootPose, StopFrame, double_support_polygon
from humfall_ros.estop.posture import PostureSolver
from humfall_ros.estop.statespace import (
    MajorAxisModel,
    MajorAxisSolution,
    MinorAxisModel,
    ModalResponse,
    StateSpaceError,
    lipm_zmp,
    lqr_poles,
    omega_of_height,
    solve_major,
    supremum_two_modes,
)
from humfall_ros.model.humanoid import SIDES, HumanoidModel


class EstopInputError(ValueError):
    """The pattern state is outside what the model can plan from (the message says why)."""


@dataclasses.dataclass(frozen=True)
class PatternState:
    """The walking pattern's state at the trigger: all the planner may read (§III-A).

    Attributes:
        com: reference CoG [m], world, (3,).
        com_velocity: its velocity [m/s], world, (3,) (z is ignored: constant-height LIPM).
        zmp: reference ZMP [m], world, (3,) or (2,) (x, y read).
        feet: ``{"l": FootPose, "r": FootPose}``, the current foot poses (both on the ground).
        cog_height: CoG height above the ground [m] (omega_c = sqrt(g / cog_height), eq. 1).
    """

    com: np.ndarray
    com_velocity: np.ndarray
    zmp: np.ndarray
    feet: dict[str, FootPose]
    cog_height: float

    @property
    def ground_height(self) -> float:
        return float(self.com[2]) - float(self.cog_height)


@dataclasses.dataclass(frozen=True)
class Crouch:
    """A rest-to-rest quintic of the CoG height from ``start_height`` to ``end_height`` [m] over ``duration`` [s]."""

    start_height: float
    end_height: float
    duration: float

    def height(self, t) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(z, zdot, zddot) at times ``t`` [s] (arrays like ``t``)."""
        t = np.asarray(t, float)
        s = np.clip(t / self.duration, 0.0, 1.0)
        dz = self.end_height - self.start_height
        inside = (t > 0) & (t < self.duration)
        z = self.start_height + dz * (10 * s ** 3 - 15 * s ** 4 + 6 * s ** 5)
        zd = np.where(inside, dz * (30 * s ** 2 - 60 * s ** 3 + 30 * s ** 4) / self.duration, 0.0)
        zdd = np.where(inside, dz * (60 * s - 180 * s ** 2 + 120 * s ** 3) / self.duration ** 2, 0.0)
        return z, zd, zdd


@dataclasses.dataclass(frozen=True)
class MinorAxisPlan:
    """The Minor-axis stop (eq. 3-7).

    Attributes:
        gains: ``k_x`` (3,) of eq. 4.
        poles: closed-loop poles [1/s] (3,), complex (the regulator's, re-placed).
        state0: ``[pbar_x, x, xdot](0)`` [m, m, m/s].
        n: residues of pbar_x at the poles [m] (3,), complex: ``pbar_x(t) = Re sum n_i e^(pole_i t)``.
        max_zmp: the pbar_x of largest magnitude over the grid [m] (signed).
        max_lipm_zmp: the same for the generated CoG's LIPM ZMP p_x [m].
        response: [pbar_x, x, xdot](t).
    """

    gains: np.ndarray
    poles: np.ndarray
    state0: np.ndarray
    n: np.ndarray
    max_zmp: float
    max_lipm_zmp: float
    response: ModalResponse


@dataclasses.dataclass(frozen=True)
class MajorAxisPlan:
    """The Major-axis stop (eq. 8-22).

    Attributes:
        solution: gains, alpha, beta, n1..n3, the response.
        y0, ydot0: initial CoG along the Major axis [m, m/s] (pbar_y(0) = 0).
        beta_requested: the configured beta before ``beta_policy`` [1/s].
        max_zmp: sup of |pbar_y| (closed form) [m], signed.
        max_lipm_zmp: sup of |p_y| of the generated CoG (closed form) [m], signed.
        lower_bound: eq. 22, ``y0 + ydot0 / omega_c`` [m].
    """

    solution: MajorAxisSolution
    y0: float
    ydot0: float
    beta_requested: float
    max_zmp: float
    max_lipm_zmp: float
    lower_bound: float

    @property
    def n(self) -> tuple[float, float, float]:
        return self.solution.n

    @property
    def n3(self) -> float:
        return self.solution.n3

    @property
    def gains(self) -> np.ndarray:
        return self.solution.gains


@dataclasses.dataclass(frozen=True)
class StopReference:
    """References at one instant of the stop (world frame).

    Attributes:
        time: since the stop's start [s].
        com, com_velocity, com_acceleration: CoG [m, m/s, m/s^2], (3,).
        zmp: the lagged ZMP pbar the robot is expected to realise (eq. 2) [m], (3,), z = ground.
        zmp_lipm: the generated CoG's own ZMP ``c - cddot z / (g + zddot)`` [m], (3,).
        omega_c: ``sqrt((g + zddot) / z)`` at this instant [1/s].
        done: past ``end_time``: the final point, velocity exactly 0.
    """

    time: float
    com: np.ndarray
    com_velocity: np.ndarray
    com_acceleration: np.ndarray
    zmp: np.ndarray
    zmp_lipm: np.ndarray
    omega_c: float
    done: bool


@dataclasses.dataclass(frozen=True)
class StopPlan:
    """A planned emergency stop (see the module docstring).

    Attributes:
        state: the pattern state it was planned from.
        frame: the Major/Minor frame.
        support_polygon: double-support polygon [m] (k, 2), world.
        omega_c, omega_f, alpha, beta: [1/s] at the trigger height.
        minor, major: the per-axis plans.
        crouch: the vertical trajectory, or None.
        final_com: final CoG [m] (3,), world (Major n3, Minor 0, crouched height).
        min_zmp_margin: smallest predicted distance of pbar and p inside the polygon [m] (< 0 outside);
            feasible needs it >= min(zmp_margin, the initial ZMP's margin).
        stop_time: predicted time the horizontal CoG speed falls below ``settle_speed`` [s].
        end_time: time after which the reference is the final point [s].
        feasible: ZMP inside by the margin and (once checked) the final posture reachable.
        reason: why not (or "" / a note).
        posture: the final-posture check (``humfall_ros.estop.posture.PostureCheck``) or None.
        fallback: the fallback applied ("" if none).
    """

    state: PatternState
    frame: StopFrame
    support_polygon: np.ndarray
    omega_c: float
    omega_f: float
    alpha: float
    beta: float
    minor: MinorAxisPlan
    major: MajorAxisPlan
    crouch: Crouch | None
    final_com: np.ndarray
    min_zmp_margin: float
    stop_time: float
    end_time: float
    feasible: bool
    reason: str
    posture: object | None = None
    fallback: str = ""

    def sample(self, t: float) -> StopReference:
        """References at ``t`` [s] after the stop's start (t < 0 gives t = 0)."""
        t = max(float(t), 0.0)
        ground = self.state.ground_height
        if t >= self.end_time:
            z = self.crouch.end_height if self.crouch else self.state.cog_height
            g = np.array([self.final_com[0], self.final_com[1], ground])
            return StopReference(t, self.final_com.copy(), np.zeros(3), np.zeros(3), g, g.copy(),
                                 math.sqrt(GRAVITY / z), True)
        pos, vel, acc, pbar, z, zd, zdd = _evaluate(self, np.array([t]))
        scale = z / (GRAVITY + zdd)
        com = np.array([*self.frame.to_world(pos[:, 0]), ground + z[0]])
        v = np.array([*self.frame.vector_to_world(vel[:, 0]), zd[0]])
        a = np.array([*self.frame.vector_to_world(acc[:, 0]), zdd[0]])
        zmp = np.array([*self.frame.to_world(pbar[:, 0]), ground])
        lipm = np.array([*self.frame.to_world(pos[:, 0] - acc[:, 0] * scale[0]), ground])
        return StopReference(t, com, v, a, zmp, lipm, float(math.sqrt((GRAVITY + zdd[0]) / z[0])), False)

    def time_grid(self, n: int) -> np.ndarray:
        """n times in [0, end_time], denser near 0 (quadratic spacing) [s]."""
        return self.end_time * np.linspace(0.0, 1.0, n) ** 2


def _evaluate(plan: StopPlan, t: np.ndarray):
    """Local (minor, major) CoG position, velocity, acceleration, pbar (2, k) and z, zdot, zddot (k,)."""
    mr = plan.minor.response(t)                       # pbar_x, x, xdot
    jr = plan.major.solution.response(t)              # pbar_y, y, ydot
    kx = plan.minor.gains
    ky = plan.major.gains
    xdd = -(kx[0] * mr[0] + kx[1] * mr[1] + kx[2] * mr[2])      # eq. 4 with zero references
    ydd = -(ky[0] * (jr[1] - jr[0]) + ky[1] * jr[2])          # eq. 12, r = y - pbar_y (eq. 8)
    pos = np.vstack([mr[1], jr[1]])
    vel = np.vstack([mr[2], jr[2]])
    acc = np.vstack([xdd, ydd])
    pbar = np.vstack([mr[0], jr[0]])
    if plan.crouch is not None:
        z, zd, zdd = plan.crouch.height(t)
    else:
        z = np.full(t.shape, plan.state.cog_height)
        zd = np.zeros(t.shape)
        zdd = np.zeros(t.shape)
    return pos, vel, acc, pbar, z, zd, zdd


def polygon_margins(points: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """Signed distances (k,) of points (k, 2) inside a convex CCW polygon (m, 2) (> 0 inside), vectorised."""
    a = polygon
    e = np.roll(polygon, -1, axis=0) - polygon
    length = np.hypot(e[:, 0], e[:, 1])
    keep = length > 1e-12
    a, e, length = a[keep], e[keep], length[keep]
    d = ((points[:, None, 0] - a[None, :, 0]) * -e[None, :, 1]
         + (points[:, None, 1] - a[None, :, 1]) * e[None, :, 0]) / length[None, :]
    return d.min(axis=1)


def _extreme(values: np.ndarray) -> float:
    """The element of largest magnitude (signed)."""
    i = int(np.argmax(np.abs(values)))
    return float(values[i])


def _end_time(responses: list[ModalResponse], tolerance: float) -> float:
    """Time after which every mode of every output is below ``tolerance`` [s]."""
    end = 0.0
    for r in responses:
        mag = np.max(np.abs(r.coefficients), axis=0)
        decay = -r.rates.real
        for c, d in zip(mag, decay):
            if c > tolerance:
                end = max(end, math.log(c / tolerance) / d)
    return end


class EstopPlanner:
    """Plans stops (paper 3) for one robot model and configuration.

    The Minor-axis regulator poles are computed once (``solve_continuous_are`` at
    ``lqr_cog_height`` with ``Q = diag(minor_lqr_weights)``, ``R = minor_lqr_input_weight``);
    everything else is closed form per call.

    Args:
        model: the robot model (sole geometry for the polygon, limits for the posture check).
        config: the node's parameters.
    """

    def __init__(self, model: HumanoidModel, config: EstopConfig | None = None):
        self.m = model
        self.cfg = config or EstopConfig.defaults()
        c = self.cfg
        nominal = MinorAxisModel(omega_of_height(c.lqr_cog_height), c.omega_f)
        self.minor_poles = lqr_poles(nominal, c.minor_lqr_weights, c.minor_lqr_input_weight)
        self._grid = np.linspace(0.0, 1.0, c.samples) ** 2      # StopPlan.time_grid's spacing
        self._posture_solver = None

    @property
    def posture_solver(self):
        """The final-posture IK (:class:`humfall_ros.estop.posture.PostureSolver`), built on first use."""
        if self._posture_solver is None:
            c = self.cfg
            self._posture_solver = PostureSolver(self.m, c.joint_margin, c.ik_dt, c.ik_max_iterations, c.ik_tolerance)
        return self._posture_solver

    # ------------------------------------------------------------------ validation
    def check_state(self, state: PatternState) -> None:
        """Raise :class:`EstopInputError` when the state is outside the model's validity."""
        c = self.cfg
        vals = [np.ravel(state.com), np.ravel(state.com_velocity), np.ravel(state.zmp), [state.cog_height]]
        for s in SIDES:
            if s not in state.feet:
                raise EstopInputError(f"no pose of foot {s!r}")
            vals += [np.ravel(state.feet[s].position), np.ravel(state.feet[s].rotation)]
        if not np.isfinite(np.concatenate(vals).astype(float)).all():
            raise EstopInputError("the pattern state has a non-finite value")
        if not c.cog_height_min <= state.cog_height <= c.cog_height_max:
            raise EstopInputError(f"CoG height {state.cog_height:.3f} m is outside the model's "
                                  f"[{c.cog_height_min}, {c.cog_height_max}] m")
        speed = float(np.hypot(state.com_velocity[0], state.com_velocity[1]))
        if speed > c.max_cog_speed:
            raise EstopInputError(f"CoG speed {speed:.2f} m/s exceeds max_cog_speed {c.max_cog_speed} m/s")
        omega_c = omega_of_height(state.cog_height)
        if c.omega_f <= (1.0 + c.beta_margin) * omega_c:
            raise EstopInputError(f"omega_f {c.omega_f} 1/s is not above (1 + beta_margin) omega_c "
                                  f"= {(1 + c.beta_margin) * omega_c:.2f} 1/s: no admissible beta")

    def choose_beta(self, omega_c: float, requested: float | None = None) -> float:
        """beta by ``beta_policy``: clamp to [-omega_f, -(1+margin) omega_c], or keep (supremum) below -omega_c,
        or ``omega_c``: -major_beta_ratio * omega_c clamped like ``clamp`` (a requested beta, e.g. the
        fallback's -omega_f, is clamped). With alpha = -omega_c the generated CoG's LIPM ZMP starts at
        p(0) = -beta n3 / omega_f: a slower beta makes that step at the take-over smaller (a larger n3)."""
        c = self.cfg
        beta = c.major_beta if requested is None else float(requested)
        slowest = -(1.0 + c.beta_margin) * omega_c
        if c.beta_policy == "omega_c" and requested is None:
            beta = -c.major_beta_ratio * omega_c
        if c.beta_policy in ("clamp", "omega_c"):
            return float(min(max(beta, -c.omega_f), slowest))
        return float(min(beta, slowest))

    # ------------------------------------------------------------------ planning
    def plan(self, state: PatternState, beta: float | None = None, crouch: Crouch | None = None) -> StopPlan:
        """The stop from ``state`` (closed form + ZMP feasibility; no posture check).

        Args:
            state: the current pattern state only.
            beta: override of the configured beta (before ``beta_policy``) [1/s].
            crouch: a vertical trajectory to plan with (from the posture check), or None.
        Raises:
            EstopInputError: the state is outside the model's validity.
        """
        self.check_state(state)
        c = self.cfg
        feet = state.feet
        frame = StopFrame.from_feet(feet["l"].sole_center(self.m, "l"), feet["r"].sole_center(self.m, "r"), state.zmp)
        polygon = double_support_polygon(self.m, feet)
        omega_c = omega_of_height(state.cog_height)
        com_l = frame.to_local(state.com)
        vel_l = frame.vector_to_local(state.com_velocity)
        zmp_l = frame.to_local(state.zmp)
        # Minor axis: the regulator's poles re-placed at the trigger height (eq. 5)
        mm = MinorAxisModel(omega_c, c.omega_f)
        kx = mm.gains_for_poles(self.minor_poles)
        x0 = np.array([zmp_l[0], com_l[0], vel_l[0]])
        mresp = mm.response(kx, x0, poles=self.minor_poles)
        # Major axis: alpha = -omega_c (eq. 17), beta by policy, gains eq. 19-20, eq. 16
        alpha = -omega_c
        beta_requested = c.major_beta if beta is None else float(beta)
        b = self.choose_beta(omega_c, None if beta is None else float(beta))
        try:
            sol = solve_major(MajorAxisModel(omega_c, c.omega_f), alpha, b, float(com_l[1]), float(vel_l[1]))
        except StateSpaceError as e:
            raise EstopInputError(str(e)) from e
        n1, n2, n3 = sol.n
        sup_zmp = supremum_two_modes(n3, n1, alpha, n2, b)
        p_major = lipm_zmp(sol.response, omega_c)
        sup_lipm = supremum_two_modes(float(p_major.constant[0]), float(p_major.coefficients[0, 0].real), alpha,
                                      float(p_major.coefficients[0, 1].real), b)
        major = MajorAxisPlan(sol, float(com_l[1]), float(vel_l[1]), beta_requested,
                              sup_zmp[0] if abs(sup_zmp[0]) >= abs(sup_zmp[1]) else sup_zmp[1],
                              sup_lipm[0] if abs(sup_lipm[0]) >= abs(sup_lipm[1]) else sup_lipm[1],
                              float(com_l[1] + vel_l[1] / omega_c))
        minor = MinorAxisPlan(kx, mresp.rates.copy(), x0, mresp.coefficients[0].copy(), 0.0, 0.0, mresp)
        end = _end_time([mresp, sol.response], c.terminal_tolerance)
        if crouch is not None:
            end = max(end, crouch.duration)
        z_final = crouch.end_height if crouch else state.cog_height
        final_xy = frame.to_world(np.array([0.0, n3]))
        final_com = np.array([final_xy[0], final_xy[1], state.ground_height + z_final])
        plan = StopPlan(state, frame, polygon, omega_c, c.omega_f, alpha, b, minor, major, crouch, final_com,
                        0.0, 0.0, end, True, "")
        return self._assess(plan)

    def _assess(self, plan: StopPlan) -> StopPlan:
        """Sample the prediction: per-axis Minor maxima, ZMP margins, the stop time, feasibility."""
        c = self.cfg
        t = plan.end_time * self._grid
        pos, vel, acc, pbar, z, _, zdd = _evaluate(plan, t)
        lipm = pos - acc * (z / (GRAVITY + zdd))
        pts = np.vstack([plan.frame.to_world(pbar.T), plan.frame.to_world(lipm.T),
                         plan.final_com[None, :2]])
        margins = polygon_margins(pts, plan.support_polygon)
        margin = float(margins.min())
        # the stop starts where the ZMP is: if that is already nearer the edge than zmp_margin, the
        # plan must not take it nearer still (the initial pbar is the first sample)
        required = min(c.zmp_margin, float(margins[0]))
        speed = np.hypot(vel[0], vel[1])
        above = np.nonzero(speed >= c.settle_speed)[0]
        if not len(above):
            stop_time = 0.0
        elif above[-1] + 1 < len(t):            # interpolate the crossing between the bracketing samples
            i = above[-1]
            f = (speed[i] - c.settle_speed) / max(speed[i] - speed[i + 1], 1e-12)
            stop_time = float(t[i] + f * (t[i + 1] - t[i]))
        else:
            stop_time = float(t[-1])
        minor = dataclasses.replace(plan.minor, max_zmp=_extreme(pbar[0]), max_lipm_zmp=_extreme(lipm[0]))
        feasible = margin >= required - 1e-9
        reason = "" if feasible else (f"predicted ZMP {margin * 100:.1f} cm inside the double-support polygon "
                                      f"(< margin {required * 100:.1f} cm)")
        return dataclasses.replace(plan, minor=minor, min_zmp_margin=margin, stop_time=stop_time,
                                   feasible=feasible, reason=reason)

    def plan_with_posture(self, state: PatternState, q_seed: np.ndarray) -> StopPlan:
        """:meth:`plan`, then the final-posture check, crouch and fallback (:func:`settle_posture`)."""
        return settle_posture(self, self.plan(state), q_seed)


def settle_posture(planner: "EstopPlanner", plan: "StopPlan", q_seed: np.ndarray) -> "StopPlan":
    """Posture check, crouch and fallback for a :class:`StopPlan` (:mod:`humfall_ros.estop.posture`'s docstring).

    Args:
        planner: the :class:`~humfall_ros.estop.planner.EstopPlanner` that made ``plan``.
        plan: its closed-form plan.
        q_seed: the current configuration (nq,), its feet at ``plan.state.feet``
            (:func:`configuration_from_feet` builds one from joint positions).
    Returns:
        the plan with ``crouch``, ``posture``, ``feasible``, ``reason`` and ``fallback`` set.
    """
    c = planner.cfg
    solver = planner.posture_solver
    state = plan.state
    ground = state.ground_height
    z0 = state.cog_height

    def attempt(p):
        """(plan, posture check, reason it fails or "")."""
        target = np.array([p.final_com[0], p.final_com[1], ground + z0])
        check = solver.solve(q_seed, state.feet, target, ground)
        if check.reachable:
            return p, check, ""
        # lower the CoG. Reachability against height is an interval (too high: the rear leg straight, its hip at
        # the extension stop; too low: the front ankle at its dorsiflexion stop), so scan down in steps of the
        # clearance for a reachable height, then bisect its top to the IK's tolerance: the crouch then keeps the
        # whole clearance below it (a bisection stopped at the clearance's width kept 0-1 of it, and at 1.8 km/h
        # the executed rear hip reached its extension stop: the rear sole let go, the CoP jumped 2.8 cm)
        step = max(c.crouch_clearance, 2 * c.ik_tolerance)
        hi_z, best, q = z0, None, check.q
        for z in [*np.arange(z0 - step, c.crouch_min_cog_height, -step), c.crouch_min_cog_height]:
            trial = solver.solve(q, state.feet, np.array([*target[:2], ground + z]), ground)
            if trial.reachable:
                lo_z, best = z, trial
                break
            hi_z, q = z, trial.q
        if best is None:
            return p, trial, (f"final CoG not reachable with the feet fixed at any height down to "
                              f"{c.crouch_min_cog_height} m (limits: {', '.join(trial.binding_joints) or 'none'})")
        while hi_z - lo_z > 2 * c.ik_tolerance:
            mid = 0.5 * (lo_z + hi_z)
            trial = solver.solve(best.q, state.feet, np.array([*target[:2], ground + mid]), ground)
            if trial.reachable:
                lo_z, best = mid, trial
            else:
                hi_z = mid
        # the whole clearance below the top, or the stop is not feasible: a crouch without it ends at the stop of
        # the binding joint once executed (2.0 km/h ds_mid at 0.55 m with none left: the CoP rode the edge)
        z1 = lo_z - c.crouch_clearance
        short = z1 < c.crouch_min_cog_height - 1e-9
        z1 = max(z1, c.crouch_min_cog_height)
        p = planner.plan(state, beta=p.beta, crouch=Crouch(z0, z1, c.crouch_duration))   # the same beta, crouched
        check = solver.solve(best.q, state.feet, p.final_com.copy(), ground)
        if short:
            return p, check, (f"the crouch's clearance does not fit: the legs reach {lo_z:.3f} m, less "
                              f"{c.crouch_clearance} m is below crouch_min_cog_height {c.crouch_min_cog_height} m")
        if not check.reachable:
            return p, check, f"crouched posture at {z1:.3f} m not reachable ({', '.join(check.binding_joints)})"
        return p, check, ""

    p, check, why = attempt(plan)
    if not why and not p.feasible:
        why = p.reason
    if not why:
        return dataclasses.replace(p, posture=check, feasible=True, reason="")
    if c.fallback == "none":
        return dataclasses.replace(p, posture=check, feasible=False, reason=why)
    # fallback min_n3_crouch: beta = -omega_f (n3 at eq. 22's bound); if the posture is still out of
    # reach, the deepest crouch; run anyway, feasible=False
    fb, check_fb, why_fb = attempt(planner.plan(state, beta=-c.omega_f))
    if why_fb and not check_fb.reachable and c.crouch_min_cog_height < z0:
        fb = planner.plan(state, beta=-c.omega_f, crouch=Crouch(z0, c.crouch_min_cog_height, c.crouch_duration))
        check_fb = solver.solve(check_fb.q, state.feet, fb.final_com.copy(), ground)
    note = "; fallback min_n3_crouch: " + ("posture reachable" if check_fb.reachable else "posture NOT reachable")
    if not fb.feasible:
        note += f", {fb.reason}"
    return dataclasses.replace(fb, posture=check_fb, feasible=False, reason=why + note, fallback="min_n3_crouch")


__all__ = ["Crouch", "EstopInputError", "EstopPlanner", "MajorAxisPlan", "MinorAxisPlan", "PatternState",
           "StopPlan", "StopReference", "polygon_margins", "settle_posture"]
