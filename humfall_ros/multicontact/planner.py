"""The planner behind the ``plan_fall`` service: a request (validated by
``request.py``: the initial state) answered from a library of plans when one is
loaded and fits (``library.py``), else by the tree search, as a plain-dict result
(no ROS types here).

Request fields mirror humfall_interfaces/srv/PlanFall: q, v (planar, may be
empty), kinetic_energy, direction, initial_mode, wall_distance, time_budget.

Conventions: the world x axis points forward; the nominal stance has both
ankles at x = 0 and the soles on z = 0; ``wall_distance`` > 0 puts a wall at
the plane x = wall_distance (so it is "ahead of the stance").
"""
from __future__ import annotations

import dataclasses
import pathlib
import threading
import time

from humfall_ros import params
from humfall_ros.multicontact.collocation import OptConfig, TrajectoryOptimizer
from humfall_ros.multicontact.landing import LandingLimits
from humfall_ros.multicontact.library import PlanLibrary
from humfall_ros.multicontact.model import PlanarModel, load_model
from humfall_ros.multicontact.modes import Environment
from humfall_ros.multicontact.resim import PlanCheck, warm_check_pool
from humfall_ros.multicontact.request import InvalidRequest, ValidRequest, validate  # noqa: F401 (re-exported)
from humfall_ros.multicontact.tree import SearchResult, search
from humfall_ros.paths import share_dir


# Named parameter sets of earlier planners, as ``FallPlanner.from_params(**...)`` overrides (the benchmarks'
# comparisons and the tests use these; one definition). NO_STEP_OPTIONS: none of the step options that are the
# defaults since session 11. DEPARTURE: the planner before issue 14 (post-impact objective and frontier key,
# departures from paper 2 Sec. III-A / Alg. 1 line 20; landings not limited).
NO_STEP_OPTIONS = {"frontier_lookahead_steps": False, "step_capture_weight": 0.0, "step_capture_margin": 0.0,
                   "release_t_min": 0.0, "step_t_min": 0.0, "max_iter": 300, "check_polish_acc_max": 0.0,
                   "release_alternatives": [0.0]}
DEPARTURE = {"transition_objective": "post_impact", "frontier_order": "post_impact", "landing_policy": "ignore",
             "touchdown_speed_constraint": False, **NO_STEP_OPTIONS}
# FOR_EXECUTION: plans meant for the 3-D robot (the multicontact executor; bench_multicontact_exec.py's default). A
# foot landing's post-impact capture point 0.25 m inside the landing toe, not the declared 0.12: the planar model has
# no lateral sway, no sensor noise and no swing that lets the stance foot go light, and with 0.12 the executed 60 J
# plan (two steps) falls and half the noisy replays of the 20-50 J plans fall; with 0.25 every step plan from 20 to
# 60 J ends at rest, also with TYPICAL_NOISE (docs/multicontact.md "Session 41"). Not the declared default: the
# planar sweep then takes 135 s instead of 108 s and lands its steps with more energy (30 J: 30.2 J > the push).
FOR_EXECUTION = {"step_capture_margin": 0.25}
# The library of FOR_EXECUTION's plans (forward pushes 10-50 J: tree searches every 2.5 J, densified to 1.25 J and
# probed; `make library-execution`, docs/multicontact.md "Session 43"): the declared library is planned with the
# declared margin, which a planner of FOR_EXECUTION's refuses (PlanLibrary.check_compatible).
EXECUTION_LIBRARY = "multicontact_library/execution_pushes.json.gz"
# A request's ``planner_profile`` (PlanFall): overrides on top of the planner's own parameters, for one request.
# "execution": FOR_EXECUTION with its own library (a request beyond it goes to the tree search, as ever).
PROFILES = {"execution": {**FOR_EXECUTION, "library_file": EXECUTION_LIBRARY}}


