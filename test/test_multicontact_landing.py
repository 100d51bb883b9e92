"""Landing severity (eq. 10), the planner's configuration from its one declaration,
and the tree's frontier rules (paper 2, Alg. 1 line 20; landing limits). No NLP solve."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import sympy as sp

from humfall_ros import params
from humfall_ros.multicontact import contacts as C
from humfall_ros.multicontact import tree as tree_mod
from humfall_ros.multicontact.collocation import OptConfig, Segment
from humfall_ros.multicontact.initial_state import nominal_configuration
from humfall_ros.multicontact.landing import LandingLimits, landing_report
from humfall_ros.multicontact.model import load_model
from humfall_ros.multicontact.modes import Environment, mode_label
from humfall_ros.multicontact.planner import (
    FallPlanner,
    PlannerConfig,
    configs_from_params,
)


@pytest.fixture(scope="module")
def model():
    return load_model()


def test_absorbed_energy_of_the_plastic_impact_is_half_the_velocity_jump_in_the_inertia_metric():
    """Derive with sympy what eq. 10 implies: with D (v+ - v-) = J^T L and J v+ = 0,
    E(v-) - E(v+) = 1/2 (v- - v+)^T D (v- - v+) >= 0 (whatever the sign of L)."""
    n = 4
    Ds = sp.Matrix(n, n, lambda i, j: sp.Symbol(f"d{min(i, j)}{max(i, j)}"))   # symmetric
    vp = sp.Matrix(sp.symbols(f"vp0:{n}"))
    dv = sp.Matrix(sp.symbols(f"dv0:{n}"))          # v- - v+
    vm = vp + dv
    energy = lambda x: (x.T * Ds * x)[0] / 2        # noqa: E731
    gap = sp.expand(energy(vm) - energy(vp) - energy(dv))
    # the gap is the cross term dv^T D v+ ...
    assert sp.expand(gap - (dv.T * Ds * vp)[0]) == 0
    # ... = (D dv)^T v+ = -(J^T L)^T v+ (first row of eq. 10) = -L J v+, zero by the second row
    J = sp.Matrix(1, n, sp.symbols(f"j0:{n}"))
    L = sp.Symbol("L")
    cross = (-(J.T * L)).T * vp
    vp_on = sp.solve((J * vp)[0], vp[0], dict=True)[0]   # J v+ = 0
    assert sp.simplify(cross[0].subs(vp_on)) == 0


def _landing_state(model, env, speed):
    """Nominal stance, RF on the ground, LF at touchdown with its faster point coming down at ``speed``."""
    q = nominal_configuration(model)
    v = np.random.default_rng(4).normal(0, 0.5, model.n)
    v, _ = C.impact_map(model, q, v, C.contact_rows(("RF",), env))     # the stance foot stays put
    vz = min(model.point_jacobian(p, q)[1] @ v for p in ("LF_toe", "LF_heel"))
    if vz >= 0:
        v, vz = -v, -max(model.point_jacobian(p, q)[1] @ v for p in ("LF_toe", "LF_heel"))
    return q, v * (speed / -vz)


def test_landing_report_is_eq10_and_flags_limits(model):
    env = Environment()
    q, v = _landing_state(model, env, 1.2)
    limits = LandingLimits(foot_normal_speed_max=1.0, foot_energy_max=1e6)
    rep, v_plus = landing_report(model, q, v, ("LF", "RF"), "LF", env, limits)
    rows = C.contact_rows(("LF", "RF"), env)
    J = C.rows_jacobian(model, rows, q)
    np.testing.assert_allclose(J @ v_plus, 0.0, atol=1e-9)                   # eq. 10: contacts stop
    assert rep.limb == "LF" and rep.surface == "ground"
    assert rep.normal_speed == pytest.approx(1.2, rel=1e-9)                    # the faster of toe and heel
    assert rep.pre_impact_ke == pytest.approx(model.kinetic_energy(q, v))
    assert rep.post_impact_ke == pytest.approx(model.kinetic_energy(q, v_plus))
    dv = v - v_plus
    assert rep.absorbed_energy == pytest.approx(0.5 * dv @ model.D(q) @ dv, rel=1e-8)   # the identity above
    assert rep.absorbed_energy > 0 and rep.normal_impulse > 0
    assert not rep.within_limits and "touchdown speed 1.20 m/s > 1 m/s" in rep.exceeded
    half = LandingLimits(foot_normal_speed_max=1.5, foot_energy_max=0.5 * rep.absorbed_energy)
    rep2, _ = landing_report(model, q, v, ("LF", "RF"), "LF", env, half)
    assert not rep2.within_limits and "absorbed energy" in rep2.exceeded and "touchdown" not in rep2.exceeded
    rep3, _ = landing_report(model, q, v, ("LF", "RF"), "LF", env, LandingLimits(1.0, 1.5, 1.0, 1e6))
    assert rep3.within_limits and rep3.exceeded == ""    # a foot is judged by the foot limits, not the hand's
    at = LandingLimits(foot_normal_speed_max=rep.normal_speed - 1e-8, foot_energy_max=1e6)
    assert landing_report(model, q, v, ("LF", "RF"), "LF", env, at)[0].within_limits   # at the limit (NLP tolerance)
    over = LandingLimits(foot_normal_speed_max=rep.normal_speed - 1e-3, foot_energy_max=1e6)
    assert not landing_report(model, q, v, ("LF", "RF"), "LF", env, over)[0].within_limits


def test_planner_is_built_from_its_one_declaration():
    decl = params.defaults("multicontact_planner")
    opt, cfg = configs_from_params(decl)
    for name, value in decl.items():
        if name in {f.name for f in dataclasses.fields(OptConfig)}:
            got = getattr(opt, name)
            want = tuple(value) if isinstance(value, list) else value
            if name == "release_seed_durations":
                want = tuple(x for x in value if x > 0)
            if name == "step_seed_capture_offset" and not decl["step_seed_at_capture_point"]:
                assert np.isnan(got)
                continue
            assert got == want, name
        elif name in {f.name for f in dataclasses.fields(PlannerConfig)}:
            want = tuple(sorted(x for x in value if x > 0)) if name == "release_alternatives" else value
            assert getattr(cfg, name) == want, name
    assert opt.transition_objective == "pre_impact"   # the paper
    assert cfg.frontier_order == "capture"   # departure from Alg. 1 line 20 (docs/multicontact.md, session 11)
    assert opt.landing_limits.hand_normal_speed_max == decl["landing_hand_normal_speed_max"]
    assert cfg.stance["knee"] == decl["stance_knee"]
    # the dataclass defaults do not drift from the declaration (nlp_max_wall_time was 20 s vs 10 s)
    for f in dataclasses.fields(OptConfig):
        if f.name in decl and f.name not in ("release_seed_durations", "step_seed_capture_offset"):
            want = tuple(decl[f.name]) if isinstance(decl[f.name], list) else decl[f.name]
            assert getattr(OptConfig(), f.name) == want, f.name


def test_loaders_refuse_unknown_keys():
    with pytest.raises(ValueError, match="unknown"):
        OptConfig.from_params({"n_knots": 8, "impact_dissipation_weight": 0.0})
    with pytest.raises(ValueError, match="unknown"):
        PlannerConfig.from_params({"max_depth": 2, "bogus": 1})
    with pytest.raises(ValueError, match="unknown"):
        configs_from_params({**params.defaults("multicontact_planner"), "not_a_parameter": 1})
    with pytest.raises(ValueError, match="no parameters"):
        FallPlanner.from_params(not_a_parameter=1)
    with pytest.raises(ValueError, match="transition_objective"):
        OptConfig(transition_objective="post")


# --------------------------------------------------------------- tree ordering
class _FakeOpt:
    """Stands in for TrajectoryOptimizer: every self-motion fails except at a chosen
    mode; every transition converges to a fixed state (the nominal stance with a
    downward hand velocity), so the tree's own bookkeeping is what is tested."""

    def __init__(self, model, limits, stop_at, pre_ke_of):
        self.model = model
        self.cfg = dataclasses.replace(OptConfig(), landing_limits=limits)
        self.stop_at = stop_at
        self.pre_ke_of = pre_ke_of
        self.popped = []

    def _seg(self, q, v, mode, target, change, ext, ok, ke_end):
        N = 3
        qs, vs = np.tile(q, (N, 1)), np.tile(v, (N, 1))
        ke = np.array([1.0, 1.0, ke_end])
        return Segment(kind="transition" if change else "self_motion", mode=mode, target_mode=target,
                       change=change, extremity=ext, time=np.linspace(0, 0.3, N), q=qs, v=vs, a=0 * qs,
                       u=np.zeros((N, self.model.m)), lam=np.zeros((N, 0)), rows=[], ke=ke, success=ok,
                       status="fake", iterations=1, nlp_time=0.0, seed_duration=0.3, attempts=1, max_violation=0.0)

    def opt_self_motion(self, q0, v0, mode, env, deadline=None):
        self.popped.append(mode_label(mode))
        ok = mode_label(mode) in self.stop_at
        return self._seg(q0, v0, mode, mode, "", "", True, 0.0 if ok else 5.0)

    def opt_transition_motion(self, q0, v0, mode, target, env, deadline=None):
        ext = (set(target) ^ set(mode)).pop()
        change = "add" if ext in target else "remove"
        if change == "remove":
            return self._seg(q0, v0, mode, target, change, ext, False, 0.0)
        q = nominal_configuration(self.model)
        v = np.zeros(self.model.n)
        v[1] = -1.0   # the whole robot coming down at 1 m/s: hand touchdown speed 1 m/s
        v *= np.sqrt(self.pre_ke_of[ext] / self.model.kinetic_energy(q, v))
        return self._seg(q, v, mode, target, change, ext, True, 0.0)


