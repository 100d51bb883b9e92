"""Planar model, impact map, seeds and request validation of the multi-contact
planner (paper 2). No ROS graph and no full NLP solve here."""
from __future__ import annotations

import math

import numpy as np
import pinocchio as pin
import pytest

from humfall_ros.multicontact import contacts as C
from humfall_ros.multicontact.collocation import OptConfig, StructureKey, TrajectoryOptimizer, hermite_mid
from humfall_ros.multicontact.initial_state import nominal_configuration, velocity_for_energy
from humfall_ros.multicontact.model import load_model
from humfall_ros.multicontact.modes import Environment, adjacent_modes, parse_mode, strategy_of
from humfall_ros.multicontact.planner import InvalidRequest, PlannerConfig, validate


@pytest.fixture(scope="module")
def model():
    return load_model()


def random_state(model, rng):
    q = np.zeros(model.n)
    q[:3] = rng.uniform([-0.5, 0.3, -1.0], [0.5, 1.2, 1.0])
    q[3:] = rng.uniform(model.q_min, model.q_max)
    v = rng.uniform(-3, 3, model.n)
    a = rng.uniform(-20, 20, model.n)
    return q, v, a


def test_planar_model_matches_table_one_and_urdf(model):
    assert (model.n, model.m) == (13, 10)
    assert model.coordinate_names[:3] == ["root_x", "root_z", "root_pitch"]
    # facts from the URDF through pinocchio, not literals of ours
    full = pin.buildModelFromUrdf(str(model.urdf))
    assert model.total_mass == pytest.approx(sum(i.mass for i in full.inertias), rel=1e-9)
    knee = full.getJointId("l_knee")
    i = model.joint_names.index("l_knee")
    assert model.q_max[i] == full.upperPositionLimit[full.joints[knee].idx_q]
    assert model.u_max[i] == full.effortLimit[full.joints[knee].idx_v]
    assert model.v_max[i] == full.velocityLimit[full.joints[knee].idx_v]


def test_casadi_dynamics_match_pinocchio(model):
    rng = np.random.default_rng(3)
    pm, pd = model.pin_model, model.pin_model.createData()
    for _ in range(10):
        q, v, a = random_state(model, rng)
        np.testing.assert_allclose(model.D(q), model.pin_crba(q), atol=1e-10)
        tau = np.array(model.f_id(q, v, a)).ravel()
        np.testing.assert_allclose(tau, model.pin_rnea(q, v, a), atol=1e-9)
        np.testing.assert_allclose(model.bias(q, v), pin.rnea(pm, pd, q, v, np.zeros(model.n)), atol=1e-9)
        pin.forwardKinematics(pm, pd, q, v, np.zeros(model.n))
        pin.computeJointJacobians(pm, pd, q)
        pin.updateFramePlacements(pm, pd)
        for point, frame in (("LH", "r_hand"), ("LF_toe", "l_sole_toe_right"), ("RF_heel", "r_sole_heel_left")):
            if point == "LH":
                frame = "l_hand"
            fid = pm.getFrameId(frame)
            np.testing.assert_allclose(model.point(point, q), pd.oMf[fid].translation[[0, 2]], atol=1e-12)
            J = pin.getFrameJacobian(pm, pd, fid, pin.LOCAL_WORLD_ALIGNED)
            np.testing.assert_allclose(model.point_jacobian(point, q), J[[0, 2]], atol=1e-12)
            acc = pin.getFrameClassicalAcceleration(pm, pd, fid, pin.LOCAL_WORLD_ALIGNED).linear
            np.testing.assert_allclose(np.array(model.f_point_dJv[point](q, v)).ravel(), acc[[0, 2]], atol=1e-9)