@dataclasses.dataclass
class PlannerConfig:
    max_depth: int = 4
    time_budget: float = 120.0        # s, default when the request gives <= 0
    max_time_budget: float = 600.0
    # NLP calls per plan (0: none): a budget that ends the search at the same node on any machine
    max_nlps: int = 0
    max_kinetic_energy: float = 1000.0  # J, refuse requests beyond this
    contact_tolerance: float = 0.005   # m, |phi| of a contact in the given state
    velocity_tolerance: float = 0.01   # m/s, |J v| of a contact in the given state
    penetration_tolerance: float = 0.001  # m
    symmetry_cut: bool = True
    # a stabilising plan is accepted only if the knot-to-knot re-simulation
    # (resim.plan_check) stays within these; <= 0 disables the check
    check_q_error_max: float = 0.1         # rad or m
    check_force_error_max_mg: float = 1.0  # contact force correction, units of M g
    # a segment that fails open loop passes if a joint tracking controller of this bandwidth
    # (rad/s) reproduces it with at most check_feedback_max of a joint's torque limit as feedback
    check_feedback_omega: float = 40.0
    check_feedback_max: float = 0.5
    # worker processes for the re-simulation check of library re-plans (0: in process; 1: each segment is
    # checked while the next one is solved, session 33)
    check_workers: int = 1
    # frontier key of a child reached by a landing: 'pre_impact' (Alg. 1 line 20, the
    # paper) or 'post_impact' (departure); landings beyond the limits: rank_last | refuse | ignore
    frontier_order: str = "capture"   # departure; default since session 11 (session 6-10: mechanical)
    landing_policy: str = "rank_last"
    # departure: solve a child's self-motion when it is made and key it on its end energy (tree.search)
    frontier_lookahead: bool = False
    # departure: the same for children reached by a foot landing only (the second half of a step)
    frontier_lookahead_steps: bool = True
    # a stopping self-motion rejected by the re-simulation check is solved again from the next seeds
    check_retry_seeds: bool = False
    # a stopping self-motion rejected by the re-simulation check is re-solved warm from itself with
    # its knot accelerations bounded by this (rad/s^2 or m/s^2; 0: off) before it is given up
    check_polish_acc_max: float = 100.0
    # a library of precomputed plans (``library.py``; a path, relative ones under the package's config/):
    # a request whose kinetic energy is within ``library_max_ke_gap`` of an entry's (same direction and
    # wall presence) is first re-solved warm from that entry (~0.3-2 s), the tree search only when that
    # is not accepted; "" = no library (the paper's Algorithm 1 for every request)
    library_file: str = ""
    library_max_ke_gap: float = 5.0   # J
    library_max_entries: int = 2      # entries re-solved, nearest first, before the tree search
    # a library re-plan is accepted only if it passes the re-simulation check the tree applies
    # (check_q_error_max > 0); session 31: 49 J re-solved from the 47.5 J entry does not
    library_check: bool = True
    # departure (session 34): T_max bounds (s) under which each release is solved a second time and added as
    # another child (tree.search ``release_alternatives``); values <= 0 are dropped (none: the paper)
    release_alternatives: tuple = (0.05,)   # session 34: (0.1,); session 35: (0.05,) with release_t_min 0.05
    # false (ours, session 37): no plan passes through one foot alone in contact (tree.search
    # ``single_foot_modes``; library entries that do are not used): plans a 3-D robot can follow without the
    # lateral weight shift the planar model has no coordinate for. True: Fig. 2's whole mode graph (the paper)
    single_foot_modes: bool = True
    # departure (session 38; the default since session 40): a plan may pass through one foot alone (a step's
    # swing) but never ends there (tree.search ``single_foot_terminal``): a planar stop on one foot leaves a 3-D
    # robot's centre of mass between the feet, over nothing. True: any mode may end a plan (the paper)
    single_foot_terminal: bool = False
    # departure (session 38; the default since session 40; s): T_max of every transition out of a node on one foot
    # alone other than the root (tree.search ``single_foot_t_max``): one foot alone for a swing, not a stance.
    # 0: t_max (the paper)
    single_foot_t_max: float = 0.4
    stance: dict = dataclasses.field(default_factory=dict)

    def __post_init__(self):
        self.release_alternatives = tuple(sorted(float(x) for x in self.release_alternatives if float(x) > 0))

    @staticmethod
    def from_params(d: dict) -> PlannerConfig:
        """From a dict of PlannerConfig field names; unknown keys are refused."""
        return params.config_from(PlannerConfig, d)


