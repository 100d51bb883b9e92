"""Trajectory optimisation: opt_self_motion and opt_transition_motion (paper 2, Sec. III-C, III-D).

Transcription (Sec. III-C.2): Nd knots over a free duration T (h = T/(Nd-1)).
Per knot the decision variables are q, qdot, qddot, u and the contact forces
lambda of the segment's mode. Positions follow the cubic Hermite spline fixed by
(q, qdot) at both knots (eq. 7); velocities the cubic fixed by (qdot, qddot);
u and lambda are piecewise linear. Eq. 1 holds at every knot (the knot
accelerations are the ones eq. 1 gives for the knot's state, control and force:
written in inverse-dynamics form, which is the same condition without a
symbolic inverse of D), and at the mid-point s = 1/2 the collocation constraints
ask (i) the slope of the position spline to equal the velocity spline and
(ii) eq. 1 to hold with the interpolated q, qdot, qddot and the averaged u,
lambda (eq. 8).

Constraints: eq. 3 (contact rows at zero distance for the mode, clearance
eps_cl for everything else, a ramp from the initial distance for points that
start closer), eq. 4 (contact velocities zero), eq. 5 (friction cone, linear in
the planar case), eq. 6 (joint, velocity and torque limits from the URDF).
Objective eq. 9: kinetic energy at the last knot, plus a tiny torque
regulariser that only breaks ties. For an added contact the impact map (eq. 10)
is part of the NLP (post-impact velocity and impulse are variables) and the
objective is the pre-impact energy (Sec. III-A; ``transition_objective``
'post_impact', the energy after the impact, is kept as a departure), with
eq. 6 applied to the post-impact velocities too: they start the child's
segments (docs/multicontact.md has the measurements behind both choices).

Speed: each NLP structure (kind, mode, target, environment shape, Nd) is built
once as a casadi SX graph and an IPOPT instance with exact Hessians, and cached.
Everything that changes between calls (initial state, contact anchors, wall
position, clearance ramps, the removed contact's zero force) enters through the
variable and constraint bounds, so no rebuild is needed.
"""
from __future__ import annotations

import ctypes
import dataclasses
import glob
import math
import os
import threading
import time

import casadi as ca
import numpy as np

from humfall_ros import params
from humfall_ros.multicontact import contacts as C
from humfall_ros.multicontact.landing import LandingLimits
from humfall_ros.multicontact.model import EXTREMITIES, FEET, PlanarModel
from humfall_ros.multicontact.modes import (
    Environment,
    Mode,
    is_foot_landing,
    make_mode,
    mode_label,
    parse_mode,
)

TRANSITION_OBJECTIVES = ("pre_impact", "post_impact")
POST_IMPACT_SPEED_LIMBS = ("all", "feet", "hands")


def set_blas_threads(n: int) -> bool:
    """Set the thread count of the OpenBLAS that casadi ships and loads with itself (MUMPS, so
    IPOPT, runs on it; numpy's OpenBLAS is another library). Its default is a thread per core:
    on the 2-core machine an NLP then took both cores for the wall time of one (the 40 J root's
    stop: 2.4-2.7 s wall and 4.8-5.4 s CPU on two threads, 2.7 s and 2.7 s on one), beside the
    simulator and nodes, and the plan depended on the machine's core count through the summation
    order. False if that library is not found."""
    if n <= 0:
        return False
    for path in glob.glob(os.path.join(os.path.dirname(ca.__file__), "libcasadi-tp-openblas.so*")):
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        if hasattr(lib, "openblas_set_num_threads"):
            lib.openblas_set_num_threads(ctypes.c_int(int(n)))
            return True
    return False


