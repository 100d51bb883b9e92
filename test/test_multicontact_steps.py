"""Protective steps with the paper's objective (issue 14, session 7): the capture-point
cost-to-go in the frontier key (``frontier_order: capture``), the soft capture-point
terminal cost of a foot landing (``step_capture_weight``), the step lookahead
(``frontier_lookahead_steps``), and a real 30 J plan that steps."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from humfall_ros.multicontact import tree as tree_mod
from humfall_ros.multicontact.collocation import OptConfig, TrajectoryOptimizer, capture_point
from humfall_ros.multicontact.initial_state import nominal_configuration, velocity_for_energy
from humfall_ros.multicontact.landing import LandingLimits
from humfall_ros.multicontact.model import load_model
from humfall_ros.multicontact.modes import Environment, mode_label
from humfall_ros.multicontact.planner import FallPlanner, library_path

from test_multicontact_landing import _FakeOpt

# the options session 7's step plans use (docs/multicontact.md, "Session 7: protective steps"); the
# declared defaults since session 11 (checked below), with the polish of a rejected stop; releases from 0.05 s
# since session 35 (0.1 s before); the capture cost's weight 6000 and 450 IPOPT iterations since session 36 (2000 /
# 600 before)
STEP_OPTIONS = {"frontier_order": "capture", "frontier_lookahead_steps": True, "step_capture_weight": 6000.0,
                "step_capture_margin": 0.12, "release_t_min": 0.05, "max_iter": 450, "step_t_min": 0.15}


@pytest.fixture(scope="module")
def model():
    return load_model()


def _pushed(model, ke, mode=("LF", "RF")):
    q = nominal_configuration(model)
    return q, velocity_for_energy(model, q, mode, ke, 1.0, Environment())


def test_capture_energy_is_zero_inside_the_support_and_the_pendulum_energy_outside(model):
    env = Environment()
    q, v = _pushed(model, 30.0)
    toe = model.point("LF_toe", q)[0]
    cp = capture_point(model, q, v)
    assert cp > toe                                  # a 30 J push: the capture point has left the feet
    s = tree_mod.capture_excess(model, q, v, ("LF", "RF"), env)
    assert s == pytest.approx(cp - toe)
    z = model.com(q)[1]
    assert tree_mod.capture_energy(model, q, v, ("LF", "RF"), env) == pytest.approx(
        0.5 * model.total_mass * 9.81 / z * s * s)
    q10, v10 = _pushed(model, 1.0)                   # a small push stays inside
    assert tree_mod.capture_excess(model, q10, v10, ("LF", "RF"), env) == 0.0
    assert tree_mod.capture_energy(model, q, 0 * v, ("RF",), env) == 0.0   # at rest over the foot
    # a hand on the wall takes horizontal momentum in its normal force: no excess
    assert tree_mod.capture_excess(model, q, v, ("LF", "RF", "LH"), Environment(0.8)) == 0.0


class _StepOpt(_FakeOpt):
    """A release keeps the state; a foot landing moves the robot 0.3 m forward (the step);
    a hand landing arrives with 40 J and the centre of mass 0.3 m lower. Only a double
    support that has stepped stops."""

    def __init__(self, model, q0):
        big = 1e9
        super().__init__(model, LandingLimits(big, big, big, big), stop_at=set(),
                         pre_ke_of={"LH": 40.0, "RH": 40.0})
        self.q0 = np.array(q0, float)

    def opt_self_motion(self, q0, v0, mode, env, deadline=None):
        self.popped.append(mode_label(mode))
        stepped = mode_label(mode) == "LF/RF" and q0[0] > self.q0[0] + 0.1
        return self._seg(q0, v0, mode, mode, "", "", True, 0.0 if stepped else 5.0)

    def opt_transition_motion(self, q0, v0, mode, target, env, deadline=None):
        ext = (set(target) ^ set(mode)).pop()
        change = "add" if ext in target else "remove"
        q, v = np.array(q0, float), np.array(v0, float)
        if change == "add" and ext in ("LF", "RF"):
            q[0] += 0.3
            v = 0 * v
        elif change == "add":
            q[1] -= 0.3
            v = v * math.sqrt(self.pre_ke_of[ext] / self.model.kinetic_energy(q, v))
        return self._seg(q, v, mode, target, change, ext, True, self.model.kinetic_energy(q, v))


@pytest.mark.parametrize("order", ["pre_impact", "mechanical", "capture"])
def test_capture_key_ranks_a_release_by_what_its_support_cannot_catch(model, order):
    """'capture' keys the release on its energy plus the capture-point energy of its one
    foot (the key is checked against ``capture_energy``); with that key the release of a
    30 J push is still popped before a hand landing that arrives with 40 J, as with the
    paper's key, and unlike 'mechanical' (which pops the landing: the centre of mass is
    not lower after a release)."""
    env = Environment()
    q0, v0 = _pushed(model, 30.0)
    fake = _StepOpt(model, q0)
    res = tree_mod.search(fake, q0, v0, ("LF", "RF"), env, time_budget=30.0, max_depth=1,
                          frontier_order=order, landing_policy="ignore")
    rel = next(n for n in res.nodes if mode_label(n.mode) in ("RF", "LF"))
    extra = tree_mod.capture_energy(model, rel.q, rel.v, rel.mode, env)
    assert extra > 0.0
    if order == "capture":
        assert rel.priority == pytest.approx(rel.ke + extra)
    popped = fake.popped[1]
    assert popped == ("LF/RF/LH" if order == "mechanical" else mode_label(rel.mode)), fake.popped


@pytest.mark.parametrize("step_lookahead", [False, True])
def test_step_lookahead_returns_a_stepped_double_support_as_soon_as_it_is_made(model, step_lookahead):
    env = Environment()
    q0, v0 = _pushed(model, 30.0)
    fake = _StepOpt(model, q0)
    res = tree_mod.search(fake, q0, v0, ("LF", "RF"), env, time_budget=30.0, max_depth=2,
                          frontier_order="capture", landing_policy="ignore", step_lookahead=step_lookahead)
    assert res.success and res.contact_sequence[1] in ("RF", "LF") and res.contact_sequence[-1] == "LF/RF"
    trans = [e for e in res.nlp_log if e["kind"] == "transition"]
    step = next(i for i, e in enumerate(trans) if e["target"] == "LF/RF")
    if step_lookahead:   # solved and returned before the release's other children are tried
        assert step == len(trans) - 1 and res.nlp_log[-1].get("lookahead")
    else:                # the search tries the release's hand landings first, then pops the step
        assert step < len(trans) - 1 and not res.nlp_log[-1].get("lookahead")


def test_soft_capture_cost_of_a_foot_landing(model):
    """``step_capture_weight`` adds two slacks (forward, backward) to a foot landing's NLP,
    rows toe - cp + s_f >= margin (forward push; the backward row unbounded), s >= 0,
    and w (s_f^2 + s_b^2) to the objective; no slack without the weight, none on a hand."""
    env = Environment()
    w_cap, margin = 1000.0, 0.05
    opt = TrajectoryOptimizer(model, OptConfig(step_capture_weight=w_cap, step_capture_margin=margin))
    nlp, _ = opt.structures(("RF",), "add", "LF", env)
    assert nlp.n_cap == 2
    q0, v0 = _pushed(model, 30.0)
    lbx, ubx, lbg, ubg = nlp.bounds(q0, v0, env)
    idx = nlp._block_idx["capture_soft"]
    assert lbg[idx][0] == pytest.approx(margin) and lbg[idx][1] == -np.inf and np.all(ubg[idx] == np.inf)
    oc = nlp.nw - 2
    assert np.all(lbx[oc:] == 0.0) and np.all(ubx[oc:] == np.inf)
    w = np.zeros(nlp.nw)
    w[oc:] = (0.1, 0.2)
    assert float(nlp.f_cap_cost(w, nlp.parameters())) == pytest.approx(w_cap * (0.01 + 0.04))
    # the weight is the NLP's parameter: another weight in the same structure (a library re-plan's)
    assert float(nlp.f_cap_cost(w, nlp.parameters(3000.0))) == pytest.approx(3000.0 * (0.01 + 0.04))
    with pytest.raises(ValueError):
        nlp.parameters(float("nan"))
    hand, _ = opt.structures(("LF", "RF"), "add", "LH", env)
    assert hand.n_cap == 0 and "capture_soft" not in hand._block_idx
    plain = TrajectoryOptimizer(model, OptConfig(step_capture_weight=0.0))
    foot, _ = plain.structures(("RF",), "add", "LF", env)
    assert foot.n_cap == 0 and "capture_soft" not in foot._block_idx


@pytest.fixture(scope="module")
def plan30():
    planner = FallPlanner.from_params(**STEP_OPTIONS)
    return planner, planner.plan({"kinetic_energy": 30.0, "direction": 1.0, "time_budget": 120.0})


def test_30J_paper_objective_takes_a_protective_step(plan30):
    """The paper's ladder at 30 J (Sec. IV-B): a protective step, with the paper's
    transition objective (pre-impact KE) and the step options: release one foot, land it
    ahead of the capture point with no more energy than the push gave, stop in the new
    double support."""
    planner, r = plan30
    assert r["success"], r["reason"]
    seq = r["contact_sequence"]
    assert seq[0] == "LF/RF" and seq[1] in ("LF", "RF") and seq[2] == "LF/RF" and len(seq) == 3, seq
    assert r["final_ke"] < planner.opt.cfg.eps_ke
    assert planner.opt.cfg.transition_objective == "pre_impact"
    (land,) = r["landings"]
    assert land.limb in ("LF", "RF") and land.within_limits
    assert land.normal_speed <= planner.opt.cfg.landing_limits.foot_normal_speed_max + 1e-4
    # issue 14's goal, met at 30 J since releases start at 0.05 s (session 35: 28.7 J; 32.0 J from 0.1 s)
    assert land.pre_impact_ke <= 30.0, land.pre_impact_ke
    step = r["segments"][1]   # the landing edge: the stepped foot ends ahead of where it started
    ext = land.limb
    x0 = planner.model.point(f"{ext}_toe", step.q[0])[0]
    x1 = planner.model.point(f"{ext}_toe", step.q[-1])[0]
    assert x1 - x0 > 0.3, (x0, x1)
    # the swing's duration is the NLP's choice, not its bound (session 37: Table I's 0.25 s held every step of
    # 20-50 J at T = 0.25 s exactly; with step_t_min 0.15 the 30 J swing ends between the two)
    assert planner.opt.cfg.step_t_min + 0.01 < step.time[-1] < planner.opt.cfg.t_min - 0.01, step.time[-1]


def test_seed_durations_skip_starts_after_the_seeds_already_used():
    cfg = OptConfig()
    full = cfg.seed_durations()
    assert len(full) == cfg.max_seed_attempts
    after = cfg.seed_durations(skip=2)
    grid = np.linspace(cfg.t_min, cfg.t_max, cfg.n_seed_durations)
    snap = [float(grid[int(np.argmin(np.abs(grid - d)))]) for d in cfg.seed_retry_durations[1:]]
    assert after == pytest.approx(snap[:cfg.max_seed_attempts]) and after[0] == pytest.approx(full[2])
    assert cfg.seed_durations(skip=99) == []


class _RetryOpt(_StepOpt):
    """The stepped double support stops; ``skip_seeds`` marks which solve it is."""

    def __init__(self, model, q0):
        super().__init__(model, q0)
        self.skips = []

    def opt_self_motion(self, q0, v0, mode, env, deadline=None, skip_seeds=0):
        seg = super().opt_self_motion(q0, v0, mode, env, deadline)
        seg.attempt_log = [{"seed_T": 0.8}, {"seed_T": 0.5}]
        seg.seed_duration = 100.0 + skip_seeds     # tells the check which solve it sees
        self.skips.append(skip_seeds)
        return seg


@pytest.mark.parametrize("retry", [False, True])
def test_check_retry_seeds_solves_a_rejected_stop_again_from_the_next_seeds(model, retry):
    env = Environment()
    q0, v0 = _pushed(model, 30.0)
    fake = _RetryOpt(model, q0)

    def check(segments):   # rejects the first stop, accepts one solved after skipping seeds
        return None if segments[-1].seed_duration > 100.0 else "test: first stop rejected"
    res = tree_mod.search(fake, q0, v0, ("LF", "RF"), env, time_budget=30.0, max_depth=2,
                          frontier_order="capture", landing_policy="ignore", step_lookahead=True,
                          check_plan=check, check_retry_seeds=retry)
    if retry:
        assert res.success and res.contact_sequence[-1] == "LF/RF"
        assert fake.skips[-1] == 2                   # after the two seeds the first solve logged
        assert res.segments()[-1].seed_duration == 102.0
        assert res.nlp_log[-1].get("check_retry") and res.nlp_log[-1]["plan_check"] == "passed"
    else:
        assert not res.success and 2 not in fake.skips
        assert any(n.rejected for n in res.nodes)


class _PolishOpt(_StepOpt):
    """The stepped double support stops; ``warm_solve`` returns a copy of the stop marked
    with the acceleration bound it was given (and whether it still stops)."""

    def __init__(self, model, q0, polished_stops=True):
        super().__init__(model, q0)
        self.warm_calls = []
        self.polished_stops = polished_stops

    def warm_solve(self, q0, v0, guess, env, acc_max=None, multipliers=None):
        # the polish changes the bounds, so the rejected stop's multipliers must not be used
        assert multipliers is False
        self.warm_calls.append(acc_max)
        ke = guess.ke.copy()
        ke[-1] = 0.0 if self.polished_stops else 1.0
        return dataclasses.replace(guess, ke=ke, seed_duration=-float(acc_max))


@pytest.mark.parametrize("polish,polished_stops", [(0.0, True), (100.0, True), (100.0, False)])
def test_polish_re_solves_a_rejected_stop_with_bounded_accelerations(model, polish, polished_stops):
    """``polish_acc_max``: a stop that the check rejects is re-solved warm from itself with
    that acceleration bound; the node is terminal only if the polished solve still stops
    and passes the check, and its self-motion is then the polished one."""
    env = Environment()
    q0, v0 = _pushed(model, 30.0)
    fake = _PolishOpt(model, q0, polished_stops)
    seen = []

    def check(segments):   # rejects any stop that was not polished with a bound <= 150
        seen.append(segments[-1].seed_duration)
        return None if -150.0 <= segments[-1].seed_duration < 0 else "test: flailing arms"
    res = tree_mod.search(fake, q0, v0, ("LF", "RF"), env, time_budget=30.0, max_depth=2,
                          frontier_order="capture", landing_policy="ignore", step_lookahead=True,
                          check_plan=check, polish_acc_max=polish)
    if polish > 0:
        assert fake.warm_calls and set(fake.warm_calls) == {polish}
        assert any(e.get("polish_acc_max") == polish for e in res.nlp_log)
    else:
        assert not fake.warm_calls
    if polish > 0 and polished_stops:
        assert res.success and res.contact_sequence[-1] == "LF/RF"
        assert res.segments()[-1].seed_duration == -polish and res.final_ke == 0.0
        assert res.nlp_log[-1]["plan_check"] == "passed"
    else:
        assert not res.success and any(n.rejected for n in res.nodes)
        if polish > 0:   # the polished solve ended above eps_KE: never checked
            assert all(s > 0 for s in seen)


def test_polish_bound_replaces_acc_max_in_the_nlp_bounds(model):
    """``warm_solve(acc_max=)`` reaches the knot-acceleration bounds of the cached NLP."""
    env = Environment()
    opt = TrajectoryOptimizer(model, OptConfig())
    nlp, _ = opt.structures(("LF", "RF"), "", "", env)
    q0, v0 = _pushed(model, 10.0)
    n = model.n
    o = nlp.knot_slices[1][0]
    for acc, want in ((None, opt.cfg.acc_max), (100.0, 100.0), (0.0, opt.cfg.acc_max)):
        lbx, ubx, *_ = nlp.bounds(q0, v0, env, acc_max=acc)
        assert np.all(ubx[o + 2 * n:o + 3 * n] == want) and np.all(lbx[o + 2 * n:o + 3 * n] == -want)


def test_release_t_max_bounds_only_a_release_and_its_seeds(model):
    """``release_t_max`` is the duration bound of a transition that removes a contact (NLP variable T and the
    seed grid); landings and self-motions keep their T_min and t_max; 0 leaves every transition at t_max (the paper)."""
    env = Environment()
    q0, v0 = _pushed(model, 30.0)
    bounded = OptConfig(release_t_max=0.15)
    opt = TrajectoryOptimizer(model, bounded)
    release, _ = opt.structures(("LF", "RF"), "remove", "LF", env)
    lbx, ubx, *_ = release.bounds(q0, v0, env)
    assert (lbx[0], ubx[0]) == (pytest.approx(bounded.release_t_min), pytest.approx(0.15))
    assert all(bounded.release_t_min - 1e-12 <= d <= 0.15 + 1e-12 for d in bounded.seed_durations("remove"))
    for mode, change, ext, t_min in ((("RF",), "add", "LF", bounded.step_t_min), (("LF", "RF"), "", "", bounded.t_min)):
        nlp, _ = opt.structures(mode, change, ext, env)
        lbx, ubx, *_ = nlp.bounds(q0, v0, env)
        assert (lbx[0], ubx[0]) == (pytest.approx(t_min), pytest.approx(bounded.t_max))
    assert max(bounded.seed_durations("add")) > 0.15
    # a bound below the release's T_min is raised to it (an empty interval would make every release infeasible)
    assert OptConfig(release_t_max=0.01).t_max_of("remove") == pytest.approx(OptConfig().release_t_min)
    assert OptConfig().t_max_of("remove") == OptConfig().t_max


def test_step_t_min_bounds_only_a_foot_landing_and_its_seed_grid(model):
    """``step_t_min`` (session 37) is the shortest foot landing (a step's swing: the NLP variable T and the seed
    grid); a hand landing, a release and a self-motion keep their own T_min; 0 gives the foot landing Table I's
    t_min back (the paper)."""
    env = Environment()
    q0, v0 = _pushed(model, 30.0)
    cfg = OptConfig(step_t_min=0.12)
    assert cfg.step_t_min < cfg.t_min and cfg.release_t_min != cfg.step_t_min
    opt = TrajectoryOptimizer(model, cfg)
    for mode, change, ext, t_min in ((("RF",), "add", "LF", 0.12), (("LF", "RF"), "add", "LH", cfg.t_min),
                                     (("LF", "RF"), "remove", "LF", cfg.release_t_min),
                                     (("LF", "RF"), "", "", cfg.t_min)):
        assert cfg.t_min_of(change, ext) == pytest.approx(t_min), (change, ext)
        nlp, _ = opt.structures(mode, change, ext, env)
        lbx, ubx, *_ = nlp.bounds(q0, v0, env)
        assert (lbx[0], ubx[0]) == (pytest.approx(t_min), pytest.approx(cfg.t_max)), (change, ext)
    feet = cfg.seed_durations("add", extremity="LF")
    hands = cfg.seed_durations("add", extremity="LH")
    assert min(feet) >= 0.12 - 1e-12 and feet != hands     # the foot's grid starts at its own T_min
    assert hands == OptConfig(step_t_min=0.0).seed_durations("add", extremity="LH")
    with pytest.raises(ValueError, match="step_t_min"):   # an empty interval is refused, not planned into
        OptConfig(step_t_min=4.0, t_max=3.5)
    # 0: Table I's T_min for every landing, feet included
    paper = OptConfig(step_t_min=0.0)
    assert paper.t_min_of("add", "LF") == paper.t_min_of("add", "LH") == paper.t_min
    assert paper.seed_durations("add", extremity="LF") == paper.seed_durations("add", extremity="LH")


def test_the_step_options_and_the_polish_are_the_declared_defaults():
    """Session 11: the step options of session 7 and the polish of a rejected stop are the
    planner's defaults (departures from the paper, listed in docs/multicontact.md); the
    transition objective stays the paper's."""
    planner = FallPlanner.from_params()
    opt, cfg = planner.opt.cfg, planner.cfg
    for name, value in STEP_OPTIONS.items():
        assert getattr(opt, name, getattr(cfg, name, None)) == value, name
    assert cfg.check_polish_acc_max > 0 and cfg.check_polish_acc_max < opt.acc_max
    assert opt.transition_objective == "pre_impact"


