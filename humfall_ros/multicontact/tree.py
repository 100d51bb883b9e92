"""Contact transition tree search (paper 2, Algorithm 1, Sec. III-A/B).

Nodes hold a contact mode, a robot state and (once popped) their self-motion;
edges hold the transition trajectory from the parent. The frontier is a
priority queue on kinetic energy. The whole tree is kept and serialisable to
JSON for inspection and plotting (Fig. 1 style).

Four additions to the paper's algorithm, documented in docs/multicontact.md:
no edge that removes the contact the parent edge just added (it undoes that
edge), a wall-clock budget (checked before every NLP; on expiry the search
stops with the deepest depth reached), a symmetry cut (the planar model's left
and right limbs are identical, so when a node's state and mode are left/right
symmetric, a neighbour that is the mirror image of one already tried is
skipped: same NLP up to relabelling), and an optional acceptance check of a
stabilising path (``check_plan``, the planner passes the knot-to-knot
re-simulation) before a node is declared terminal. Optionally (``release_alternatives``) a release is
also solved with a shorter T_max and kept as a second child of the same mode.

The frontier key is E_K(End(y_ij)) as line 20 writes it (for an added contact
the pre-impact energy; ``frontier_order='post_impact'`` is the departure that
keys on the energy after the impact map; 'mechanical', the planner's default,
'landing_first', 'capture' (a capture-point cost-to-go), ``lookahead`` and
``step_lookahead`` are departures that look past the edge, see ``search``), and
every landing gets a
``LandingReport`` (eq. 10): with ``landing_policy='rank_last'`` a node reached
through a landing beyond ``opt.cfg.landing_limits`` (and its subtree) is popped
after every node within the limits.
"""
from __future__ import annotations

import dataclasses
import heapq
import itertools
import time

import numpy as np

from humfall_ros.multicontact import contacts as C
from humfall_ros.multicontact.collocation import Segment, TrajectoryOptimizer
from humfall_ros.multicontact.landing import LandingReport, landing_report
from humfall_ros.multicontact.model import FEET, mirror_extremity
from humfall_ros.multicontact.modes import (
    Environment,
    Mode,
    adjacent_modes,
    is_foot_landing,
    make_mode,
    mode_label,
    one_foot_alone,
)


@dataclasses.dataclass
class TreeNode:
    id: int
    parent: int | None
    depth: int
    mode: Mode
    q: np.ndarray
    v: np.ndarray
    ke: float
    pre_impact_ke: float | None = None
    min_normal_impulse: float | None = None
    # N s, normal impulse the added extremity takes in the impact (eq. 10): what a hard landing costs the limb
    landing_impulse: float | None = None
    landing: LandingReport | None = None   # severity of the landing that created this node (eq. 10)
    # this node or an ancestor was reached through a landing beyond the limits
    over_limits: bool = False
    priority: float = float("nan")         # frontier key (J): see ``search``
    edge: Segment | None = None          # transition from the parent
    self_motion: Segment | None = None
    status: str = "frontier"             # frontier | expanded | terminal | unexpanded
    rejected: str | None = None          # why a stabilising self-motion was not accepted (re-simulation)
    children: list = dataclasses.field(default_factory=list)

    def to_dict(self, with_trajectories: bool = True) -> dict:
        d = {"id": self.id, "parent": self.parent, "depth": self.depth, "mode": mode_label(self.mode),
             "ke": self.ke, "pre_impact_ke": self.pre_impact_ke, "min_normal_impulse": self.min_normal_impulse,
             "landing_impulse": self.landing_impulse,
             "landing": self.landing.to_dict() if self.landing is not None else None,
             "over_limits": self.over_limits, "priority": self.priority,
             "status": self.status, "children": list(self.children), "rejected": self.rejected,
             "q": self.q.tolist(), "v": self.v.tolist()}
        for name, seg in (("edge", self.edge), ("self_motion", self.self_motion)):
            if seg is None:
                d[name] = None
            elif with_trajectories:
                d[name] = seg.to_dict()
            else:
                d[name] = {"success": seg.success, "final_ke": seg.final_ke, "nlp_time": seg.nlp_time,
                           "build_time": seg.build_time, "duration": float(seg.time[-1]), "status": seg.status}
        return d