@dataclasses.dataclass
class OptConfig:
    """Table I defaults plus solver settings (all configurable from the node yaml)."""

    n_knots: int = 8              # Nd
    t_min: float = 0.25           # T_min (s)
    t_max: float = 3.5            # T_max (s)
    n_seed_durations: int = 40    # N_tot: seed duration grid over [T_min, T_max]
    max_seed_attempts: int = 3    # seeds tried per NLP call (first one, then the retry list)
    # the first seed tried: T_min, as Sec. III-D (seeds of increasing duration; T is a variable anyway). Until
    # session 30 0.8 s first, then 0.5, 1.2: from one foot 70 / 80 J found no plan, from two feet 40-80 J
    seed_first_duration: float = 0.25
    # seeds tried, in this order, after the first when it fails or ends above
    # the starting energy (snapped to the N_tot grid over [T_min, T_max]); increasing as the paper's, spaced
    # wider than its 40-point grid since at most max_seed_attempts are tried
    seed_retry_durations: tuple = (0.5, 0.8, 1.2, 2.0)
    # a converged contact-adding transition whose objective ends above the
    # kinetic energy it started with is a poor local optimum (another seed of
    # the same NLP often lands softly): try the next seed too, keep the best
    retry_if_energy_rises: bool = True
    # ... and the threshold: retry when the objective ends above this fraction
    # of the start energy (1.0: only when it rises; 0.5 measured better for
    # the wall: the first landing kept 39 of 40 J, another seed keeps ~1 J)
    retry_energy_fraction: float = 0.5
    # an IPOPT run that hits max_iter is restarted this many times from its
    # last iterate and multipliers before the next seed is tried
    # measured: warm restarts help stalled landings, but double the time spent on infeasible nodes (60/70 J)
    warm_restarts: int = 0
    eps_ke: float = 0.1           # J, stationary threshold
    eps_cl: float = 0.025         # m, clearance of non-contact points
    mu: float = 0.35              # friction coefficient
    torque_reg: float = 1e-4      # weight of sum (u/u_max)^2 h (tie breaker)
    force_reg: float = 0.0        # weight of sum (lambda/(M g))^2 h: picks one of the non-unique internal forces
    max_iter: int = 450            # 300 until session 11 (the 40 J step's stop needs ~400); 600 in sessions 11-35
    tol: float = 1e-4
    constr_viol_tol: float = 1e-5
    feasibility_tol: float = 1e-4  # our own check of the returned solution
    root_z_min: float = 0.0
    acc_max: float = 300.0          # rad/s^2 or m/s^2 at the knots (100: post-impact children could not stop)
    force_max_mg: float = 3.0       # contact force component cap, in units of M g
    knee_margin: float = 0.05      # rad, lower knee bound used by the NLP (URDF lower limit is 0)
    post_impact_velocity_limits: bool = True  # eq. 6 velocity limits on the post-impact joint velocities too
    # ... at this fraction of the limits (departure when < 1): a child that starts at a joint's speed limit next to
    # its position limit cannot brake it (the 60 / 80 J hand nodes, session 25)
    post_impact_speed_fraction: float = 1.0
    # ... for the landings of these limbs only ('all', 'feet' or 'hands'): from one foot, 0.8 on the feet only plans
    # 70 J (a step, then the rear foot lifted) and keeps the wall's hand (0.8 on every limb loses it: session 30)
    post_impact_speed_fraction_limbs: str = "all"
    # rad, upper elbow bound -elbow_margin (URDF: 0, the straight arm); 0.1 measured worse
    elbow_margin: float = 0.0
    contact_pos_tol: float = 0.002   # m, eq. 3 at the knots (drift bound)
    contact_vel_tol: float = 0.02    # m/s, eq. 4 at the knots
    nlp_max_wall_time: float = 10.0
    # IPOPT's heuristics for problems expected to be infeasible (``expect_infeasible_problem``: the restoration
    # phase is entered sooner and left later) in the tree search's cold solves (not in warm re-solves from a
    # neighbouring optimum, ``SegmentNLP.WARM_START_OPTIONS``). Most of a search's time goes to NLPs that end
    # infeasible (the stops and hands from a stepped node: ~10 s each over three seeds); measured (session 36):
    # the same plans 10-80 J from two feet, 60 / 70 / 80 J in 71 / 55 / 65 s instead of 87 / 63 / 84 s
    expect_infeasible: bool = True
    # a warm re-solve (``warm_solve``: the library re-plan) whose guess carries the IPOPT multipliers of
    # its own solve starts IPOPT from them too (warm_start_init_point); false: from the primal guess only
    # (before session 25). The tree's polish of a rejected stop never uses them (its bounds differ).
    warm_start_multipliers: bool = True
    # threads of casadi's own OpenBLAS under IPOPT's MUMPS (0: the library's default, one per core)
    blas_threads: int = 1
    # Objective of a transition that adds a contact (Sec. III-A): 'pre_impact' (the
    # paper: E_K just before the impact) or 'post_impact' (departure, the energy the
    # child node starts with: makes the rigid impact of eq. 10 a free energy sink).
    transition_objective: str = "pre_impact"
    # T_min of a transition that removes a contact (s; <= 0: t_min). A release is
    # a lift-off: it has no reason to last as long as the shortest landing.
    # 0.1: session 7, default in sessions 11-34; 0.05 since session 35 (with the 0.05 s alternative of
    # ``PlannerConfig.release_alternatives``): the executor's task-space swing lifts the foot at once anyway
    release_t_min: float = 0.05    # Table I: t_min (0.25 s) for all
    # T_max of a release (s; <= 0: t_max, the paper). Ours (session 28): the release's objective (its end
    # energy) prefers braking on both feet as long as T allows, so the step comes late; from one foot, where a
    # step is a single landing, the same planner steps at 30-60 J in 2-10 s
    release_t_max: float = 0.0
    # T_min of a foot landing (a step's swing; s; <= 0: t_min, Table I's 0.25 s for all). Ours (session 37): with
    # Table I's T_min every step from 20 to 50 J lands at T = 0.25 s exactly, the bound active: the pre-impact
    # energy (eq. 9) wants a faster swing, and the joint speed limits (eq. 6) bound how fast. With 0.15 no swing
    # of the two-foot sweep is at the bound (0.175-0.24 s)
    step_t_min: float = 0.15
    # seed durations of a release (s; values <= 0 dropped; empty: the general list). Tried in order: increasing
    # from the release's T_min, as the general list from T_min (session 30; the first 0.05 since session 35)
    release_seed_durations: tuple = (0.05, 0.25, 0.5)
    # foot landing seeds: the seed goal puts the landing foot's toe this far past
    # the capture point of the pushed state (m; nan: the paper's seed, the goal
    # projection alone decides)
    step_seed_capture_offset: float = float("nan")
    # touchdown normal speed of the landing limb as a constraint of the NLP (limits
    # from ``landing_limits``); off: the limits only rank plans (tree.py)
    touchdown_speed_constraint: bool = True
    # a foot landing must put the post-impact capture point at least this far inside
    # the landing foot (behind its toe for a forward fall): looks beyond the edge, which
    # eq. 9 does not (departure from the paper, off by default)
    step_capture_constraint: bool = False
    # eq. 5 on the impulses of eq. 10 (|Lambda_t| <= mu Lambda_n per contact): the
    # paper's impact map sticks whatever friction that needs (departure, off by default)
    impact_friction_cone: bool = False
    # each of a foot's two points (toe, heel) carries at least this fraction of the foot's normal force at every
    # knot: the centre of pressure stays inside the middle (1 - 2 r) of the sole (departure, 0 = off, the paper's
    # contact model): the planar plans ride their support's edge, and the 3-D robot then rolls over it
    foot_cop_margin: float = 0.0
    step_capture_margin: float = 0.12
    # J/m^2, terminal cost w * s^2 of a foot landing, s = how far the post-impact capture point is past the
    # landing foot's toe (forward push; heel backward) less step_capture_margin (departure, 0 = off, the paper):
    # a cost-to-go estimate of the next node that eq. 9 does not have. Soft, unlike step_capture_constraint
    # (with which the landing did not converge); scale: 1/2 M g / z_com = 374 J/m^2 is the kinetic energy of
    # the excess capture-point velocity omega * s of the linear inverted pendulum
    step_capture_weight: float = 6000.0   # 2000 in sessions 11-35; 6000 since session 36 (70 J from two feet planned)
    # kinetic energy at every inner knot of a contact-adding transition <= this many times the energy it
    # starts with (departure, 0 = off, the paper): eq. 9 prices only the end, so a plan may swing up to 6x
    # its start energy and brake just before the touchdown, which an early contact turns into a hard impact
    transition_ke_cap_ratio: float = 0.0
    landing_limits: LandingLimits = dataclasses.field(default_factory=LandingLimits)

    def __post_init__(self):
        if self.transition_objective not in TRANSITION_OBJECTIVES:
            raise ValueError(f"transition_objective {self.transition_objective!r} is not one of "
                             f"{', '.join(TRANSITION_OBJECTIVES)}")
        if self.post_impact_speed_fraction_limbs not in POST_IMPACT_SPEED_LIMBS:
            raise ValueError(f"post_impact_speed_fraction_limbs {self.post_impact_speed_fraction_limbs!r} is not "
                             f"one of {', '.join(POST_IMPACT_SPEED_LIMBS)}")
        if self.step_t_min > self.t_max:   # an empty duration interval: every foot landing infeasible, silently
            raise ValueError(f"step_t_min {self.step_t_min:g} s exceeds t_max {self.t_max:g} s")
        self.seed_retry_durations = tuple(float(x) for x in self.seed_retry_durations)
        self.release_seed_durations = tuple(float(x) for x in self.release_seed_durations if float(x) > 0)

    def post_impact_speed_limit_factor(self, extremity: str) -> float:
        """Fraction of the URDF's joint speed limits that bounds the post-impact velocities of a landing of
        ``extremity`` (eq. 6 on the state eq. 10 gives): ``post_impact_speed_fraction`` for the limbs
        ``post_impact_speed_fraction_limbs`` names, 1 (eq. 6 as it is) for the others."""
        limbs = self.post_impact_speed_fraction_limbs
        if limbs == "all" or (extremity in FEET) == (limbs == "feet"):
            return self.post_impact_speed_fraction
        return 1.0

    @staticmethod
    def from_params(d: dict) -> OptConfig:
        """From a dict of OptConfig field names (e.g. split out of the node's
        declaration by ``planner.configs_from_params``); unknown keys are refused."""
        return params.config_from(OptConfig, d)

    def t_min_of(self, change: str, extremity: str = "") -> float:
        """T_min of a segment of this kind (s): a release's ``release_t_min``, a foot landing's
        ``step_t_min``, when set; else ``t_min``."""
        if change == "remove" and self.release_t_min > 0:
            return self.release_t_min
        if is_foot_landing(change, extremity) and self.step_t_min > 0:
            return self.step_t_min
        return self.t_min

    def t_max_of(self, change: str) -> float:
        """T_max of a segment of this kind (s)."""
        if change == "remove" and self.release_t_max > 0:
            return max(self.release_t_max, self.t_min_of(change))
        return self.t_max

    def seed_durations(self, change: str = "", skip: int = 0, extremity: str = "") -> list[float]:
        """Seed durations in the order they are tried (Sec. III-D).

        The paper sweeps the whole N_tot grid by increasing duration until a
        seed converges. T is a decision variable here, so a handful suffices:
        ``seed_first_duration`` first, then ``seed_retry_durations``, each
        snapped to the grid, duplicates dropped, at most ``max_seed_attempts``.
        A release (``change == 'remove'``) uses ``release_seed_durations`` when
        given, on a grid that starts at its own T_min (a foot landing's grid at ``step_t_min``, when
        set: ``extremity``). ``skip``: start after that
        many seeds of the list (another local optimum of the same NLP).
        """
        grid = np.linspace(self.t_min_of(change, extremity), self.t_max_of(change), max(2, self.n_seed_durations))
        wanted = (self.release_seed_durations if change == "remove" and self.release_seed_durations
                  else (self.seed_first_duration, *self.seed_retry_durations))
        out: list[float] = []
        for d in wanted:
            g = float(grid[int(np.argmin(np.abs(grid - d)))])
            if g not in out:
                out.append(g)
        return out[skip:skip + max(1, self.max_seed_attempts)]