def test_40J_search_expands_the_short_release_before_the_hand_and_lands_a_step_within_limits():
    """Sec. IV-B puts 40 J among the protective steps. With the defaults (paper objective, step
    options, polish, the short-release alternative), on a budget of 7 NLPs (``max_nlps``: the same tree on
    any machine): the root has a hand landing and, per released foot, two releases of the same mode: eq. 9's
    (braking on both feet beyond T_min) and the one bounded at T_min, 0.05 s (``release_alternatives``, sessions 34-35).
    The short release is expanded before the hand landing, which lands harder than the released foot; the
    released foot lands ahead (> 0.3 m) within the limits, and the stop of that double support is tried at
    once (step lookahead). When the stop converges and passes the check, the plan is the step:
    LF/RF -> foot -> LF/RF, final KE < eps_KE, and it passes the re-simulation check again here.

    Why not always the plan: whether a stop converges within IPOPT's iterations can depend on rounding
    (session 14: the 40 J step of the defaults then, after a long release, ended at max_iter on one machine and
    converged on another). Until that is settled this test asserts what every machine reproduces and the plan
    where it is found."""
    planner = FallPlanner.from_params(max_nlps=7, nlp_max_wall_time=60.0)
    (bound,) = planner.cfg.release_alternatives
    assert bound == pytest.approx(planner.opt.cfg.release_t_min)   # session 35: the short release lasts T_min
    r = planner.plan({"kinetic_energy": 40.0, "direction": 1.0, "time_budget": 600.0})
    res = r["search"]
    nodes = res.nodes
    root = nodes[0]
    releases = [nodes[c] for c in root.children if len(nodes[c].mode) == 1]
    hand = [nodes[c] for c in root.children if len(nodes[c].mode) == 3]
    assert len(releases) == 2 and len(hand) == 1, [nodes[c].mode for c in root.children]
    assert releases[0].mode == releases[1].mode
    (hand,) = hand
    durations = [float(n.edge.time[-1]) for n in releases]
    assert durations[0] > bound + 1e-3 and durations[1] <= bound + 1e-6, durations   # eq. 9's, then the bounded one
    release = releases[1]
    # a node on one foot alone is stopped (a self-motion tried) only where a plan may end there: not with the
    # defaults since session 40 (single_foot_terminal false), where it is a swing expanded at once
    assert release.status in ("expanded", "terminal")
    assert (release.self_motion is not None) == planner.cfg.single_foot_terminal
    # the hand landing is not expanded before the release (whether it is over the limits or just at the hand's
    # touchdown-speed bound depends on where the NLP stops: session 19's machine met the bound, 1.5000000143 m/s)
    assert hand.self_motion is None and hand.landing is not None
    steps = [nodes[c] for c in release.children if nodes[c].mode == ("LF", "RF")]
    assert len(steps) == 1, [nodes[c].mode for c in release.children]
    (step,) = steps
    assert step.landing is not None and step.landing.within_limits, step.landing
    # ... and it is the harder landing: the hand comes down faster than the released foot
    assert hand.landing.normal_speed > step.landing.normal_speed, (hand.landing, step.landing)
    limb = step.landing.limb
    assert limb in ("LF", "RF") and (limb,) != release.mode
    moved = (planner.model.point(f"{limb}_toe", step.edge.q[-1])[0]
             - planner.model.point(f"{limb}_toe", release.edge.q[0])[0])
    assert moved > 0.3, moved
    lookahead = [e for e in res.nlp_log if e["node"] == step.id and e["kind"] == "self_motion"]
    assert lookahead and lookahead[0].get("lookahead"), lookahead
    assert r["nlp_count"] <= 7
    if not r["success"]:
        assert "budget of 7 NLPs" in r["reason"] or "exhausted" in r["reason"], r["reason"]
        return
    assert r["contact_sequence"] == ["LF/RF", mode_label(release.mode), "LF/RF"], r["contact_sequence"]
    assert r["final_ke"] < planner.opt.cfg.eps_ke
    assert r["landings_within_limits"]
    from humfall_ros.multicontact.resim import plan_check
    c = planner.cfg
    assert plan_check(planner.model, r["segments"], r["env"], c.check_q_error_max, c.check_force_error_max_mg,
                      c.check_feedback_omega, c.check_feedback_max) is None