def test_modes_adjacency_and_parsing():
    assert parse_mode("RF/LF") == ("LF", "RF")
    with pytest.raises(ValueError, match="unknown extremity 'LK'"):
        parse_mode("LF/LK")
    adj = adjacent_modes(("LF", "RF"))
    assert {m for m, _, _ in adj} == {("LF", "RF", "LH"), ("LF", "RF", "RH"), ("LF",), ("RF",)}
    assert all(m for m, _, _ in adjacent_modes(("LF",)))  # never the empty mode


@pytest.mark.parametrize("sequence, name", [
    (["LF/RF"], "inertial shaping"),
    (["RF"], "inertial shaping"),
    (["LF/RF", "RF", "LF/RF"], "protective step"),            # from two feet: a release, then the landing
    (["RF", "LF/RF"], "protective step"),                     # from one foot (the paper's Figs. 1 and 3)
    (["LF/RF", "RF", "LF/RF", "LF"], "protective step"),      # a step, then the rear foot lifted
    (["LF/RF", "LF/RF/RH"], "hand contact"),
    (["LF/RF", "LF/RF/LH", "LF/RF/LH/RH"], "hand contact"),
    (["RF", "LF/RF", "LF/RF/LH"], "protective step + hand contact"),   # the paper's Fig. 1
    (["LF/RF", "RF"], "foot lifted"),                         # no new contact: not a step
    ([], "none"),
])
def test_strategy_names_a_contact_sequence_as_the_paper_does(sequence, name):
    assert strategy_of(sequence) == name


def test_impact_map_zeroes_contact_velocity_and_conserves_momentum(model):
    q = nominal_configuration(model)
    env = Environment()
    rng = np.random.default_rng(7)
    v_minus = rng.uniform(-1.5, 1.5, model.n)
    rows = C.contact_rows(("LF", "RF", "LH"), env)
    v_plus, impulse = C.impact_map(model, q, v_minus, rows)
    J = C.rows_jacobian(model, rows, q)
    D = model.D(q)
    np.testing.assert_allclose(J @ v_plus, 0.0, atol=1e-9)               # eq. 10, second row
    np.testing.assert_allclose(D @ (v_plus - v_minus), J.T @ impulse, atol=1e-9)  # eq. 10, first row
    assert model.kinetic_energy(q, v_plus) <= model.kinetic_energy(q, v_minus) + 1e-9  # inelastic


def test_initial_velocity_has_requested_energy_and_keeps_feet(model):
    q = nominal_configuration(model)
    env = Environment()
    mode = ("LF", "RF")
    for ke, direction in ((10.0, 1.0), (55.0, -1.0)):
        v = velocity_for_energy(model, q, mode, ke, direction, env)
        assert model.kinetic_energy(q, v) == pytest.approx(ke, rel=1e-9)
        J = C.rows_jacobian(model, C.contact_rows(mode, env), q)
        np.testing.assert_allclose(J @ v, 0.0, atol=1e-9)
        assert np.sign(v[0]) == direction  # trunk moves with the push
    pts = model.all_points(q)
    for p in ("LF_toe", "LF_heel", "RF_toe", "RF_heel"):
        assert abs(pts[p][1]) < 1e-12