@dataclasses.dataclass
class Segment:
    """One optimised trajectory (a tree edge or a node's self-motion)."""

    kind: str            # 'self_motion' | 'transition'
    mode: Mode           # contact mode during the segment
    target_mode: Mode
    change: str          # '', 'add', 'remove'
    extremity: str       # changed extremity ('' for self-motion)
    time: np.ndarray     # Nd
    q: np.ndarray        # Nd x n
    v: np.ndarray
    a: np.ndarray
    u: np.ndarray        # Nd x m
    lam: np.ndarray      # Nd x rows
    rows: list           # ContactRow list of lambda columns
    ke: np.ndarray       # Nd
    success: bool
    status: str
    iterations: int
    nlp_time: float
    seed_duration: float
    attempts: int
    max_violation: float
    cpu_time: float = 0.0  # CPU time of this thread (the machine may be shared)
    build_time: float = 0.0  # part of nlp_time spent building a not yet cached NLP structure
    objective: float = float("nan")   # eq. 9 value (blended for an added contact)
    attempt_log: list = dataclasses.field(default_factory=list)  # one dict per seed tried
    # IPOPT's multipliers at this solution (bounds of the variables, constraints), in the NLP's own
    # layout: a warm re-solve of the same structure starts from them (``warm_solve``)
    multipliers: tuple | None = None
    # the bounds on the duration T this segment was solved within (s; None: not recorded, files before
    # session 32): a warm re-solve of it keeps them (``warm_solve``)
    t_bounds: tuple | None = None

    @property
    def final_ke(self) -> float:
        return float(self.ke[-1])

    def to_dict(self, model: PlanarModel | None = None, multipliers: bool = False) -> dict:
        """JSON-able; ``multipliers``: also IPOPT's multipliers (a library entry keeps them for its
        warm re-plans; plan responses leave them out)."""
        d = {
            "kind": self.kind, "mode": mode_label(self.mode), "target_mode": mode_label(self.target_mode),
            "change": self.change, "extremity": self.extremity,
            "time": self.time.tolist(), "q": self.q.tolist(), "v": self.v.tolist(), "a": self.a.tolist(),
            "u": self.u.tolist(), "lam": self.lam.tolist(),
            "rows": [dataclasses.asdict(r) for r in self.rows], "ke": self.ke.tolist(),
            "success": self.success, "status": self.status, "iterations": self.iterations,
            "nlp_time": self.nlp_time, "cpu_time": self.cpu_time, "build_time": self.build_time,
            "seed_duration": self.seed_duration, "attempts": self.attempts,
            "max_violation": self.max_violation, "objective": self.objective, "attempt_log": self.attempt_log,
        }
        if self.t_bounds is not None:
            d["t_bounds"] = [float(x) for x in self.t_bounds]
        if multipliers and self.multipliers is not None:
            d["multipliers"] = {"x": np.asarray(self.multipliers[0]).tolist(),
                                "g": np.asarray(self.multipliers[1]).tolist()}
        return d

    @staticmethod
    def from_dict(d: dict) -> Segment:
        """Inverse of ``to_dict`` (a stored plan re-checked or re-plotted later)."""
        arrays = {k: np.asarray(d[k], float) for k in ("time", "q", "v", "a", "u", "lam", "ke")}
        if arrays["lam"].ndim == 1:      # no contact rows: keep the (Nd, 0) shape
            arrays["lam"] = arrays["lam"].reshape(len(arrays["time"]), -1)
        return Segment(kind=d["kind"], mode=parse_mode(d["mode"]), target_mode=parse_mode(d["target_mode"]),
                       change=d["change"], extremity=d["extremity"], rows=[C.ContactRow(**r) for r in d["rows"]],
                       success=bool(d["success"]), status=d["status"], iterations=int(d["iterations"]),
                       nlp_time=float(d["nlp_time"]), seed_duration=float(d["seed_duration"]),
                       attempts=int(d["attempts"]), max_violation=float(d["max_violation"]),
                       cpu_time=float(d.get("cpu_time", 0.0)), build_time=float(d.get("build_time", 0.0)),
                       objective=float(d.get("objective", float("nan"))),
                       attempt_log=list(d.get("attempt_log", [])),
                       multipliers=(np.asarray(d["multipliers"]["x"], float), np.asarray(d["multipliers"]["g"], float))
                       if d.get("multipliers") else None,
                       t_bounds=_duration_bounds(d["t_bounds"]) if d.get("t_bounds") else None, **arrays)


def _duration_bounds(b) -> tuple[float, float]:
    """A stored segment's (T_min, T_max): two finite positive numbers, in order (a file's values are checked
    when it is read, not when a re-solve would use it)."""
    lo, hi = (float(x) for x in b) if len(b) == 2 else (math.nan, math.nan)
    if not (math.isfinite(lo) and math.isfinite(hi) and 0 < lo <= hi):
        raise ValueError(f"segment t_bounds {b!r}: not (T_min, T_max) with 0 < T_min <= T_max")
    return lo, hi


# ---------------------------------------------------------------- splines
def hermite_mid(q0, v0, q1, v1, a0, a1, h):
    """Mid-point (s = 1/2) values of the implicit cubic splines (eq. 7-8).

    Returns q_mid, qdot_mid (velocity spline), qddot_mid (slope of the velocity
    spline) and the slope of the position spline at s = 1/2.
    """
    q_mid = 0.5 * (q0 + q1) + h / 8.0 * (v0 - v1)
    v_mid = 0.5 * (v0 + v1) + h / 8.0 * (a0 - a1)
    a_mid = 1.5 / h * (v1 - v0) - 0.25 * (a0 + a1)
    qdot_mid = 1.5 / h * (q1 - q0) - 0.25 * (v0 + v1)
    return q_mid, v_mid, a_mid, qdot_mid


def hermite_eval(t0, t1, y0, dy0, y1, dy1, t):
    """Cubic Hermite interpolation on [t0, t1] (value and derivative)."""
    h = t1 - t0
    s = (t - t0) / h
    h00 = 2 * s**3 - 3 * s**2 + 1
    h10 = s**3 - 2 * s**2 + s
    h01 = -2 * s**3 + 3 * s**2
    h11 = s**3 - s**2
    y = h00 * y0 + h10 * h * dy0 + h01 * y1 + h11 * h * dy1
    dh00 = (6 * s**2 - 6 * s) / h
    dh10 = (3 * s**2 - 4 * s + 1)
    dh01 = (-6 * s**2 + 6 * s) / h
    dh11 = (3 * s**2 - 2 * s)
    dy = dh00 * y0 + dh10 * dy0 + dh01 * y1 + dh11 * dy1
    return y, dy


# ----------------------------------------------------------- NLP structure
@dataclasses.dataclass(frozen=True)
class StructureKey:
    change: str           # '' (self-motion), 'add', 'remove'
    mode: Mode            # mode during the segment
    extremity: str
    has_wall: bool
    n_knots: int