def test_an_nlp_budget_ends_the_search_at_the_same_node_and_says_so(model):
    """``max_nlps``: the search stops after that many NLP calls with a reason naming the budget,
    and a larger budget continues the same tree (the first calls are the same ones)."""
    opt = TrajectoryOptimizer(model, OptConfig())
    q0, v0 = _pushed(model, 40.0)
    env = Environment()
    small = tree_mod.search(opt, q0, v0, ("LF", "RF"), env, max_nlps=2, time_budget=600.0)
    assert not small.success and "budget of 2 NLPs" in small.reason, small.reason
    assert len(small.nlp_log) == 2
    larger = tree_mod.search(opt, q0, v0, ("LF", "RF"), env, max_nlps=3, time_budget=600.0)
    assert len(larger.nlp_log) == 3
    for a, b in zip(small.nlp_log, larger.nlp_log):
        assert (a["kind"], a["node"], a["target"], a["iterations"]) == (b["kind"], b["node"], b["target"],
                                                                        b["iterations"])
    with pytest.raises(ValueError):
        tree_mod.search(opt, q0, v0, ("LF", "RF"), env, max_nlps=-1)


class _LateReleaseOpt(_FakeOpt):
    """A release as eq. 9 makes it: it brakes for 0.3 s unless bounded, and from there the step is too late
    (the stepped double support cannot stop); a release bounded at <= 0.15 s leaves a state from which the
    step stops. Hand landings do not converge. Records every release's T_max."""

    def __init__(self, model):
        big = 1e9
        super().__init__(model, LandingLimits(big, big, big, big), stop_at=set(), pre_ke_of={})
        self.release_bounds = []

    def opt_self_motion(self, q0, v0, mode, env, deadline=None):
        self.popped.append(mode_label(mode))
        early = q0[2] > 0.5          # marks a state that came through the short release
        stops = mode_label(mode) == "LF/RF" and early and q0[0] > 0.1
        return self._seg(q0, v0, mode, mode, "", "", True, 0.0 if stops else 5.0)

    def opt_transition_motion(self, q0, v0, mode, target, env, deadline=None, release_t_max=None):
        ext = (set(target) ^ set(mode)).pop()
        change = "add" if ext in target else "remove"
        q, v = np.array(q0, float), np.array(v0, float)
        if change == "remove":
            self.release_bounds.append(release_t_max)
            seg = self._seg(q, v, mode, target, change, ext, True, 5.0)
            T = 0.3 if release_t_max is None else min(0.3, release_t_max)
            seg.time = np.linspace(0.0, T, len(seg.time))
            if T <= 0.15:
                seg.q[-1, 2] = 1.0
            return seg
        if ext not in ("LF", "RF"):
            return self._seg(q, v, mode, target, change, ext, False, 5.0)
        q[0] += 0.3
        return self._seg(q, 0 * v, mode, target, change, ext, True, 0.0)