def test_seed_satisfies_boundary_conditions(model):
    q0 = nominal_configuration(model)
    env = Environment()
    mode = ("LF", "RF")
    v0 = velocity_for_energy(model, q0, mode, 30.0, 1.0, env)
    opt = TrajectoryOptimizer(model, OptConfig())
    T = 1.0
    nlp, (t, q, v, a, u, lam), q_goal = opt.seed(q0, v0, mode, "add", "LH", env, T)
    assert t[0] == 0 and t[-1] == pytest.approx(T)
    np.testing.assert_allclose(q[0], q0, atol=1e-12)
    np.testing.assert_allclose(v[0], v0, atol=1e-12)
    np.testing.assert_allclose(q[-1], q_goal, atol=1e-9)
    # the goal is on the goal mode's manifold: hand on the ground, feet where they were
    assert abs(model.point("LH", q_goal)[1]) < 1e-5
    goal_rows = C.contact_rows(("LF", "RF"), env)
    np.testing.assert_allclose(C.rows_value(model, goal_rows, q_goal), C.rows_value(model, goal_rows, q0), atol=1e-5)
    assert np.all(q_goal[3:] >= model.q_min - 1e-6) and np.all(q_goal[3:] <= model.q_max + 1e-6)
    # u, lambda from the pseudo-inverse: eq. 1 holds at the knots up to the torque clipping
    for k in range(len(t)):
        J = C.rows_jacobian(model, nlp.rows, q[k])
        res = np.array(model.f_id(q[k], v[k], a[k])).ravel() - model.B @ u[k] - J.T @ lam[k]
        clipped = np.any(np.abs(u[k]) >= model.u_max - 1e-9)
        if not clipped:
            assert np.abs(res).max() < 1e-6
    # parabola: constant acceleration, q(T) from q0, v0 and a
    np.testing.assert_allclose(q[-1], q0 + v0 * T + 0.5 * a[0] * T**2, atol=1e-9)


def test_hermite_mid_point_formulas_exact_for_cubics():
    # q(t) = t^3 on [0, h]: the mid-point values of eq. 7 must be exact
    h = 0.3
    q0, q1 = 0.0, h**3
    v0, v1 = 0.0, 3 * h**2
    a0, a1 = 0.0, 6 * h
    q_mid, v_mid, a_mid, qdot_mid = hermite_mid(q0, v0, q1, v1, a0, a1, h)
    assert q_mid == pytest.approx((h / 2) ** 3)
    assert qdot_mid == pytest.approx(3 * (h / 2) ** 2)
    assert v_mid == pytest.approx(3 * (h / 2) ** 2)
    assert a_mid == pytest.approx(6 * h / 2)


# ------------------------------------------------------------ validation
def _req(**kw):
    r = {"q": [], "v": [], "kinetic_energy": 20.0, "direction": 1.0, "initial_mode": "LF/RF",
         "wall_distance": 0.0, "time_budget": 0.0}
    r.update(kw)
    return r


@pytest.mark.parametrize("change, match", [
    ({"kinetic_energy": float("nan")}, "kinetic_energy is not a finite"),
    ({"q": [0.0] * 12 + [float("inf")]}, "q contains a non-finite"),
    ({"q": [0.0] * 5}, "q has 5 entries, expected 13"),
    ({"v": [0.0] * 14}, "v has 14 entries"),
    ({"initial_mode": "LF/RK"}, "unknown extremity 'RK'"),
    ({"initial_mode": "LF/RF/LH"}, "does not match the configuration: LH"),
    ({"wall_distance": 0.1}, "wall .* inside the robot"),
    ({"kinetic_energy": 5000.0}, "exceeds the maximum"),
    ({"direction": 0.0}, "direction must be"),
    ({"time_budget": -1.0}, "time_budget must be >= 0"),
    ({"wall_distance": float("inf")}, "wall_distance is not a finite"),
])
def test_validation_rejects_bad_requests(model, change, match):
    with pytest.raises(InvalidRequest, match=match):
        validate(model, _req(**change), PlannerConfig())