class SegmentNLP:
    """One cached NLP structure (see module doc)."""

    def __init__(self, model: PlanarModel, key: StructureKey, cfg: OptConfig):
        self.model, self.key, self.cfg = model, key, cfg
        n, m, N = model.n, model.m, key.n_knots
        env_shape = Environment(0.0 if key.has_wall else None)  # surfaces only; wall_x enters via bounds
        self.rows = C.contact_rows(key.mode, env_shape)
        self.nl = len(self.rows)
        self.clear_pts = self._clearance_points(env_shape)
        nk = 3 * n + m + self.nl
        self.nk = nk
        # Decision variables in scaled units: u = u_max * u~, lambda = M g * lambda~,
        # so that every block is O(1) for IPOPT.
        self.u_scale = np.asarray(model.u_max, float)
        self.f_scale = model.total_mass * 9.81
        # An added contact: post-impact velocity and impulse of eq. 10 as extra
        # variables, so the objective can be the post-impact energy.
        self.impact_rows = (C.contact_rows(make_mode(set(key.mode) | {key.extremity}), env_shape)
                            if key.change == "add" else [])
        self.n_imp = (n + len(self.impact_rows)) if key.change == "add" else 0
        # slacks (forward, backward) of the soft capture-point cost of a foot landing
        self.n_cap = 2 if (is_foot_landing(key.change, key.extremity) and cfg.step_capture_weight > 0) else 0
        self.imp_scale = model.total_mass
        w = ca.SX.sym("w", 1 + N * nk + self.n_imp + self.n_cap)
        # the capture cost's weight is the NLP's parameter, not a constant of the structure: a library
        # re-plan re-solves its entries with the weight they were planned with (``warm_solve``)
        capture_weight = ca.SX.sym("capture_weight")
        cap_cost = 0
        T = w[0]
        h = T / (N - 1)
        knots = []
        for k in range(N):
            o = 1 + k * nk
            knots.append({"q": w[o:o + n], "v": w[o + n:o + 2 * n], "a": w[o + 2 * n:o + 3 * n],
                          "u": ca.DM(self.u_scale) * w[o + 3 * n:o + 3 * n + m],
                          "l": self.f_scale * w[o + 3 * n + m:o + nk]})
        dyn_scale = 1.0 / self.f_scale
        g, self.g_tags = [], []  # tags: (block, knot, index-in-block)

        def add(block, k, expr):
            g.append(expr)
            self.g_tags += [(block, k, i) for i in range(expr.shape[0])]

        Bs = ca.DM(model.B)
        row_fns = [self._row_fn(r) for r in self.rows]
        dJv_fns = [self._row_dJv(r) for r in self.rows]

        def generalized_force(q, lam):
            f = ca.SX.zeros(n)
            for i, (_, J) in enumerate(row_fns):
                f += J(q).T * lam[i]
            return f

        for k, kn in enumerate(knots):
            # eq. 1 at the knot (residual in units of M g * 1 m)
            add("dyn", k, dyn_scale * (model.f_id(kn["q"], kn["v"], kn["a"]) - Bs @ kn["u"]
                                       - generalized_force(kn["q"], kn["l"])))
        for k in range(N - 1):
            k0, k1 = knots[k], knots[k + 1]
            q_mid, v_mid, a_mid, qdot_mid = hermite_mid(k0["q"], k0["v"], k1["q"], k1["v"], k0["a"], k1["a"], h)
            u_mid = 0.5 * (k0["u"] + k1["u"])
            l_mid = 0.5 * (k0["l"] + k1["l"])
            # position-spline slope == velocity spline at s = 1/2 (scaled by h)
            add("coll_q", k, h * (qdot_mid - v_mid))
            # eq. 8
            add("coll_dyn", k, dyn_scale * (model.f_id(q_mid, v_mid, a_mid) - Bs @ u_mid
                                            - generalized_force(q_mid, l_mid)))
        # Contact rows. Holding positions and velocities exactly at every knot
        # over-determines the discrete problem (one control lost per row and
        # interval, none left with four contacts), and a velocity-correction
        # slack would let q move without kinetic energy, which the objective
        # exploits. So: the contact *acceleration* J a + Jdot v = 0 holds
        # exactly at every knot (index reduction: balanced with lambda), and
        # eq. 3-4 hold at every knot within small tolerances
        # (contact_pos_tol, contact_vel_tol), which bound the drift.
        for k in range(1, N):
            kn = knots[k]
            for i, (val, J) in enumerate(row_fns):
                add("cacc", k, J(kn["q"]) @ kn["a"] + dJv_fns[i](kn["q"], kn["v"]))
                add("cpos", k, val(kn["q"]))           # eq. 3 (contact at distance 0, anchored)
                add("cvel", k, J(kn["q"]) @ kn["v"])   # eq. 4
        for k in range(N):
            lam = knots[k]["l"]
            for ti, ni in C.friction_groups(self.rows):   # eq. 5 (planar: two half-planes)
                fn = sum(lam[i] for i in ni)
                add("fric", k, ca.vertcat(cfg.mu * fn - lam[ti], cfg.mu * fn + lam[ti]))
                if cfg.foot_cop_margin > 0 and len(ni) == 2:   # a foot: toe and heel (bounded >= 0 in bounds())
                    add("cop", k, ca.vertcat(*[lam[i] - cfg.foot_cop_margin * fn for i in ni]))
        for k in range(1, N):
            qk = knots[k]["q"]
            for (pt, surf) in self.clear_pts:            # eq. 3, non-contact clearance
                p = model.f_point[pt](qk)
                add("clear", k, p[1] if surf == "ground" else p[0])
        if key.change == "add" and cfg.transition_ke_cap_ratio > 0:
            for k in range(1, N - 1):   # bounded in ``bounds`` (the start energy is known per solve)
                add("ke_path", k, model.f_ke(knots[k]["q"], knots[k]["v"]))
        qN, vN = knots[-1]["q"], knots[-1]["v"]
        ke = model.f_ke(qN, vN)   # eq. 9
        self.ke_pre = ke
        if key.change == "add":
            oi = 1 + N * nk
            v_plus = w[oi:oi + n]
            imp = self.imp_scale * w[oi + n:oi + self.n_imp]
            imp_fns = [self._row_fn(r) for r in self.impact_rows]
            Jt = ca.vertcat(*[J(qN) for _, J in imp_fns])
            # eq. 10: D (v+ - v-) = J^T Lambda, J v+ = 0
            add("impact", N - 1, (model.f_D(qN) @ (v_plus - vN) - Jt.T @ imp) / self.imp_scale)
            add("impact_vel", N - 1, Jt @ v_plus)
            # eq. 5 applied to the impulse of eq. 10 (bounded only when impact_friction_cone):
            # a sticking impact must not need more friction than the contact has
            for ti, ni in C.friction_groups(self.impact_rows):
                fn = sum(imp[i] for i in ni)
                add("imp_fric", N - 1, ca.vertcat(cfg.mu * fn - imp[ti], cfg.mu * fn + imp[ti]) / self.imp_scale)
            ke_post = model.f_ke(qN, v_plus)
            self.ke_post = ke_post
            # Sec. III-A: the pre-impact energy (default); 'post_impact' is the
            # departure that lets the rigid impact take the energy out for free
            if cfg.transition_objective == "post_impact":
                ke = ke_post
            # touchdown velocity of the landing limb's points along the surface
            # normal (bounded in ``bounds`` when touchdown_speed_constraint)
            surf = env_shape.surface_of(key.extremity)
            nd = C.row_direction(C.ContactRow(key.extremity, key.extremity, surf, "n"))
            pts = [f"{key.extremity}_toe", f"{key.extremity}_heel"] if key.extremity in FEET else [key.extremity]
            add("touchdown", N - 1, ca.vertcat(*[
                ca.mtimes(nd[0] * model.f_point_jac[p](qN)[0, :] + nd[1] * model.f_point_jac[p](qN)[1, :], vN)
                for p in pts]))
            if key.extremity in FEET:
                # capture point after the impact relative to the landing foot: rows
                # (toe x - x_cp, x_cp - heel x); ``bounds`` asks the row of the push's
                # direction to be >= step_capture_margin when step_capture_constraint
                qs, vs = ca.SX.sym("q", n), ca.SX.sym("v", n)
                cs = model.f_com(qs)
                f_cp = ca.Function("cp", [qs, vs], [cs[0] + ca.mtimes(ca.jacobian(cs[0], qs), vs)
                                                    * ca.sqrt(ca.fmax(cs[1], 1e-3) / 9.81)])
                cp = f_cp(qN, v_plus)
                toe = model.f_point[f"{key.extremity}_toe"](qN)[0]
                heel = model.f_point[f"{key.extremity}_heel"](qN)[0]
                add("capture", N - 1, ca.vertcat(toe - cp, cp - heel))
                if self.n_cap:
                    # soft version: s_f >= cp - toe + margin, s_b >= heel - cp + margin, s >= 0
                    # (only the push direction's row is bounded in ``bounds``), cost w s^2
                    oc = 1 + N * nk + self.n_imp
                    s_cap = w[oc:oc + 2]
                    add("capture_soft", N - 1, ca.vertcat(toe - cp + s_cap[0], cp - heel + s_cap[1]))
                    cap_cost = capture_weight * ca.sumsqr(s_cap)
        reg = 0
        freg = 0
        for k in range(N):
            o = 1 + k * nk
            reg += ca.sumsqr(w[o + 3 * n:o + 3 * n + m])
            freg += ca.sumsqr(w[o + 3 * n + m:o + nk])
        f = ke + cap_cost + cfg.torque_reg * reg * h + (cfg.force_reg * freg * h if cfg.force_reg > 0 else 0)
        G = ca.vertcat(*g)
        self.ng = G.shape[0]
        self.nw = w.shape[0]
        opts = {
            "ipopt.print_level": 0, "print_time": False, "ipopt.sb": "yes",
            "ipopt.max_iter": cfg.max_iter, "ipopt.tol": cfg.tol,
            "ipopt.constr_viol_tol": cfg.constr_viol_tol,
            "ipopt.acceptable_tol": 1e-3, "ipopt.acceptable_iter": 5,
            "ipopt.mu_strategy": "adaptive",
            "ipopt.linear_solver": "mumps",
            "ipopt.max_wall_time": cfg.nlp_max_wall_time,
            "ipopt.expect_infeasible_problem": "yes" if cfg.expect_infeasible else "no",
        }
        self.solver = ca.nlpsol(f"seg_{id(self)}", "ipopt", {"x": w, "p": capture_weight, "f": f, "g": G}, opts)
        self._opts = opts
        self._warm_solver = None
        self.f_ke_end = ca.Function("ke_end", [w], [ke])
        self.f_cap_cost = ca.Function("cap_cost", [w, capture_weight], [ca.SX(cap_cost)])
        self.f_g = ca.Function("g", [w], [G])
        tags = np.array([t[0] for t in self.g_tags])
        self._block_idx = {b: np.where(tags == b)[0] for b in set(tags)}
        self.knot_slices = [(1 + k * nk, 1 + (k + 1) * nk) for k in range(N)]
        self.lock = threading.Lock()

    # IPOPT's warm start from a known solution's multipliers: the initial point is not pushed into the
    # interior (bound pushes ~0) and the barrier starts small, since the guess is a neighbouring optimum
    # (so no heuristics for an infeasible problem either: measured with them, the library's answers were
    # 0.02-0.15 s slower at the slowest, session 36)
    WARM_START_OPTIONS = {"ipopt.warm_start_init_point": "yes", "ipopt.mu_init": 1e-3,
                          "ipopt.warm_start_bound_push": 1e-6, "ipopt.warm_start_mult_bound_push": 1e-6,
                          "ipopt.warm_start_slack_bound_push": 1e-6, "ipopt.expect_infeasible_problem": "no"}

    def warm_solver(self):
        """The same NLP (its oracle: no second symbolic build) with IPOPT's warm-start options; built
        on first use (~2 s, as the cold solver; the derivative functions are generated again)."""
        with self.lock:
            if self._warm_solver is None:
                self._warm_solver = ca.nlpsol(f"warm_{id(self)}", "ipopt", self.solver.oracle(),
                                              {**self._opts, **self.WARM_START_OPTIONS})
            return self._warm_solver

    def parameters(self, capture_weight: float | None = None) -> np.ndarray:
        """The NLP's parameter vector: the weight of a foot landing's capture cost (J/m^2;
        None: ``OptConfig.step_capture_weight``; ignored by structures without the cost's slacks)."""
        wcap = self.cfg.step_capture_weight if capture_weight is None else float(capture_weight)
        if not (math.isfinite(wcap) and wcap >= 0):
            raise ValueError(f"capture weight {capture_weight!r}: a finite number >= 0")
        return np.array([wcap])

    def fits(self, multipliers) -> bool:
        """Multipliers of this structure's layout (variables, constraints)?"""
        return (multipliers is not None and len(multipliers) == 2 and np.size(multipliers[0]) == self.nw
                and np.size(multipliers[1]) == self.ng)

    def _row_fn(self, row: C.ContactRow):
        model = self.model
        d = C.row_direction(row)
        fp = model.f_point[row.point]
        fj = model.f_point_jac[row.point]

        def val(q):
            p = fp(q)
            return d[0] * p[0] + d[1] * p[1]

        def jac(q):
            J = fj(q)
            return d[0] * J[0, :] + d[1] * J[1, :]
        return val, jac

    def _row_dJv(self, row: C.ContactRow):
        d = C.row_direction(row)
        f = self.model.f_point_dJv[row.point]

        def dJv(q, v):
            x = f(q, v)
            return d[0] * x[0] + d[1] * x[1]
        return dJv

    def _clearance_points(self, env: Environment):
        """(point, surface) pairs kept at clearance: every point not in a contact row."""
        model = self.model
        in_contact = {r.point for r in self.rows}
        # the foot's toe and heel are both in contact rows when the foot is
        pts = []
        for nm in model.point_names:
            if nm in in_contact:
                continue
            ext = nm.split("_")[0] if nm.split("_")[0] in EXTREMITIES else None
            if ext is not None and ext in self.key.mode:
                continue
            pts.append((nm, "ground"))
            if env.has_wall:
                pts.append((nm, "wall"))
        return pts

    # ------------------------------------------------------------ bounds
    def bounds(self, q0, v0, env: Environment, lb_clear_start: np.ndarray | None = None,
               acc_max: float | None = None, t_bounds: tuple | None = None):
        """Numeric variable and constraint bounds for one solve (``acc_max``: the knot
        acceleration bound of this solve instead of ``OptConfig.acc_max``; ``t_bounds``: the
        duration's (T_min, T_max) instead of ``OptConfig``'s for this segment kind)."""
        model, cfg, key = self.model, self.cfg, self.key
        acc = cfg.acc_max if acc_max is None or acc_max <= 0 else float(acc_max)
        n, m, N = model.n, model.m, key.n_knots
        lbx = np.full(self.nw, -np.inf)
        ubx = np.full(self.nw, np.inf)
        lbx[0], ubx[0] = t_bounds if t_bounds is not None else (cfg.t_min_of(key.change, key.extremity),
                                                                 cfg.t_max_of(key.change))
        for k, (a, b) in enumerate(self.knot_slices):
            o = a
            # q
            lbx[o + 1] = cfg.root_z_min
            lbx[o + 2], ubx[o + 2] = -math.pi, math.pi
            lbx[o + 3:o + n], ubx[o + 3:o + n] = model.q_min, model.q_max
            # keep knees off the stretched-leg singularity, where the re-simulation
            # found that tiny errors need huge contact forces (the URDF's 0 stays
            # the hard limit; this only tightens it)
            for jn, qi in model.q_index.items():
                if jn.endswith("_knee"):
                    lbx[o + qi] = max(lbx[o + qi], cfg.knee_margin)
                # optional, same idea for the arms (a hand landing on a straight
                # arm: contact Jacobian sigma_min ~ 0.006); measured: 0.1 rad
                # makes the hand landings keep far more energy, so off
                if jn.endswith("_elbow") and cfg.elbow_margin > 0:
                    ubx[o + qi] = min(ubx[o + qi], -cfg.elbow_margin)
            # v
            lbx[o + n + 3:o + 2 * n], ubx[o + n + 3:o + 2 * n] = -model.v_max, model.v_max
            # u (scaled by u_max)
            lbx[o + 3 * n:o + 3 * n + m], ubx[o + 3 * n:o + 3 * n + m] = -1.0, 1.0
            # a: bounded so that the splines cannot hide an oscillating
            # acceleration between the collocation points
            lbx[o + 2 * n:o + 3 * n], ubx[o + 2 * n:o + 3 * n] = -acc, acc
            # lambda (scaled by M g): normal components >= 0 (eq. 5), and a cap
            # on any component (no impulsive forces inside a segment)
            lo = o + 3 * n + m
            lbx[lo:lo + self.nl], ubx[lo:lo + self.nl] = -cfg.force_max_mg, cfg.force_max_mg
            for i in C.normal_row_indices(self.rows):
                lbx[lo + i] = 0.0
            if k == 0:
                lbx[o:o + n] = ubx[o:o + n] = q0
                lbx[o + n:o + 2 * n] = ubx[o + n:o + 2 * n] = v0
        if key.change == "add":
            oi = 1 + N * self.nk
            for i in C.normal_row_indices(self.impact_rows):
                lbx[oi + n + i] = 0.0  # surfaces can only push (normal impulses >= 0)
            # the post-impact state starts the child's segment: its joint
            # velocities obey eq. 6 too (without this the impact map of eq. 10
            # left the child up to 2.6 v_max, and the child's NLPs could not
            # converge from a start outside their own bounds)
            if cfg.post_impact_velocity_limits:
                vmax = cfg.post_impact_speed_limit_factor(key.extremity) * np.asarray(model.v_max, float)
                lbx[oi + 3:oi + n], ubx[oi + 3:oi + n] = -vmax, vmax
        if key.change == "remove":
            # the released contact carries no force at the end (mode sigma_j dynamics)
            lo = self.knot_slices[-1][0] + 3 * n + m
            for i, r in enumerate(self.rows):
                if r.extremity == key.extremity:
                    lbx[lo + i] = ubx[lo + i] = 0.0
        lbg = np.zeros(self.ng)
        ubg = np.zeros(self.ng)
        # contact positions: anchored at the start values (tangential), on the surface (normal)
        anchors = C.rows_value(model, self.rows, q0)
        for i, r in enumerate(self.rows):
            if r.axis == "n":
                anchors[i] = -(env.wall_x) if r.surface == "wall" else 0.0
        idx = self._block_idx.get("cpos", np.array([], int))
        if len(idx):
            rep = np.tile(anchors, N - 1)
            lbg[idx] = rep - cfg.contact_pos_tol
            ubg[idx] = rep + cfg.contact_pos_tol
        idx = self._block_idx.get("cvel", np.array([], int))
        lbg[idx], ubg[idx] = -cfg.contact_vel_tol, cfg.contact_vel_tol
        idx = self._block_idx.get("fric", np.array([], int))
        ubg[idx] = np.inf
        idx = self._block_idx.get("clear", np.array([], int))
        if len(idx):
            lo, hi = self._clearance_bounds(q0, env)
            lbg[idx], ubg[idx] = lo, hi
        idx = self._block_idx.get("cop", np.array([], int))
        lbg[idx], ubg[idx] = 0.0, np.inf
        idx = self._block_idx.get("imp_fric", np.array([], int))
        if len(idx):
            lbg[idx], ubg[idx] = (0.0 if cfg.impact_friction_cone else -np.inf), np.inf
        idx = self._block_idx.get("capture", np.array([], int))
        if len(idx):
            lbg[idx], ubg[idx] = -np.inf, np.inf
            if cfg.step_capture_constraint:
                forward = capture_point(model, q0, v0) >= model.com(q0)[0]
                lbg[idx[0 if forward else 1]] = cfg.step_capture_margin
        idx = self._block_idx.get("capture_soft", np.array([], int))
        if len(idx):
            lbg[idx], ubg[idx] = -np.inf, np.inf
            forward = capture_point(model, q0, v0) >= model.com(q0)[0]
            lbg[idx[0 if forward else 1]] = cfg.step_capture_margin
            oc = 1 + N * self.nk + self.n_imp
            lbx[oc:oc + 2], ubx[oc:oc + 2] = 0.0, np.inf
        idx = self._block_idx.get("touchdown", np.array([], int))
        if len(idx):   # normal velocity (surface normal points out of it): > -v_max, i.e. approach < v_max
            vlim = cfg.landing_limits.speed_max(key.extremity) if cfg.touchdown_speed_constraint else np.inf
            lbg[idx], ubg[idx] = -vlim, np.inf
        idx = self._block_idx.get("ke_path", np.array([], int))
        if len(idx):
            lbg[idx], ubg[idx] = -np.inf, cfg.transition_ke_cap_ratio * model.kinetic_energy(q0, v0)
        return lbx, ubx, lbg, ubg

    def _clearance_bounds(self, q0, env: Environment):
        """Clearance rows: phi >= eps_cl, ramped from the start value for points
        that start closer (a lifted foot); the target of an added contact may go
        down to 0 and is put on its surface at the last knot."""
        cfg, key, model = self.cfg, self.key, self.model
        N = key.n_knots
        lo, hi = [], []
        phi0 = [C.signed_distance(model, pt, s, env, q0) for pt, s in self.clear_pts]
        for k in range(1, N):
            frac = k / (N - 1)
            for (pt, s), p0 in zip(self.clear_pts, phi0):
                target = key.change == "add" and pt.split("_")[0] == key.extremity
                surf_target = target and env.surface_of(key.extremity) == s
                if surf_target:
                    dist_lb = 0.0
                    dist_ub = 0.0 if k == N - 1 else np.inf
                else:
                    dist_lb = min(cfg.eps_cl, max(0.0, p0) + cfg.eps_cl * frac) if p0 < cfg.eps_cl else cfg.eps_cl
                    if target:
                        dist_lb = 0.0  # the landing limb may touch the other surface's corner region
                    dist_ub = np.inf
                if s == "ground":        # row value is z = phi
                    lo.append(dist_lb)
                    hi.append(dist_ub)
                else:                    # row value is x = wall_x - phi
                    lo.append(env.wall_x - dist_ub)
                    hi.append(env.wall_x - dist_lb)
        return np.array(lo), np.array(hi)

    # ------------------------------------------------------------- packing
    def pack(self, T, q, v, a, u, lam) -> np.ndarray:
        w = np.zeros(self.nw)
        w[0] = T
        n, m = self.model.n, self.model.m
        for k, (o, _) in enumerate(self.knot_slices):
            w[o:o + n] = q[k]
            w[o + n:o + 2 * n] = v[k]
            w[o + 2 * n:o + 3 * n] = a[k]
            w[o + 3 * n:o + 3 * n + m] = u[k] / self.u_scale
            w[o + 3 * n + m:o + self.nk] = lam[k] / self.f_scale
        if self.n_imp:
            v_plus, imp = C.impact_map(self.model, q[-1], v[-1], self.impact_rows_for(q[-1]))
            oi = 1 + len(self.knot_slices) * self.nk
            w[oi:oi + n] = v_plus
            w[oi + n:oi + self.n_imp] = imp / self.imp_scale
        return w

    def impact_rows_for(self, q):
        return self.impact_rows

    def unpack(self, w):
        n, m = self.model.n, self.model.m
        W = np.asarray(w).ravel()
        T = float(W[0])
        blocks = np.stack([W[o:e] for o, e in self.knot_slices])
        return (T, blocks[:, :n], blocks[:, n:2 * n], blocks[:, 2 * n:3 * n],
                blocks[:, 3 * n:3 * n + m] * self.u_scale, blocks[:, 3 * n + m:] * self.f_scale)

    def violation(self, w, lbx, ubx, lbg, ubg) -> float:
        """Worst bound or constraint violation of a candidate (our own check)."""
        g = np.array(self.f_g(w)).ravel()
        W = np.asarray(w).ravel()
        vg = np.maximum(0, np.maximum(lbg - g, g - ubg))
        vx = np.maximum(0, np.maximum(lbx - W, W - ubx))
        return float(max(vg.max(initial=0.0), vx.max(initial=0.0)))