@pytest.mark.parametrize("alternatives", [(), (0.1,), (0.5,)])
def test_release_alternatives_add_a_short_release_child_the_frontier_can_take(model, alternatives):
    """``release_alternatives`` (session 34): a release that lasts longer than a bound is solved again with
    that T_max and kept as a second child of the same mode. Without it (or with a bound the release already
    meets: no second NLP) the late step cannot stop and the tree is exhausted; with 0.1 s the step after the
    short release stops."""
    q0, v0 = _pushed(model, 30.0)
    q0 = q0.copy()
    q0[2] = 0.0
    fake = _LateReleaseOpt(model)
    res = tree_mod.search(fake, q0, v0, ("LF", "RF"), Environment(), time_budget=30.0, max_depth=2,
                          frontier_order="capture", landing_policy="ignore", step_lookahead=True,
                          symmetry_cut=False, release_alternatives=alternatives)
    shorts = [b for b in fake.release_bounds if b is not None]
    if alternatives == (0.1,):
        assert shorts == [0.1, 0.1], fake.release_bounds          # one per released foot
        assert res.success, res.reason
        released = res.nodes[res.path[1]]
        assert float(released.edge.time[-1]) == pytest.approx(0.1)
        assert res.contact_sequence[-1] == "LF/RF"
        assert [e.get("release_t_max") for e in res.nlp_log if e["kind"] == "transition"
                and e["target"] in ("LF", "RF")].count(0.1) == 2
        # both releases of each foot are children of the root, with the same mode
        modes = [mode_label(res.nodes[c].mode) for c in res.nodes[0].children]
        assert modes.count("LF") == 2 and modes.count("RF") == 2, modes
    else:
        assert shorts == [], fake.release_bounds
        assert not res.success and "exhausted" in res.reason, res.reason