def test_validation_rejects_bad_configurations(model):
    cfg = PlannerConfig()
    q = nominal_configuration(model)
    knee = model.q_index["l_knee"]
    bad = q.copy()
    bad[knee] = model.q_max[knee - 3] + 0.5
    with pytest.raises(InvalidRequest, match="outside joint limits: l_knee"):
        validate(model, _req(q=bad.tolist()), cfg)
    sunk = q.copy()
    sunk[1] -= 0.05
    with pytest.raises(InvalidRequest, match="penetrates the ground"):
        validate(model, _req(q=sunk.tolist()), cfg)
    lifted = q.copy()
    lifted[1] += 0.1
    with pytest.raises(InvalidRequest, match="does not match the configuration: LF"):
        validate(model, _req(q=lifted.tolist()), cfg)
    ahead = q.copy()
    ahead[0] += 2.0  # robot now stands beyond a wall at 0.8 m
    with pytest.raises(InvalidRequest, match="behind the robot"):
        validate(model, _req(q=ahead.tolist(), wall_distance=0.8), cfg)
    sliding = np.zeros(model.n)
    sliding[0] = 1.0  # the whole robot translating: feet slide
    with pytest.raises(InvalidRequest, match="moves the contacts"):
        validate(model, _req(q=q.tolist(), v=sliding.tolist()), cfg)
    ok = validate(model, _req(wall_distance=0.8), cfg)
    assert ok.env.wall_x == 0.8 and ok.mode == ("LF", "RF")
    assert model.kinetic_energy(ok.q, ok.v) == pytest.approx(20.0)
    assert math.isfinite(ok.time_budget) and ok.time_budget == cfg.time_budget


def test_transition_ke_cap_bounds_the_inner_knots_of_a_landing_only_when_asked(model):
    """transition_ke_cap_ratio (departure): rows KE(q_k, v_k) at the inner knots of a contact-adding
    transition, bounded above by ratio x the start energy; absent when 0 (the paper's NLP unchanged)."""
    q0 = nominal_configuration(model)
    env = Environment()
    v0 = velocity_for_energy(model, q0, ("LF", "RF"), 20.0, 1.0, env)
    ke0 = model.kinetic_energy(q0, v0)
    key = StructureKey("add", ("LF", "RF"), "LH", False, OptConfig().n_knots)
    off = TrajectoryOptimizer(model, OptConfig()).nlp(key)
    assert "ke_path" not in off._block_idx
    opt = TrajectoryOptimizer(model, OptConfig(transition_ke_cap_ratio=2.0))
    nlp, (t, q, v, a, u, lam), _ = opt.seed(q0, v0, ("LF", "RF"), "add", "LH", env, 0.8)
    idx = nlp._block_idx["ke_path"]
    assert len(idx) == nlp.key.n_knots - 2
    lbx, ubx, lbg, ubg = nlp.bounds(q0, v0, env)
    np.testing.assert_allclose(ubg[idx], 2.0 * ke0)
    assert np.all(np.isneginf(lbg[idx]))
    # the rows are the energies of the inner knots of a candidate
    g = np.array(nlp.f_g(nlp.pack(t[-1], q, v, a, u, lam))).ravel()
    np.testing.assert_allclose(g[idx], [model.kinetic_energy(q[k], v[k]) for k in range(1, nlp.key.n_knots - 1)],
                               rtol=1e-9, atol=1e-9)
    # a release has no landing to soften
    assert "ke_path" not in opt.nlp(StructureKey("remove", ("LF", "RF"), "LF", False, nlp.key.n_knots))._block_idx


def test_foot_cop_margin_keeps_each_sole_point_loaded_in_the_solved_stop(model):
    """foot_cop_margin (departure, session 26): rows lam_n(point) - r (lam_n(toe) + lam_n(heel)) >= 0 per foot and
    knot, absent when 0; a solved 10 J stop from two feet then has its centre of pressure inside the middle of each
    sole at every knot, which without the rows it is not (the plans ride the toe)."""
    from humfall_ros.multicontact import contacts as C

    q0 = nominal_configuration(model)
    env = Environment()
    v0 = velocity_for_energy(model, q0, ("LF", "RF"), 10.0, 1.0, env)
    key = StructureKey("", ("LF", "RF"), "", False, OptConfig().n_knots)
    assert "cop" not in TrajectoryOptimizer(model, OptConfig()).nlp(key)._block_idx
    r = 0.2
    opt = TrajectoryOptimizer(model, OptConfig(foot_cop_margin=r, nlp_max_wall_time=60.0))
    nlp = opt.nlp(key)
    assert len(nlp._block_idx["cop"]) == 2 * 2 * nlp.key.n_knots     # two feet, toe and heel, every knot
    lbx, ubx, lbg, ubg = nlp.bounds(q0, v0, env)
    assert np.all(lbg[nlp._block_idx["cop"]] == 0.0) and np.all(np.isposinf(ubg[nlp._block_idx["cop"]]))

    def worst_share(seg):
        shares = []
        for _, ni in C.friction_groups(seg.rows):
            fn = seg.lam[:, ni]
            shares.append((fn.min(axis=1) / np.maximum(fn.sum(axis=1), 1e-9)).min())
        return min(shares)

    seg = opt.opt_self_motion(q0, v0, ("LF", "RF"), env)
    assert seg.success, seg.status
    assert worst_share(seg) >= r - 1e-3
    free = TrajectoryOptimizer(model, OptConfig(nlp_max_wall_time=60.0)).opt_self_motion(q0, v0, ("LF", "RF"), env)
    assert free.success and worst_share(free) < r