# ------------------------------------------------------------------ seeds
class SeedProjector:
    """Projection of the reference goal configuration onto the goal mode's
    constraint manifold (Sec. III-D step 2): a small least-squares NLP."""

    def __init__(self, model: PlanarModel, goal_rows: list, clear_pts: list, has_wall: bool):
        self.model, self.goal_rows, self.clear_pts = model, goal_rows, clear_pts
        n = model.n
        q = ca.SX.sym("q", n)
        qref = ca.SX.sym("qref", n)
        g = []
        for r in goal_rows:
            d = C.row_direction(r)
            p = model.f_point[r.point](q)
            g.append(d[0] * p[0] + d[1] * p[1])
        for pt, s in clear_pts:
            p = model.f_point[pt](q)
            g.append(p[1] if s == "ground" else p[0])
        G = ca.vertcat(*g) if g else ca.SX.zeros(0)
        wts = np.ones(n)
        wts[:3] = 4.0  # keep the trunk where it would be, move the limbs
        f = ca.sumsqr(ca.DM(np.sqrt(wts)) * (q - qref))
        self.solver = ca.nlpsol(f"proj_{id(self)}", "ipopt", {"x": q, "p": qref, "f": f, "g": G},
                                {"ipopt.print_level": 0, "print_time": False, "ipopt.sb": "yes",
                                 "ipopt.max_iter": 200, "ipopt.linear_solver": "mumps"})
        self.ng = G.shape[0]