def test_a_release_t_max_override_bounds_one_release_solve(model):
    """``opt_transition_motion(release_t_max=)``: that solve's T and its recorded bounds are the release's
    [release_t_min, bound], the optimizer's configuration is unchanged, and a landing refuses the override."""
    opt = TrajectoryOptimizer(model, OptConfig())
    q0, v0 = _pushed(model, 30.0)
    env = Environment()
    seg = opt.opt_transition_motion(q0, v0, ("LF", "RF"), ("RF",), env, release_t_max=0.12)
    assert seg.t_bounds == (pytest.approx(opt.cfg.release_t_min), pytest.approx(0.12))
    assert opt.cfg.release_t_min - 1e-6 <= float(seg.time[-1]) <= 0.12 + 1e-6   # IPOPT relaxes bounds by ~1e-8
    assert all(a["seed_T"] <= 0.12 + 1e-9 for a in seg.attempt_log)
    assert opt.cfg.release_t_max == 0.0
    with pytest.raises(ValueError, match="release"):
        opt.opt_transition_motion(q0, v0, ("RF",), ("LF", "RF"), env, release_t_max=0.12)


def test_one_foot_alone_names_the_supports_without_a_lateral_base():
    from humfall_ros.multicontact.modes import one_foot_alone, parse_mode
    assert one_foot_alone(parse_mode("LF")) and one_foot_alone(parse_mode("RF"))
    for label in ("LF/RF", "LH", "RF/LH", "LF/RF/LH", "LH/RH"):
        assert not one_foot_alone(parse_mode(label)), label