# parameters of config/multicontact_planner.yaml that only the node uses
NODE_ONLY_PARAMS = ("queue_size", "warm_up")
_LANDING_PARAMS = {"landing_hand_normal_speed_max": "hand_normal_speed_max",
                   "landing_foot_normal_speed_max": "foot_normal_speed_max",
                   "landing_hand_energy_max": "hand_energy_max",
                   "landing_foot_energy_max": "foot_energy_max"}


def configs_from_params(values: dict) -> tuple[OptConfig, PlannerConfig]:
    """(OptConfig, PlannerConfig) from the flat parameters of config/multicontact_planner.yaml
    (``humfall_ros.params.defaults("multicontact_planner")`` or the node's declared values).

    ``stance_<joint>`` go to ``PlannerConfig.stance``, ``landing_*`` to
    ``OptConfig.landing_limits``, ``step_seed_at_capture_point`` gates
    ``step_seed_capture_offset``; a name neither dataclass knows is refused
    (ValueError), except the node's own (``NODE_ONLY_PARAMS``)."""
    opt_names = {f.name for f in dataclasses.fields(OptConfig)}
    plan_names = {f.name for f in dataclasses.fields(PlannerConfig)} - {"stance"}
    opt, plan, stance, limits = {}, {}, {}, {}
    unknown = []
    step_seed = bool(values.get("step_seed_at_capture_point", False))
    for k, v in values.items():
        if k in NODE_ONLY_PARAMS or k == "step_seed_at_capture_point":
            continue
        if k.startswith("stance_"):
            stance[k.removeprefix("stance_")] = v
        elif k in _LANDING_PARAMS:
            limits[_LANDING_PARAMS[k]] = float(v)
        elif k in opt_names:
            opt[k] = tuple(v) if isinstance(v, list) else v
        elif k in plan_names:
            plan[k] = v
        else:
            unknown.append(k)
    if unknown:
        raise ValueError(f"multicontact_planner parameters: unknown {sorted(unknown)}")
    if "step_seed_capture_offset" in opt and not step_seed:
        opt["step_seed_capture_offset"] = float("nan")
    opt["landing_limits"] = LandingLimits(**limits)
    return OptConfig.from_params(opt), PlannerConfig.from_params({**plan, "stance": stance})