def test_post_impact_speed_fraction_scales_the_eq6_bounds_of_the_impact_state_only(model):
    """post_impact_speed_fraction (departure when < 1, session 26): the post-impact joint velocities of a landing are
    bounded by the fraction x the URDF limits; the knots keep eq. 6 as it is."""
    q0 = nominal_configuration(model)
    env = Environment()
    v0 = velocity_for_energy(model, q0, ("LF", "RF"), 20.0, 1.0, env)
    key = StructureKey("add", ("LF", "RF"), "LH", False, OptConfig().n_knots)
    full = TrajectoryOptimizer(model, OptConfig()).nlp(key)
    part = TrajectoryOptimizer(model, OptConfig(post_impact_speed_fraction=0.5)).nlp(key)
    n = model.n
    oi = 1 + key.n_knots * full.nk            # the impact variables: post-impact velocities first
    lf, uf = full.bounds(q0, v0, env)[:2]
    lp, up = part.bounds(q0, v0, env)[:2]
    np.testing.assert_allclose(uf[oi + 3:oi + n], model.v_max)
    np.testing.assert_allclose(up[oi + 3:oi + n], 0.5 * np.asarray(model.v_max))
    np.testing.assert_allclose(lp[oi + 3:oi + n], -0.5 * np.asarray(model.v_max))
    a, b = full.knot_slices[2]
    np.testing.assert_array_equal(up[a:b], uf[a:b])             # a knot's bounds unchanged


@pytest.mark.parametrize("limbs, scaled", [("all", {"LH", "LF"}), ("feet", {"LF"}), ("hands", {"LH"})])
def test_post_impact_speed_fraction_limbs_picks_the_landings_it_bounds(model, limbs, scaled):
    """post_impact_speed_fraction_limbs (session 30): the fraction bounds the post-impact velocities of the landings
    of the named limbs only; the others keep eq. 6's URDF limits."""
    q0 = nominal_configuration(model)
    env = Environment()
    cfg = OptConfig(post_impact_speed_fraction=0.5, post_impact_speed_fraction_limbs=limbs)
    n = model.n
    for mode, limb in ((("LF", "RF"), "LH"), (("RF",), "LF")):
        v0 = velocity_for_energy(model, q0, mode, 20.0, 1.0, env)
        nlp = TrajectoryOptimizer(model, cfg).nlp(StructureKey("add", mode, limb, False, cfg.n_knots))
        oi = 1 + cfg.n_knots * nlp.nk
        ub = nlp.bounds(q0, v0, env)[1]
        expected = 0.5 if limb in scaled else 1.0
        np.testing.assert_allclose(ub[oi + 3:oi + n], expected * np.asarray(model.v_max), err_msg=f"{limbs} {limb}")
    with pytest.raises(ValueError, match="post_impact_speed_fraction_limbs"):
        OptConfig(post_impact_speed_fraction_limbs="arms")