def test_without_single_foot_modes_the_20J_push_lands_a_hand_and_no_node_stands_on_one_foot(plan30):
    """``single_foot_modes`` false (session 37): the search never makes a node on one foot alone. At 20 J the
    defaults step (through one foot); without those modes the plan lands a hand within the limits and stops,
    which the 3-D robot executes at rest (docs/multicontact.md "Session 37")."""
    from humfall_ros.multicontact.modes import one_foot_alone, parse_mode
    planner = FallPlanner.from_params(single_foot_modes=False)
    assert planner.cfg.single_foot_modes is False and FallPlanner.from_params().cfg.single_foot_modes is True
    r = planner.plan({"kinetic_energy": 20.0, "direction": 1.0, "time_budget": 120.0})
    assert r["success"], r["reason"]
    assert not any(one_foot_alone(n.mode) for n in r["search"].nodes), [n.mode for n in r["search"].nodes]
    final = parse_mode(r["contact_sequence"][-1])
    assert {"LF", "RF"} <= set(final) and set(final) & {"LH", "RH"}, r["contact_sequence"]
    assert r["final_ke"] < planner.opt.cfg.eps_ke
    assert r["landings_within_limits"] and all(x.pre_impact_ke <= 20.0 * 1.1 for x in r["landings"])
    # the same push with the whole mode graph passes through one foot (a step or a foot lifted)
    _, r30 = plan30
    assert any(one_foot_alone(parse_mode(m)) for m in r30["contact_sequence"]), r30["contact_sequence"]