@dataclasses.dataclass
class SearchResult:
    success: bool
    reason: str
    nodes: list[TreeNode]
    path: list[int]                       # node ids root..terminal (empty on failure)
    nlp_log: list[dict]                   # every NLP in call order
    total_time: float
    deepest_depth: int

    @property
    def contact_sequence(self) -> list[str]:
        return [mode_label(self.nodes[i].mode) for i in self.path]

    @property
    def node_ke(self) -> list[float]:
        return [self.nodes[i].ke for i in self.path]

    @property
    def final_ke(self) -> float:
        if not self.path:
            return float("nan")
        return self.nodes[self.path[-1]].self_motion.final_ke

    def landings(self) -> list[LandingReport]:
        """The landings along the solution path, in order (with their plan times)."""
        out, t = [], 0.0
        for i in self.path[1:]:
            n = self.nodes[i]
            t += float(n.edge.time[-1])
            if n.landing is not None:
                out.append(dataclasses.replace(n.landing, time=t))
        return out

    def segments(self) -> list[Segment]:
        """Transitions along the path, then the terminal self-motion."""
        segs = [self.nodes[i].edge for i in self.path[1:]]
        if self.path:
            segs.append(self.nodes[self.path[-1]].self_motion)
        return segs

    def tree_dict(self, with_trajectories: bool = False) -> dict:
        return {"success": self.success, "reason": self.reason, "path": self.path,
                "deepest_depth": self.deepest_depth, "total_time_s": self.total_time,
                "nodes": [n.to_dict(with_trajectories) for n in self.nodes], "nlp_log": self.nlp_log}


def _mirror_mode(mode: Mode) -> Mode:
    return make_mode(mirror_extremity(e) for e in mode)


FRONTIER_ORDERS = ("pre_impact", "post_impact", "mechanical", "landing_first", "capture")
LANDING_POLICIES = ("rank_last", "refuse", "ignore")   # a landing beyond the limits: last, dropped, or as any other


def capture_excess(model, q, v, mode: Mode, env: Environment) -> float:
    """How far (m) the instantaneous capture point (linear inverted pendulum, as
    ``collocation.capture_point``) lies outside the support of ``mode``: the
    x-interval spanned by its ground contact points (feet: toe and heel; hands on
    the ground). 0 when inside, or when a contact is on the wall (a wall takes
    horizontal momentum in its normal force, friction does not bound it)."""
    from humfall_ros.multicontact.collocation import capture_point
    xs = []
    for e in mode:
        if env.surface_of(e) == "wall":
            return 0.0
        pts = [f"{e}_toe", f"{e}_heel"] if e in FEET else [e]
        xs += [float(model.point(p, q)[0]) for p in pts]
    if not xs:
        return float("inf")
    cp = capture_point(model, q, v)
    return max(0.0, cp - max(xs), min(xs) - cp)


def capture_energy(model, q, v, mode: Mode, env: Environment) -> float:
    """Cost-to-go estimate (J) of a node: 1/2 M (g / z_com) s^2, s = ``capture_excess``:
    the kinetic energy of the capture point's excess velocity omega s of the linear
    inverted pendulum, i.e. what the node's support alone cannot take out (0 when the
    capture point is inside the support). Not in the paper (eq. 9 and Alg. 1 line 20
    look at the end of the edge only)."""
    s = capture_excess(model, q, v, mode, env)
    if not np.isfinite(s):
        return float("inf")
    z = max(float(model.com(q)[1]), 1e-3)
    return 0.5 * model.total_mass * 9.81 / z * s * s