class FallPlanner:
    """Holds the planar model and the cached NLP structures across requests."""

    def __init__(self, opt_cfg: OptConfig | None = None, cfg: PlannerConfig | None = None,
                 model: PlanarModel | None = None):
        self.model = model or load_model()
        self.cfg = cfg or PlannerConfig()
        self.opt = TrajectoryOptimizer(self.model, opt_cfg or OptConfig())
        self.values: dict | None = None   # the parameters it was built from (from_params), for the profiles
        self._profiles: dict[str, FallPlanner] = {}
        self._profiles_lock = threading.Lock()   # the node's warm-up and a request may ask for one at once
        self.library = None
        if self.cfg.library_file:
            path = library_path(self.cfg.library_file)
            try:
                self.library = PlanLibrary.load(path)
            except (OSError, ValueError, KeyError, TypeError) as e:
                raise ValueError(f"library_file {self.cfg.library_file!r} ({path}) cannot be read: "
                                 f"{type(e).__name__}: {e}") from e
            self.library.check_compatible(self.opt.cfg)
            if not self.cfg.single_foot_modes:
                self.library = self.library.without_single_foot_modes()
            if not self.cfg.single_foot_terminal:
                self.library = self.library.without_single_foot_ends()

    @staticmethod
    def from_params(values: dict | None = None, **overrides) -> FallPlanner:
        """A planner built from the node's declaration (config/multicontact_planner.yaml),
        ``overrides`` by parameter name on top (the way tests and benchmarks build it)."""
        vals = params.defaults("multicontact_planner") if values is None else dict(values)
        unknown = set(overrides) - set(vals)
        if unknown:
            raise ValueError(f"multicontact_planner has no parameters {sorted(unknown)}")
        vals.update(overrides)
        opt, cfg = configs_from_params(vals)
        planner = FallPlanner(opt, cfg)
        planner.values = vals
        return planner

    def profile(self, name: str) -> FallPlanner:
        """The planner for a request's ``planner_profile``: this one for "", else one built from this planner's
        parameters (the declaration's when it was not built by :meth:`from_params`) with ``PROFILES[name]`` on
        top, made on first use and kept (its NLP structures are its own). ValueError for an unknown name."""
        if not name:
            return self
        if name not in PROFILES:
            raise ValueError(f"unknown planner_profile {name!r} (one of '', {', '.join(map(repr, PROFILES))})")
        with self._profiles_lock:
            if name not in self._profiles:
                self._profiles[name] = FallPlanner.from_params(self.values, **PROFILES[name])
            return self._profiles[name]

    def warm_up_library(self, stop=None) -> tuple[bool, int]:
        """Ready the library's re-plans before the first request (the node's warm-up, the library benchmark): the
        check's worker (:meth:`warm_up_checks`), then each stored segment's NLP structure and warm-start solver.
        ``stop()`` true ends it early. Returns (the check runs in a worker, segments readied); (False, 0) without
        a library."""
        if self.library is None:
            return False, 0
        worker, n = self.warm_up_checks(), 0
        for e in self.library.entries:
            env = Environment.from_distance(e.wall_distance)
            for s in e.segments:
                if stop is not None and stop():
                    return worker, n
                self.opt.prepare_warm(s, env)
                n += 1
        return worker, n

    def warm_up_checks(self) -> bool:
        """Start the check's worker process (``check_workers``) before the first request needs it; False
        when it cannot be used (the checks then run in process) or is not asked for."""
        if self.cfg.check_workers > 0 and self.cfg.check_q_error_max > 0 and self.cfg.library_check:
            return warm_check_pool(self.model.urdf)
        return False

    def check_fn(self, env) -> PlanCheck | None:
        """The re-simulation acceptance test of a plan in ``env`` (``resim.PlanCheck`` with this planner's
        ``check_*`` parameters: segments -> None or the reason; its ``start()`` checks segments one at a time,
        in a worker process with ``check_workers`` 1, for the library's re-plans), or None when
        ``check_q_error_max`` <= 0."""
        if self.cfg.check_q_error_max <= 0:
            return None
        c = self.cfg
        return PlanCheck(self.model, env, (c.check_q_error_max, c.check_force_error_max_mg, c.check_feedback_omega,
                                           c.check_feedback_max), c.check_workers)

    def plan(self, req: dict) -> dict:
        """A plan for one request: from the library when one is loaded and its re-plan is accepted
        (``result["source"] == "library"``), else by the tree search (``"tree_search"``, with what the
        library said in ``library_attempt``), within the request's time budget all told. A request's
        ``planner_profile`` (e.g. "execution") is planned by :meth:`profile`'s planner."""
        t0 = time.perf_counter()
        name = req.get("planner_profile") or ""
        if name:
            try:
                planner = self.profile(name)
            except ValueError as e:
                return failure(f"invalid request: {e}", time.perf_counter() - t0)
            out = planner.plan({**req, "planner_profile": ""})
            out["total_time_s"] = time.perf_counter() - t0   # with the profile's planner built, the first time
            return out
        try:
            vr = validate(self.model, req, self.cfg)
        except InvalidRequest as e:
            return failure(f"invalid request: {e}", time.perf_counter() - t0)
        check = self.check_fn(vr.env)
        attempt = None
        if self.library is not None:
            rp = self.library.replan_valid(self, vr, max_ke_gap=self.cfg.library_max_ke_gap,
                                           max_entries=self.cfg.library_max_entries,
                                           check_plan=check if self.cfg.library_check else None)
            if rp.success:
                out = replan_dict(self.model, rp, vr)
                out["total_time_s"] = time.perf_counter() - t0
                return out
            attempt = rp.reason
            vr = dataclasses.replace(vr, time_budget=max(vr.time_budget - (time.perf_counter() - t0), 0.0))
        res = search(self.opt, vr.q, vr.v, vr.mode, vr.env, max_depth=self.cfg.max_depth,
                     time_budget=vr.time_budget, symmetry_cut=self.cfg.symmetry_cut, check_plan=check,
                     frontier_order=self.cfg.frontier_order, landing_policy=self.cfg.landing_policy,
                     lookahead=self.cfg.frontier_lookahead, step_lookahead=self.cfg.frontier_lookahead_steps,
                     check_retry_seeds=self.cfg.check_retry_seeds,
                     polish_acc_max=self.cfg.check_polish_acc_max if check is not None else 0.0,
                     max_nlps=self.cfg.max_nlps, release_alternatives=self.cfg.release_alternatives,
                     single_foot_modes=self.cfg.single_foot_modes,
                     single_foot_terminal=self.cfg.single_foot_terminal,
                     single_foot_t_max=self.cfg.single_foot_t_max)
        out = result_dict(self.model, res, vr)
        out["total_time_s"] = time.perf_counter() - t0
        if attempt is not None:
            out["library_attempt"] = attempt
        return out