def test_a_library_without_single_foot_modes_keeps_the_entries_that_never_stand_on_one_foot():
    from humfall_ros.multicontact.modes import one_foot_alone, parse_mode
    full = FallPlanner.from_params(library_file="multicontact_library/standing_pushes.json.gz").library
    planner = FallPlanner.from_params(library_file="multicontact_library/standing_pushes.json.gz",
                                      single_foot_modes=False)

    def stands_on_one_foot(e):
        return any(one_foot_alone(parse_mode(m)) for m in e.contact_sequence[1:])

    kept = planner.library.entries
    assert kept and all(not stands_on_one_foot(e) for e in kept)
    assert len(kept) == sum(not stands_on_one_foot(e) for e in full.entries) < len(full.entries)
    assert planner.library.built_with == full.built_with


class _OneFootStopOpt(_FakeOpt):
    """A stop is possible on one foot alone and, after a step, on both feet; the bounds the tree passes to
    each transition are recorded. Releases from one foot and hand landings do not converge."""

    def __init__(self, model):
        big = 1e9
        super().__init__(model, LandingLimits(big, big, big, big), stop_at=set(), pre_ke_of={})
        self.t_max_of = []

    def opt_self_motion(self, q0, v0, mode, env, deadline=None):
        label = mode_label(mode)
        self.popped.append(label)
        stops = label in ("LF", "RF") or (label == "LF/RF" and q0[0] > 0.1)
        return self._seg(q0, v0, mode, mode, "", "", True, 0.0 if stops else 5.0)

    def opt_transition_motion(self, q0, v0, mode, target, env, deadline=None, **bounds):
        ext = (set(target) ^ set(mode)).pop()
        change = "add" if ext in target else "remove"
        self.t_max_of.append((mode_label(mode), mode_label(target), bounds.get("t_max")))
        q, v = np.array(q0, float), np.array(v0, float)
        if change == "remove":
            return self._seg(q, v, mode, target, change, ext, len(mode) > 1, 5.0)
        if ext not in ("LF", "RF"):
            return self._seg(q, v, mode, target, change, ext, False, 5.0)
        q[0] += 0.3
        return self._seg(q, 0 * v, mode, target, change, ext, True, 0.0)