def parabolic_seed(model: PlanarModel, q0, v0, qg, T, N, rows):
    """Sec. III-D steps 3-4: parabola q0 -> qg over T with initial velocity v0,
    sampled at the knots; u and lambda from the pseudo-inverse of [B, J^T]."""
    q0, v0, qg = (np.asarray(x, float) for x in (q0, v0, qg))
    acc = 2.0 * (qg - q0 - v0 * T) / T**2
    t = np.linspace(0.0, T, N)
    q = q0 + np.outer(t, v0) + 0.5 * np.outer(t**2, acc)
    v = v0 + np.outer(t, acc)
    a = np.tile(acc, (N, 1))
    u = np.zeros((N, model.m))
    lam = np.zeros((N, len(rows)))
    for k in range(N):
        rhs = np.array(model.f_id(q[k], v[k], a[k])).ravel()
        J = C.rows_jacobian(model, rows, q[k]) if rows else np.zeros((0, model.n))
        A = np.hstack([model.B, J.T])
        x = np.linalg.pinv(A) @ rhs
        u[k] = np.clip(x[:model.m], -model.u_max, model.u_max)
        lam[k] = x[model.m:]
    return t, q, v, a, u, lam


def capture_point(model: PlanarModel, q, v) -> float:
    """Instantaneous capture point x_com + xdot_com / omega, omega = sqrt(g / z_com) [m]
    (linear inverted pendulum over the ground; the step seed's reference)."""
    c = model.com(q)
    dc = model.com_velocity(q, v)
    return float(c[0] + dc[0] / math.sqrt(9.81 / max(c[1], 1e-3)))