def library_path(name: str):
    """``library_file`` as a path: absolute as given, relative under the package's config/."""
    p = pathlib.Path(name).expanduser()
    return p if p.is_absolute() else share_dir() / "config" / p


def failure(reason: str, elapsed: float = 0.0) -> dict:
    return {"success": False, "reason": reason, "source": "", "contact_sequence": [], "node_ke": [],
            "final_ke": float("nan"),
            "segments": [], "nlp_times_s": [], "nlp_cpu_s": [], "nlp_build_s": [], "total_time_s": elapsed,
            "nlp_count": 0, "tree_nodes": 0, "landings": [], "landings_within_limits": False,
            "deepest_depth": 0, "tree": None, "initial_ke": float("nan")}


def replan_dict(model: PlanarModel, rp, vr: ValidRequest) -> dict:
    """``result_dict``'s shape for an accepted library re-plan (``library.Replan``): no tree."""
    segs = rp.segments
    return {
        "success": True, "reason": rp.reason, "source": "library",
        "contact_sequence": list(rp.entry.contact_sequence), "node_ke": [float(s.ke[0]) for s in segs],
        "final_ke": rp.final_ke, "initial_ke": model.kinetic_energy(vr.q, vr.v),
        "segments": segs, "nlp_times_s": list(rp.nlp_times_s), "nlp_cpu_s": [s.cpu_time for s in segs],
        "nlp_build_s": [s.build_time for s in segs], "total_time_s": rp.time_s,
        "nlp_count": len(rp.nlp_times_s), "tree_nodes": 0, "deepest_depth": len(segs) - 1,
        "tree": None, "landings": list(rp.landings),
        "landings_within_limits": bool(all(x.within_limits for x in rp.landings)),
        "search": None, "env": vr.env, "wall_x": vr.env.wall_x,
    }


def result_dict(model: PlanarModel, res: SearchResult, vr: ValidRequest) -> dict:
    return {
        "success": res.success, "reason": res.reason,
        "contact_sequence": res.contact_sequence, "node_ke": res.node_ke,
        "final_ke": res.final_ke, "initial_ke": model.kinetic_energy(vr.q, vr.v),
        "segments": res.segments(), "nlp_times_s": [e["nlp_time"] for e in res.nlp_log],
        "nlp_cpu_s": [e["cpu_time"] for e in res.nlp_log],
        "nlp_build_s": [e["build_time"] for e in res.nlp_log],
        "total_time_s": res.total_time, "nlp_count": len(res.nlp_log), "tree_nodes": len(res.nodes),
        "deepest_depth": res.deepest_depth, "tree": res.tree_dict(with_trajectories=False),
        "landings": res.landings(),
        "landings_within_limits": bool(res.success and all(x.within_limits for x in res.landings())),
        "search": res, "env": vr.env, "wall_x": vr.env.wall_x, "source": "tree_search",
    }