@pytest.mark.parametrize("terminal, t_max", [(True, 0.0), (False, 0.4), (False, 0.2)])
def test_single_foot_terminal_false_passes_through_one_foot_but_never_ends_there(model, terminal, t_max):
    """``single_foot_terminal`` (session 38): with the whole mode graph a released foot's node that stops on
    the other foot ends the plan; with false that node is never solved for a stop (no line-5 NLP), only
    expanded, and the plan ends on both feet after the step. ``single_foot_t_max`` bounds the transitions
    out of that node only, not the root's; a hand landing, whose T_min (Table I's 0.25 s) exceeds a 0.2 s
    bound, is not tried from there."""
    q0, v0 = _pushed(model, 30.0)
    fake = _OneFootStopOpt(model)
    res = tree_mod.search(fake, q0, v0, ("LF", "RF"), Environment(), time_budget=30.0, max_depth=2,
                          landing_policy="ignore", symmetry_cut=False, single_foot_terminal=terminal,
                          single_foot_t_max=t_max)
    assert res.success, res.reason
    if terminal:
        assert res.contact_sequence[-1] in ("LF", "RF"), res.contact_sequence
        assert all(b is None for *_, b in fake.t_max_of)
    else:
        assert res.contact_sequence[-1] == "LF/RF" and len(res.contact_sequence) == 3, res.contact_sequence
        assert "LF" not in fake.popped and "RF" not in fake.popped, fake.popped
        out_of_one_foot = [b for m, _, b in fake.t_max_of if m in ("LF", "RF")]
        assert out_of_one_foot and all(b == t_max for b in out_of_one_foot), fake.t_max_of
        assert all(b is None for m, _, b in fake.t_max_of if m == "LF/RF"), fake.t_max_of
        hands_from_one_foot = [t for m, t, _ in fake.t_max_of if m in ("LF", "RF") and ("LH" in t or "RH" in t)]
        assert bool(hands_from_one_foot) == (t_max >= fake.cfg.t_min), fake.t_max_of


def test_a_transition_t_max_override_bounds_one_solve_and_is_refused_below_its_t_min(model):
    """``opt_transition_motion(t_max=)`` (the tree's ``single_foot_t_max``): a step's landing from one foot is
    solved within [step_t_min, t_max] and records those bounds; the configuration is unchanged; a bound below
    the transition's T_min is refused rather than solved empty."""
    opt = TrajectoryOptimizer(model, OptConfig())
    q0, v0 = _pushed(model, 30.0, mode=("RF",))
    env = Environment()
    seg = opt.opt_transition_motion(q0, v0, ("RF",), ("LF", "RF"), env, t_max=0.3)
    assert seg.t_bounds == (pytest.approx(opt.cfg.step_t_min), pytest.approx(0.3))
    assert float(seg.time[-1]) <= 0.3 + 1e-6 and all(a["seed_T"] <= 0.3 + 1e-9 for a in seg.attempt_log)
    assert opt.cfg.t_max > 0.3
    with pytest.raises(ValueError, match="T_min"):
        opt.opt_transition_motion(q0, v0, ("RF",), ("LF", "RF"), env, t_max=opt.cfg.step_t_min / 2)
    with pytest.raises(ValueError, match="T_min"):   # a hand landing keeps Table I's T_min
        opt.opt_transition_motion(q0, v0, ("RF",), ("RF", "LH"), env, t_max=opt.cfg.t_min - 0.01)


def test_a_library_without_single_foot_ends_drops_the_entries_that_end_on_one_foot(tmp_path):
    """The planner's defaults since session 40 (``single_foot_terminal`` false) drop library entries whose plan ends
    on one foot alone and keep the ones that only pass through it (steps); the paper's setting keeps them all.
    The shipped library has no such end since session 40 (built with the option), so a library is made here with
    entries cut after the step's release (the plan then ends on the stance foot)."""
    from humfall_ros.multicontact.library import LibraryEntry, PlanLibrary
    from humfall_ros.multicontact.modes import one_foot_alone, parse_mode
    shipped = PlanLibrary.load(library_path("multicontact_library/standing_pushes.json.gz"))
    assert FallPlanner.from_params().cfg.single_foot_terminal is False
    assert not any(one_foot_alone(parse_mode(e.contact_sequence[-1])) for e in shipped.entries)
    steps = [e for e in shipped.entries if e.wall_distance == 0 and len(e.contact_sequence) == 3
             and one_foot_alone(parse_mode(e.contact_sequence[1]))][:3]
    assert steps
    cut = [LibraryEntry(e.kinetic_energy + 0.1, e.direction, e.wall_distance, e.contact_sequence[:2],
                        e.segments[:1]) for e in steps]
    path = tmp_path / "lib.json.gz"
    PlanLibrary(shipped.entries + cut, shipped.built_with).save(path)
    full = FallPlanner.from_params(library_file=str(path), single_foot_terminal=True).library
    kept = FallPlanner.from_params(library_file=str(path)).library.entries
    assert len(full.entries) == len(shipped.entries) + len(cut)
    assert len(kept) == len(shipped.entries) and not any(one_foot_alone(parse_mode(e.contact_sequence[-1]))
                                                         for e in kept)
    # entries that pass through one foot (steps) are kept
    assert any(one_foot_alone(parse_mode(m)) for e in kept for m in e.contact_sequence[1:-1])