def test_frontier_ranks_landings_beyond_the_limits_last(model, monkeypatch):
    """Two hand landings: LH arrives with less energy but beyond the touchdown limit,
    RH with more but within it. rank_last pops RH first (and stops there); ignore
    pops LH first (least pre-impact energy, Alg. 1 line 20); refuse drops LH."""
    monkeypatch.setattr(tree_mod, "mirror_extremity", lambda e: e)   # no symmetry cut between LH and RH
    env = Environment()
    q0 = nominal_configuration(model)
    v0 = np.zeros(model.n)
    pre = {"LH": 20.0, "RH": 30.0}
    limits = LandingLimits()
    results = {}
    for policy in ("rank_last", "ignore", "refuse"):
        fake = _FakeOpt(model, limits, stop_at={"LF/RF/LH", "LF/RF/RH"}, pre_ke_of=pre)
        real = tree_mod.landing_report

        def flagged(model_, q, v, target, limb, env_, lim, time=float("nan"), real=real):
            rep, vp = real(model_, q, v, target, limb, env_, lim, time)
            if limb == "LH":
                rep = dataclasses.replace(rep, within_limits=False, exceeded="test: LH beyond its limit")
            return rep, vp
        monkeypatch.setattr(tree_mod, "landing_report", flagged)
        res = tree_mod.search(fake, q0, v0, ("LF", "RF"), env, time_budget=30.0, landing_policy=policy,
                              check_plan=None)
        monkeypatch.setattr(tree_mod, "landing_report", real)
        results[policy] = (res, fake.popped)
    res, popped = results["rank_last"]
    assert res.success and res.contact_sequence == ["LF/RF", "LF/RF/RH"], popped
    assert popped[:2] == ["LF/RF", "LF/RF/RH"]
    assert res.landings()[0].limb == "RH" and res.landings()[0].time == pytest.approx(0.3)
    lh = [n for n in res.nodes if n.landing is not None and n.landing.limb == "LH"]
    assert lh and lh[0].over_limits and lh[0].priority == pytest.approx(20.0)   # pre-impact key (line 20)
    res, popped = results["ignore"]
    assert res.contact_sequence == ["LF/RF", "LF/RF/LH"] and popped[:2] == ["LF/RF", "LF/RF/LH"]
    res, popped = results["refuse"]
    assert res.contact_sequence == ["LF/RF", "LF/RF/RH"]
    assert not any(n.landing is not None and n.landing.limb == "LH" for n in res.nodes)
    assert any(e.get("landing_refused") for e in res.nlp_log)