# -------------------------------------------------------------- optimiser
class TrajectoryOptimizer:
    """opt_self_motion / opt_transition_motion with cached NLP structures."""

    def __init__(self, model: PlanarModel, cfg: OptConfig | None = None):
        self.model = model
        self.cfg = cfg or OptConfig()
        set_blas_threads(self.cfg.blas_threads)
        self._nlps: dict[StructureKey, SegmentNLP] = {}
        self._proj: dict[tuple, SeedProjector] = {}
        self._lock = threading.Lock()
        self.build_times: dict[str, float] = {}

    def nlp(self, key: StructureKey) -> SegmentNLP:
        with self._lock:
            if key not in self._nlps:
                t0 = time.perf_counter()
                self._nlps[key] = SegmentNLP(self.model, key, self.cfg)
                self.build_times[str(key)] = time.perf_counter() - t0
            return self._nlps[key]

    def projector(self, goal_mode: Mode, env: Environment, nlp: SegmentNLP) -> SeedProjector:
        pkey = (goal_mode, env.has_wall, nlp.key)
        with self._lock:
            if pkey not in self._proj:
                shape = Environment(0.0 if env.has_wall else None)
                rows = C.contact_rows(goal_mode, shape)
                self._proj[pkey] = SeedProjector(self.model, rows, nlp.clear_pts, env.has_wall)
            return self._proj[pkey]

    # ---------------------------------------------------------- public API
    def opt_self_motion(self, q0, v0, mode: Mode, env: Environment, deadline: float | None = None,
                        skip_seeds: int = 0) -> Segment:
        """Fixed-contact (inertial shaping) trajectory at mode sigma (Alg. 1 line 5);
        ``skip_seeds``: begin after that many seeds of ``OptConfig.seed_durations``."""
        return self._optimize(q0, v0, mode, "", "", env, deadline, skip_seeds)

    def opt_transition_motion(self, q0, v0, mode: Mode, target: Mode, env: Environment,
                              deadline: float | None = None, release_t_max: float | None = None,
                              t_max: float | None = None) -> Segment:
        """Trajectory from mode sigma_i that ends ready for sigma_j (Alg. 1 line 13).
        ``release_t_max`` (a release only): its T_max for this solve instead of ``OptConfig.release_t_max``
        (the tree's short-release alternative, ``search(release_alternatives=)``). ``t_max``: a T_max for
        this solve below the one of its kind (the tree's ``single_foot_t_max``); refused below its T_min."""
        added = set(target) - set(mode)
        removed = set(mode) - set(target)
        if len(added) + len(removed) != 1:
            raise ValueError("adjacent modes differ by exactly one extremity")
        change, ext = ("add", added.pop()) if added else ("remove", removed.pop())
        if release_t_max is not None and change != "remove":
            raise ValueError("release_t_max bounds a release (a transition that removes a contact) only")
        if t_max is not None and not t_max >= self.cfg.t_min_of(change, ext):
            raise ValueError(f"t_max {t_max!r} s is below this transition's T_min "
                             f"{self.cfg.t_min_of(change, ext):g} s")
        return self._optimize(q0, v0, mode, change, ext, env, deadline, release_t_max=release_t_max, t_max=t_max)

    def structures(self, mode: Mode, change: str, ext: str, env: Environment) -> tuple[SegmentNLP, Mode]:
        """The cached NLP of a segment and the mode its seed goal is projected onto
        (both built on first use)."""
        nlp = self.nlp(StructureKey(change, tuple(mode), ext, env.has_wall, self.cfg.n_knots))
        # a released contact is held until the end of the transition, so only
        # an added contact changes the manifold the goal is projected onto
        goal_mode = make_mode(set(mode) | {ext}) if change == "add" else tuple(mode)
        self.projector(goal_mode, env, nlp)
        return nlp, goal_mode

    def seed(self, q0, v0, mode: Mode, change: str, ext: str, env: Environment, T: float):
        """Initial guess for one duration (Sec. III-D); returns (nlp, guess arrays, q_goal)."""
        nlp, goal_mode = self.structures(mode, change, ext, env)
        q_goal = self.project_goal(q0, v0, mode, goal_mode, env, nlp, T)
        t, q, v, a, u, lam = parabolic_seed(self.model, q0, v0, q_goal, T, nlp.key.n_knots, nlp.rows)
        return nlp, (t, q, v, a, u, lam), q_goal

    def project_goal(self, q0, v0, mode, goal_mode, env, nlp: SegmentNLP, T):
        q0 = np.asarray(q0, float)
        q_ref = q0 + 0.5 * np.asarray(v0, float) * T  # q_dot decreasing linearly to 0 at T
        proj = self.projector(goal_mode, env, nlp)
        # bounds: goal rows anchored like the NLP's last knot
        lbg, ubg = [], []
        anchors = C.rows_value(self.model, proj.goal_rows, q0)
        step_x = None
        if math.isfinite(self.cfg.step_seed_capture_offset):
            landing = [e for e in goal_mode if e not in mode and e in FEET]
            if landing:
                step_x = capture_point(self.model, q0, v0) + self.cfg.step_seed_capture_offset
        for i, r in enumerate(proj.goal_rows):
            if r.axis == "n":
                val = -(env.wall_x) if r.surface == "wall" else 0.0
                lbg.append(val); ubg.append(val)
            elif r.extremity in mode:
                lbg.append(anchors[i]); ubg.append(anchors[i])
            elif step_x is not None:   # the landing foot's toe past the capture point (a step seed)
                lbg.append(step_x); ubg.append(step_x + 0.1)
            else:
                lbg.append(-np.inf); ubg.append(np.inf)
        lo, hi = nlp._clearance_bounds(q0, env)
        nc = len(nlp.clear_pts)
        lo, hi = (lo[-nc:].copy(), hi[-nc:].copy()) if nc else (np.zeros(0), np.zeros(0))
        goal_points = {(r.point, r.surface) for r in proj.goal_rows}
        for i, ps in enumerate(nlp.clear_pts):
            if ps in goal_points:  # already an equality among the goal rows
                lo[i], hi[i] = -np.inf, np.inf
        lbg += list(lo)
        ubg += list(hi)
        lbx = np.full(self.model.n, -np.inf)
        ubx = np.full(self.model.n, np.inf)
        lbx[1] = self.cfg.root_z_min
        lbx[3:], ubx[3:] = self.model.q_min, self.model.q_max
        x0 = np.clip(q_ref, lbx, ubx)
        try:
            sol = proj.solver(x0=x0, p=q_ref, lbx=lbx, ubx=ubx, lbg=np.array(lbg), ubg=np.array(ubg))
            qg = np.array(sol["x"]).ravel()
            if proj.solver.stats()["success"]:
                return qg
        except RuntimeError:
            pass
        return x0

    def _optimize(self, q0, v0, mode, change, ext, env, deadline, skip_seeds: int = 0,
                  release_t_max: float | None = None, t_max: float | None = None) -> Segment:
        cfg, model = self.cfg, self.model
        # the T bounds and seed grid of this solve (a release may be given its own T_max; any transition a
        # lower one)
        cfg_t = cfg if release_t_max is None else dataclasses.replace(cfg, release_t_max=float(release_t_max))
        if t_max is not None and t_max < cfg_t.t_max_of(change):
            cfg_t = dataclasses.replace(cfg_t, t_max=float(t_max),
                                        release_t_max=min(cfg_t.release_t_max, float(t_max)))
        t_bounds = (cfg_t.t_min_of(change, ext), cfg_t.t_max_of(change))
        q0 = np.asarray(q0, float)
        v0 = np.asarray(v0, float)
        target = make_mode(set(mode) | {ext}) if change == "add" else (
            make_mode(set(mode) - {ext}) if change == "remove" else tuple(mode))
        t_start = time.perf_counter()
        c_start = time.thread_time()
        # build (or fetch) the cached structures first, so that the one-off
        # build cost is reported apart from the solve time
        self.structures(mode, change, ext, env)
        build_time = time.perf_counter() - t_start
        ke0 = model.kinetic_energy(q0, v0)
        best = None
        attempts = 0
        log = []
        for T in cfg_t.seed_durations(change, skip_seeds, ext):
            if deadline is not None and time.perf_counter() >= deadline:
                break
            attempts += 1
            t_a = time.perf_counter()
            nlp, (_, q, v, a, u, lam), _ = self.seed(q0, v0, mode, change, ext, env, T)
            lbx, ubx, lbg, ubg = nlp.bounds(q0, v0, env, t_bounds=t_bounds)
            w0 = np.clip(nlp.pack(T, q, v, a, u, lam), lbx, ubx)
            with nlp.lock:
                sol = nlp.solver(x0=w0, p=nlp.parameters(), lbx=lbx, ubx=ubx, lbg=lbg, ubg=ubg)
                stats = nlp.solver.stats()
            iters = int(stats.get("iter_count", 0))
            restarts = 0
            w = np.array(sol["x"]).ravel()
            viol = nlp.violation(w, lbx, ubx, lbg, ubg)
            # IPOPT stalled (tiny steps, barrier parameter stuck high), or stopped at its
            # "acceptable" level with the constraints still violated beyond our tolerance:
            # restart it from its last iterate and multipliers. Measured on the 60/70 J
            # hand landings: 300 iterations without convergence, then the restart
            # converged in 34-58 iterations; the 30 J stepped double support (session 7):
            # acceptable at 1035 iterations with violation 1.2e-4 > feasibility_tol.
            while ((stats["return_status"] == "Maximum_Iterations_Exceeded"
                    or (stats["return_status"] == "Solved_To_Acceptable_Level" and viol > cfg.feasibility_tol))
                   and restarts < cfg.warm_restarts and (deadline is None or time.perf_counter() < deadline)):
                restarts += 1
                with nlp.lock:
                    sol = nlp.solver(x0=sol["x"], p=nlp.parameters(), lam_x0=sol["lam_x"], lam_g0=sol["lam_g"],
                                     lbx=lbx, ubx=ubx, lbg=lbg, ubg=ubg)
                    stats = nlp.solver.stats()
                iters += int(stats.get("iter_count", 0))
                w = np.array(sol["x"]).ravel()
                viol = nlp.violation(w, lbx, ubx, lbg, ubg)
            stats = dict(stats)
            stats["iter_count"] = iters
            ok = stats["return_status"] in ("Solve_Succeeded", "Solved_To_Acceptable_Level") \
                and viol <= cfg.feasibility_tol
            seg = self._segment(nlp, w, mode, target, change, ext, ok, stats, T, viol, t_bounds)
            seg.objective = float(nlp.f_ke_end(w))
            seg.multipliers = (np.array(sol["lam_x"]).ravel(), np.array(sol["lam_g"]).ravel())
            log.append({"seed_T": round(T, 4), "status": seg.status, "iterations": seg.iterations,
                        "time": round(time.perf_counter() - t_a, 3), "objective": round(seg.objective, 4),
                        "final_ke": round(seg.final_ke, 4), "T": round(float(seg.time[-1]), 4),
                        "violation": viol, "success": bool(ok), "warm_restarts": restarts})
            if best is None or (ok and not best.success) or (ok == best.success and seg.objective < best.objective):
                best = seg
            # stop at the first converged seed (Sec. III-D), unless a contact
            # landing keeps most of the energy it started with (a poor local optimum)
            # (post_impact objective only: with the paper's pre-impact objective a landing
            # from standing always arrives with more than it started with, it falls, and
            # the seeds converged to the same optimum: 30 J hand landing, 52.23 J x 3)
            if best.success and not (cfg.retry_if_energy_rises and change == "add"
                                     and cfg.transition_objective == "post_impact"
                                     and best.objective > cfg.retry_energy_fraction * ke0):
                break
        if best is None:
            if skip_seeds and not cfg_t.seed_durations(change, skip_seeds, ext):
                raise ValueError("no seed left after skipping")
            raise TimeoutError("time budget exhausted before the first NLP")
        best.nlp_time = time.perf_counter() - t_start
        best.build_time = build_time
        best.cpu_time = time.thread_time() - c_start
        best.attempts = attempts
        best.attempt_log = log
        return best

    def prepare_warm(self, guess: Segment, env: Environment) -> None:
        """Build what ``warm_solve(.., guess, env)`` will use (a node's warm-up for its library)."""
        nlp, _ = self.structures(guess.mode, guess.change, guess.extremity, env)
        if self.cfg.warm_start_multipliers and nlp.fits(guess.multipliers):
            nlp.warm_solver()

    def warm_solve(self, q0, v0, guess: Segment, env: Environment, acc_max: float | None = None,
                   multipliers: bool | None = None, capture_weight: float | None = None) -> Segment:
        """Re-solve ``guess``'s NLP (same mode and contact change) from a new initial
        state, with ``guess``'s knots, torques and forces as the initial point: one
        IPOPT run, no seed sweep (the online re-plan from a library of plans; paper 2,
        Sec. V names such a database as future work). The first knot is the new state
        (the bounds fix it); the rest of the guess is used as it is.

        ``acc_max`` (rad/s^2 or m/s^2) replaces ``OptConfig.acc_max`` as the bound on
        the knot accelerations of this solve (a bound, not a structure: the cached NLP
        serves). The tree's polish of a stop the re-simulation check rejected uses it
        (docs/multicontact.md, "Session 11").

        ``multipliers`` (None: ``OptConfig.warm_start_multipliers``): when ``guess`` carries IPOPT's
        multipliers of this structure, start IPOPT from them as well (``SegmentNLP.warm_solver``);
        measured on the library re-plans (session 25): 20 J entry re-solved at 22 / 25 J, 1.36 / 2.10 s
        primal only, 0.99 / 1.08 s with them (iterations 130 / 191 -> 93 / 95).

        The duration T stays within ``guess.t_bounds`` when the guess records them (the bounds it was
        solved within; else ``OptConfig``'s): a re-solve is the guess's NLP from a new state, and a
        library entry planned with a bounded release (``release_t_max``) is re-solved as it was planned
        (session 32: with the default T_max its release, whose multipliers hold T at the bound, ends
        infeasible).

        ``capture_weight`` (None: ``OptConfig.step_capture_weight``): the weight of a foot landing's capture
        cost in this solve; a library re-plans its entries with the weight they were planned with (session 36:
        the shipped library's 2000 J/m^2 entries re-solved at 6000 answered 16 instead of 19 of 19 queries
        within 1 s)."""
        q0 = np.asarray(q0, float)
        v0 = np.asarray(v0, float)
        t0, c0 = time.perf_counter(), time.thread_time()
        nlp, _ = self.structures(guess.mode, guess.change, guess.extremity, env)
        use_mult = (self.cfg.warm_start_multipliers if multipliers is None else multipliers) \
            and nlp.fits(guess.multipliers)
        solver = nlp.warm_solver() if use_mult else nlp.solver   # built on first use: part of build_time
        build_time = time.perf_counter() - t0
        lbx, ubx, lbg, ubg = nlp.bounds(q0, v0, env, acc_max=acc_max, t_bounds=guess.t_bounds)
        # the stored knots moved so that they start at the new state, the shift fading
        # out linearly to the last knot (which keeps the stored end)
        fade = np.linspace(1.0, 0.0, len(guess.time))[:, None]
        q = guess.q + fade * (q0 - guess.q[0])
        v = guess.v + fade * (v0 - guess.v[0])
        w0 = np.clip(nlp.pack(float(guess.time[-1]), q, v, guess.a, guess.u, guess.lam), lbx, ubx)
        mult = {"lam_x0": guess.multipliers[0], "lam_g0": guess.multipliers[1]} if use_mult else {}
        p = nlp.parameters(capture_weight)
        with nlp.lock:
            sol = solver(x0=w0, p=p, lbx=lbx, ubx=ubx, lbg=lbg, ubg=ubg, **mult)
            stats = dict(solver.stats())
        iters = int(stats.get("iter_count", 0))
        w = np.array(sol["x"]).ravel()
        viol = nlp.violation(w, lbx, ubx, lbg, ubg)
        ok = stats["return_status"] in ("Solve_Succeeded", "Solved_To_Acceptable_Level") \
            and viol <= self.cfg.feasibility_tol
        restarts = 0
        # a warm start that stopped short (iteration cap, or IPOPT's "acceptable" exit
        # with constraints still violated: seen in CI on a 12 J re-plan of the 10 J plan)
        # is restarted from its last iterate and multipliers, as _optimize does; at least
        # once, since a re-plan has no other seed to try
        while not ok and restarts < max(1, self.cfg.warm_restarts) and stats["return_status"] in (
                "Maximum_Iterations_Exceeded", "Solved_To_Acceptable_Level"):
            restarts += 1
            with nlp.lock:
                sol = solver(x0=sol["x"], p=p, lam_x0=sol["lam_x"], lam_g0=sol["lam_g"],
                             lbx=lbx, ubx=ubx, lbg=lbg, ubg=ubg)
                stats = dict(solver.stats())
            iters += int(stats.get("iter_count", 0))
            w = np.array(sol["x"]).ravel()
            viol = nlp.violation(w, lbx, ubx, lbg, ubg)
            ok = stats["return_status"] in ("Solve_Succeeded", "Solved_To_Acceptable_Level") \
                and viol <= self.cfg.feasibility_tol
        stats["iter_count"] = iters
        seg = self._segment(nlp, w, guess.mode, guess.target_mode, guess.change, guess.extremity, ok, stats,
                            float(guess.time[-1]), viol, (float(lbx[0]), float(ubx[0])))
        seg.objective = float(nlp.f_ke_end(w))
        seg.multipliers = (np.array(sol["lam_x"]).ravel(), np.array(sol["lam_g"]).ravel())
        seg.nlp_time, seg.build_time, seg.cpu_time = time.perf_counter() - t0, build_time, time.thread_time() - c0
        seg.attempt_log = [{"seed_T": "warm", "multipliers": bool(use_mult), "status": seg.status,
                            "iterations": seg.iterations,
                            "time": round(seg.nlp_time, 3), "objective": round(seg.objective, 4),
                            "final_ke": round(seg.final_ke, 4), "T": round(float(seg.time[-1]), 4),
                            "violation": viol, "success": bool(ok), "warm_restarts": restarts}]
        return seg

    def _segment(self, nlp, w, mode, target, change, ext, ok, stats, T_seed, viol, t_bounds: tuple) -> Segment:
        """The solved NLP ``w`` as a Segment; ``t_bounds``: the (T_min, T_max) it was solved within."""
        T, q, v, a, u, lam = nlp.unpack(w)
        N = nlp.key.n_knots
        ke = np.array([self.model.kinetic_energy(q[k], v[k]) for k in range(N)])
        return Segment(kind="transition" if change else "self_motion", mode=tuple(mode), target_mode=target,
                       change=change, extremity=ext, time=np.linspace(0, T, N), q=q, v=v, a=a, u=u, lam=lam,
                       rows=list(nlp.rows), ke=ke, success=bool(ok), status=str(stats["return_status"]),
                       iterations=int(stats.get("iter_count", -1)), nlp_time=0.0, seed_duration=T_seed,
                       attempts=1, max_violation=viol, t_bounds=tuple(t_bounds))