def search(opt: TrajectoryOptimizer, q0, v0, mode0: Mode, env: Environment, *,
           eps_ke: float | None = None, max_depth: int = 4, time_budget: float = 60.0,
           symmetry_cut: bool = True, check_plan=None, frontier_order: str = "pre_impact",
           landing_policy: str = "rank_last", lookahead: bool = False,
           step_lookahead: bool = False, check_retry_seeds: bool = False,
           polish_acc_max: float = 0.0, max_nlps: int = 0,
           release_alternatives: tuple = (), single_foot_modes: bool = True,
           single_foot_terminal: bool = True, single_foot_t_max: float = 0.0) -> SearchResult:
    """Algorithm 1: grow the tree by least kinetic energy until a node's
    self-motion ends with E_K < eps_KE, the frontier empties or the budget ends.

    ``frontier_order``: 'pre_impact' ranks a child by E_K(End(y_ij)) as line 20
    does (for an added contact: the energy just before the impact);
    'post_impact' (departure) by the energy after the impact map (line 16).
    Departures that look past the edge (docs/multicontact.md, "Frontier keys"):
    'mechanical' adds the potential energy relative to the root,
    M g (z_com(End(y_ij)) - z_com(x_0)), to the line-20 key: the energy still in
    the robot, so a release that keeps the centre of mass high no longer ranks
    before a landing that has already converted its height; 'landing_first' pops
    every child reached by a landing within the limits before any release (then
    by the line-20 key). ``lookahead`` (departure) solves a child's self-motion
    (line 5) as soon as the child is made and keys it on E_K(End(y_self)), the
    energy its own stabilisation attempt ends with (a child whose self-motion
    failed ranks after every child whose converged); a child that stops within
    eps_KE is checked and returned at once.
    'capture' (departure, a cost-to-go estimate) adds ``capture_energy`` of the
    child's state (after the impact map for a landing) to the line-20 key: a
    release whose capture point has left the remaining foot ranks by the energy
    still in it plus what its support cannot catch, so at 30-50 J the release
    (the first half of a protective step) is popped before a hand landing that
    arrives with more energy than that.
    ``step_lookahead`` (departure): the lookahead for children reached by a foot
    landing only (the second half of a step is judged by whether the double
    support it makes can stop; eq. 9 on the landing edge alone puts the foot
    back where it was).
    ``landing_policy`` for a landing beyond ``opt.cfg.landing_limits``:
    'rank_last' (the node and its subtree are popped after every node within
    the limits), 'refuse' (the node is not added) or 'ignore'.
    ``check_plan(segments) -> reason | None``, when given, must accept the
    path's segments before a node is declared terminal; a rejected node is
    expanded like any other (its reason is kept in the node and the log).
    ``check_retry_seeds``: a stopping self-motion that the check rejects is solved
    again from the seeds after the ones it used (another local optimum of the same
    NLP; 40 J step, session 7: the first stop swung the free elbow so that tracking
    missed a knot by 0.13 > 0.1 rad); the node is terminal if that one stops and passes.
    ``polish_acc_max`` > 0 (departure, tried before ``check_retry_seeds``): a stopping
    self-motion that the check rejects is solved once more, warm from itself
    (``opt.warm_solve``), with its knot accelerations bounded by this value instead of
    ``acc_max``; the node is terminal if the polished one stops and passes. Why: the
    40 J step's stop flails the light arms (elbows 0 <-> -2.5 rad from knot to knot)
    in ways eq. 1-8 allow at 8 knots and the re-simulation does not reproduce; the
    same stop with |qddot| <= 100 at the knots passes (session 11).
    ``max_nlps`` > 0: a budget in NLP calls (each entry of the log: one line-5 or line-13
    optimisation with its seeds) besides ``time_budget``; unlike wall time it ends the search
    at the same node on any machine and load, so campaigns and tests that set it are
    reproducible (the search itself is deterministic for given NLP results).
    ``release_alternatives`` (departure, s): for each release (a transition that removes a
    contact) whose solution lasts longer than one of these, the release is solved again with that
    T_max and added as a second child of the same mode when it converges. Why: eq. 9 makes a
    release brake on both feet for as long as T allows (0.13-0.31 s from two feet), and from
    there the step that should follow is too late at 50 J; a release bounded at 0.1 s makes the
    step (session 28) but loses other plans (the 40 J step then lift). With both children the
    frontier decides (session 34).
    ``single_foot_modes`` false (ours, session 37): no transition ends with one foot alone in contact
    (``modes.one_foot_alone``); the root may start there. Fig. 2's whole mode graph is the paper's.
    ``single_foot_terminal`` false (ours, session 38): a node on one foot alone other than the root is
    passed through (a step's swing) but never solved for a stop nor accepted as the plan's end: a planar
    stop on one foot leaves a 3-D robot with its centre of mass between the feet, over nothing.
    ``single_foot_t_max`` > 0 (ours, session 38): the T_max of every transition out of a node on one foot
    alone other than the root (how long the plan stands on one foot: a swing, not a stance)."""
    if frontier_order not in FRONTIER_ORDERS:
        raise ValueError(f"frontier_order {frontier_order!r}: one of {', '.join(FRONTIER_ORDERS)}")
    if landing_policy not in LANDING_POLICIES:
        raise ValueError(f"landing_policy {landing_policy!r}: one of {', '.join(LANDING_POLICIES)}")
    limits = opt.cfg.landing_limits
    model = opt.model
    eps_ke = opt.cfg.eps_ke if eps_ke is None else eps_ke
    if max_nlps < 0:
        raise ValueError(f"max_nlps {max_nlps}: >= 0 (0: no NLP budget)")
    t0 = time.perf_counter()
    deadline = t0 + time_budget
    q0 = np.asarray(q0, float)
    v0 = np.asarray(v0, float)
    root = TreeNode(0, None, 0, tuple(mode0), q0, v0, model.kinetic_energy(q0, v0))
    root.priority = root.ke
    nodes = [root]
    counter = itertools.count()
    # (over the landing limits, class (landing_first: releases 1; lookahead: failed self-motion 1), key, tie, node)
    frontier = [(False, 0, root.ke, next(counter), 0)]
    z_root = float(model.com(q0)[1])
    g_mass = model.total_mass * 9.81
    log: list[dict] = []
    deepest = 0

    def nlps_spent() -> bool:
        return max_nlps > 0 and len(log) >= max_nlps

    def spent() -> bool:
        """The wall-time or NLP budget is used up."""
        return time.perf_counter() >= deadline or nlps_spent()

    def out_of_budget():
        if nlps_spent():
            return result(False, f"no solution within the budget of {max_nlps} NLPs "
                                 f"(deepest tree depth reached: {deepest})", [])
        return result(False, f"no solution within the time budget of {time_budget:.1f} s "
                             f"(deepest tree depth reached: {deepest})", [])

    def result(success, reason, path):
        for n in nodes:
            if n.status == "frontier" and n.self_motion is None and path and n.id not in path:
                n.status = "unexpanded"
        return SearchResult(success, reason, nodes, path, log, time.perf_counter() - t0, deepest)

    def record(kind, node, seg, target=None):
        log.append({"kind": kind, "node": node.id, "mode": mode_label(node.mode),
                    "target": mode_label(target) if target is not None else mode_label(node.mode),
                    "success": seg.success, "final_ke": seg.final_ke, "nlp_time": seg.nlp_time,
                    "build_time": seg.build_time, "cpu_time": seg.cpu_time, "iterations": seg.iterations,
                    "attempts": seg.attempts, "status": seg.status,
                    "objective": seg.objective, "attempt_log": seg.attempt_log})

    def path_to(d):
        path, i = [], d.id
        while i is not None:
            path.append(i)
            i = nodes[i].parent
        return path[::-1]

    def try_terminal(d) -> bool:
        """Lines 6-10 with the optional acceptance check; True: d is the solution."""
        y = d.self_motion
        if not (y.success and y.final_ke < eps_ke):
            return False
        path = path_to(d)
        rejected = None
        if check_plan is not None:
            rejected = check_plan([nodes[i].edge for i in path[1:]] + [y])
            log[-1]["plan_check"] = rejected or "passed"
        def accept(y2, key, value) -> bool:
            """Another self-motion for d after a rejection: terminal if it stops and passes the check."""
            record("self_motion", d, y2)
            log[-1][key] = value
            if not (y2.success and y2.final_ke < eps_ke):
                return False
            rejected2 = check_plan([nodes[i].edge for i in path[1:]] + [y2])
            log[-1]["plan_check"] = rejected2 or "passed"
            if rejected2 is not None:
                return False
            d.self_motion = y2
            d.status = "terminal"
            return True

        if rejected is not None and polish_acc_max > 0 and not spent():
            polished = opt.warm_solve(d.q, d.v, y, env, acc_max=polish_acc_max, multipliers=False)
            if accept(polished, "polish_acc_max", polish_acc_max):
                return True
        if rejected is not None and check_retry_seeds and not spent():
            try:
                y2 = opt.opt_self_motion(d.q, d.v, d.mode, env, deadline=deadline,
                                         skip_seeds=sum(1 for a in y.attempt_log if a.get("seed_T") != "warm"))
            except (TimeoutError, ValueError):
                y2 = None
            if y2 is not None and accept(y2, "check_retry", True):
                return True
        if rejected is None:
            d.status = "terminal"
            return True
        d.rejected = rejected
        return False

    def add_child(d, sigma_j, change, ext, y_ij):
        """Lines 14-20 for the transition y_ij from d (nothing when it did not converge); the result
        when the child's early self-motion (lookahead) is terminal, else None."""
        nonlocal deepest
        if not y_ij.success:
            return None
        qj, vj = y_ij.q[-1].copy(), y_ij.v[-1].copy()                       # line 15
        pre, min_imp, landing, rep = None, None, None, None
        if change == "add":                                                # line 16, eq. 10
            pre = model.kinetic_energy(qj, vj)
            rows = C.contact_rows(sigma_j, env)
            rep, _ = landing_report(model, qj, vj, sigma_j, ext, env, limits)
            vj, impulse = C.impact_map(model, qj, vj, rows)
            normals = [impulse[i] for i, r in enumerate(rows) if r.axis == "n"]
            min_imp = float(min(normals)) if normals else None
            landing = rep.normal_impulse
            if not rep.within_limits and landing_policy == "refuse":
                log[-1]["landing_refused"] = rep.exceeded
                return None
        ke_j = model.kinetic_energy(qj, vj)
        over = d.over_limits or (rep is not None and not rep.within_limits and landing_policy == "rank_last")
        key = ke_j if (pre is None or frontier_order == "post_impact") else pre      # line 20
        if frontier_order == "mechanical":
            key += g_mass * (float(model.com(qj)[1]) - z_root)
        elif frontier_order == "capture":
            key += capture_energy(model, qj, vj, sigma_j, env)
        cls = 1 if (frontier_order == "landing_first" and change == "remove") else 0
        child = TreeNode(len(nodes), d.id, d.depth + 1, sigma_j, qj, vj, ke_j,
                         pre_impact_ke=pre, min_normal_impulse=min_imp, landing_impulse=landing, edge=y_ij,
                         landing=rep, over_limits=over, priority=key)
        nodes.append(child)                                               # lines 17-19
        d.children.append(child.id)
        deepest = max(deepest, child.depth)
        early = lookahead or (step_lookahead and is_foot_landing(change, ext))
        if not single_foot_terminal and one_foot_alone(sigma_j):
            early = False   # never a stop on one foot alone: nothing to look ahead to
        if early and not child.over_limits and not spent():
            try:
                y_c = opt.opt_self_motion(qj, vj, sigma_j, env, deadline=deadline)   # line 5, early
            except TimeoutError:
                y_c = None
            if y_c is not None:
                child.self_motion = y_c
                record("self_motion", child, y_c)
                log[-1]["lookahead"] = True
                if try_terminal(child):
                    return result(True, f"stabilised at depth {child.depth}: final kinetic energy "
                                        f"{child.self_motion.final_ke:.3g} J < {eps_ke:g} J", path_to(child))
                if lookahead:
                    cls = 0 if y_c.success else 1
                    child.priority = key = y_c.final_ke if y_c.success else key
        heapq.heappush(frontier, (child.over_limits, cls, key, next(counter), child.id))   # line 20
        return None

    while frontier:
        if spent():
            return out_of_budget()
        *_, nid = heapq.heappop(frontier)
        d = nodes[nid]
        deepest = max(deepest, d.depth)
        # one foot alone after the push: with single_foot_terminal false passed through without a stop (a
        # swing), and with single_foot_t_max its transitions get that T_max
        swing_node = d.parent is not None and one_foot_alone(d.mode)
        if d.self_motion is None and not (swing_node and not single_foot_terminal):
            try:
                y = opt.opt_self_motion(d.q, d.v, d.mode, env, deadline=deadline)   # line 5
            except TimeoutError:
                continue
            d.self_motion = y
            record("self_motion", d, y)
            if try_terminal(d):                                                  # lines 6-10
                return result(True, f"stabilised at depth {d.depth}: final kinetic energy "
                                    f"{d.self_motion.final_ke:.3g} J < {eps_ke:g} J", path_to(d))
        d.status = "expanded"
        if d.depth >= max_depth:
            continue
        symmetric = symmetry_cut and model.is_symmetric(d.q, d.v) and _mirror_mode(d.mode) == d.mode
        tried: set = set()
        parent_mode = nodes[d.parent].mode if d.parent is not None else None
        bound = {"t_max": single_foot_t_max} if swing_node and single_foot_t_max > 0 else {}
        for sigma_j, change, ext in adjacent_modes(d.mode):                   # line 12
            if symmetric and _mirror_mode(sigma_j) in tried:
                continue
            if not single_foot_modes and one_foot_alone(sigma_j):
                continue
            if sigma_j == parent_mode and change == "remove":
                # removing the contact the parent edge just added undoes that
                # edge; landing a limb the parent edge released is a step
                # (the limb lands somewhere else) and is kept
                continue
            tried.add(sigma_j)
            if spent():
                break
            # a transition that cannot be as short as the swing's bound (a hand landing's T_min with a shorter
            # bound) is not tried
            if bound and single_foot_t_max < opt.cfg.t_min_of(change, ext):
                continue
            try:
                y_ij = opt.opt_transition_motion(d.q, d.v, d.mode, sigma_j, env, deadline=deadline,
                                                 **bound)   # line 13
            except TimeoutError:
                break
            record("transition", d, y_ij, sigma_j)
            found = add_child(d, sigma_j, change, ext, y_ij)
            if found is not None:
                return found
            if change != "remove" or not y_ij.success:
                continue
            for t_alt in release_alternatives:
                if float(y_ij.time[-1]) <= t_alt + 1e-3 or spent():
                    continue   # the release already ends within the bound: the same child
                try:
                    y_alt = opt.opt_transition_motion(d.q, d.v, d.mode, sigma_j, env, deadline=deadline,
                                                      release_t_max=t_alt, **bound)
                except TimeoutError:
                    break
                record("transition", d, y_alt, sigma_j)
                log[-1]["release_t_max"] = t_alt
                found = add_child(d, sigma_j, change, ext, y_alt)
                if found is not None:
                    return found
    if spent():   # the last NLPs were cut by the budget: not a complete search
        return out_of_budget()
    return result(False, f"no solution found: tree exhausted (deepest tree depth reached: {deepest})", [])