class _KeyOpt(_FakeOpt):
    """A release (RF stays) that keeps the start state, and a hand landing whose state has
    the centre of mass 0.3 m lower and arrives with more energy than the release keeps: the
    line-20 key pops the release first, the departures that look past the edge the landing."""

    def opt_transition_motion(self, q0, v0, mode, target, env, deadline=None):
        ext = (set(target) ^ set(mode)).pop()
        change = "add" if ext in target else "remove"
        q = np.array(q0, float)
        v = np.array(v0, float)
        if change == "add":
            q[1] -= 0.3                       # root (hence CoM) 0.3 m lower: height converted
            v = v * np.sqrt(self.pre_ke_of[ext] / self.model.kinetic_energy(q, v))
        return self._seg(q, v, mode, target, change, ext, True, self.model.kinetic_energy(q, v))


@pytest.mark.parametrize("order,lookahead,first", [("pre_impact", False, "RF"), ("mechanical", False, "LF/RF/LH"),
                                                   ("landing_first", False, "LF/RF/LH"),
                                                   ("pre_impact", True, "LF/RF/LH")])
def test_frontier_keys_that_look_past_the_edge_pop_the_landing_before_the_release(model, order, lookahead, first):
    env = Environment()
    q0 = nominal_configuration(model)
    v0 = np.zeros(model.n)
    v0[0] = 1.0                               # forward, 0.5 M J
    v0 *= np.sqrt(20.0 / model.kinetic_energy(q0, v0))
    fake = _KeyOpt(model, LandingLimits(hand_normal_speed_max=1e9, foot_normal_speed_max=1e9,
                                        hand_energy_max=1e9, foot_energy_max=1e9),
                   stop_at=set(), pre_ke_of={"LH": 40.0, "RH": 40.0, "LF": 40.0, "RF": 40.0})
    if lookahead:    # self-motions: the landing's ends lower than the release's
        base = fake.opt_self_motion

        def sm(q, v, mode, env_, deadline=None):
            seg = base(q, v, mode, env_, deadline)
            seg.ke[-1] = 3.0 if "LH" in mode_label(mode) else 30.0
            return seg
        fake.opt_self_motion = sm
    res = tree_mod.search(fake, q0, v0, ("LF", "RF"), env, time_budget=30.0, max_depth=2,
                          frontier_order=order, lookahead=lookahead, landing_policy="ignore")
    assert not res.success
    expanded = [e["mode"] for e in res.nlp_log if e["kind"] == "transition" and e["node"] != 0]
    assert expanded[0] == first, expanded   # the first child popped is the first one expanded
    if order == "mechanical":
        land = next(n for n in res.nodes if n.landing is not None)
        dz = model.com(land.q)[1] - model.com(q0)[1]
        assert land.priority == pytest.approx(land.pre_impact_ke + model.total_mass * 9.81 * dz)
