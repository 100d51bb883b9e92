"""Paper 3's state-space models (humfall_ros/estop/statespace.py): derivations, closed forms, gains, limits."""
from __future__ import annotations

import math

import numpy as np
import pytest
import sympy as sp
from scipy.integrate import solve_ivp
from scipy.signal import place_poles

from humfall_ros.estop.statespace import (
    MajorAxisModel,
    MinorAxisModel,
    StateSpaceError,
    fit_zmp_lag,
    lipm_zmp,
    lqr_poles,
    omega_of_height,
    return_home,
    solve_major,
    stop_duration_within_limits,
    supremum_two_modes,
)

s, wf, wc = sp.symbols("s omega_f omega_c", positive=True)
k1, k2, k3 = sp.symbols("k1 k2 k3")


def _minor_symbolic():
    """Eq. 1-4 from scratch: pbar' = wf (p - pbar), p = x - xdd / wc^2, u = xdd = -k . state."""
    pbar, x, xd, u = sp.symbols("pbar x xd u")
    p = x - u / wc ** 2
    rhs = sp.Matrix([wf * (p - pbar), xd, u])
    state = sp.Matrix([pbar, x, xd])
    A = rhs.jacobian(state)
    B = rhs.jacobian(sp.Matrix([u]))
    K = sp.Matrix([[k1, k2, k3]])
    M = s * sp.eye(3) - (A - B * K)
    return A, B, M.det(), M.adjugate()


def _poly_coeffs(expr, degree):
    poly = sp.Poly(sp.expand(expr), s)
    c = [float(v) for v in poly.all_coeffs()]
    return np.array([0.0] * (degree + 1 - len(c)) + c)


def test_minor_axis_eq5_to_7_derived_symbolically():
    A, B, D, adj = _minor_symbolic()
    rng = np.random.default_rng(1)
    for _ in range(5):
        vals = {wf: rng.uniform(8, 60), wc: rng.uniform(2.5, 5), k1: rng.normal(0, 50), k2: rng.normal(0, 50),
                k3: rng.normal(0, 20)}
        model = MinorAxisModel(float(vals[wc]), float(vals[wf]))
        np.testing.assert_allclose(np.array(A.subs(vals), float), model.A, atol=1e-12)
        np.testing.assert_allclose(np.array(B.subs(vals), float), model.B, atol=1e-12)
        k = [float(vals[k1]), float(vals[k2]), float(vals[k3])]
        np.testing.assert_allclose(_poly_coeffs(D.subs(vals), 3), model.characteristic(k), rtol=1e-10, atol=1e-9)
        state0 = rng.normal(size=3)
        num = model.numerators(k, state0)
        derived = adj.subs(vals) * sp.Matrix(state0)
        for row in range(3):
            np.testing.assert_allclose(_poly_coeffs(derived[row], 2), num[row], rtol=1e-10, atol=1e-9)
    # the printed eq. 7 does not follow: C_x4 is -k_x1 (printed +k_x1), C_x5's s term has the other sign
    assert sp.simplify(adj[1, 0] + k1) == 0
    printed_cx5 = s ** 2 + (wf * k1 / wc ** 2 - k3 - wf) * s + k3 * wf
    assert sp.simplify(sp.expand(adj[1, 1] - printed_cx5)) != 0


def test_major_axis_eq13_to_15_and_eq19_20_derived_symbolically():
    r, yd, u, y0, v0 = sp.symbols("r yd u y0 v0")
    ky1, ky2 = sp.symbols("ky1 ky2")
    # eq. 8-9 from eq. 2: r = y - pbar, r' = yd - wf (y - u/wc^2 - pbar)
    rhs = sp.Matrix([yd - wf * (r - u / wc ** 2), u])
    A = rhs.jacobian(sp.Matrix([r, yd]))
    B = rhs.jacobian(sp.Matrix([u]))
    M = s * sp.eye(2) - (A - B * sp.Matrix([[ky1, ky2]]))
    D = sp.expand(M.det())
    X = M.inv() * sp.Matrix([y0, v0])               # pbar_y(0) = 0: r(0) = y0
    Y = (y0 + X[1]) / s                             # eq. 10
    P = Y - X[0]                                    # eq. 11 with pbar_y(0) = 0
    P_num = sp.cancel(sp.together(P * s * D))       # numerators over H(s) = s D_y(s) (eq. 14-15)
    Y_num = sp.cancel(sp.together(Y * s * D))
    rng = np.random.default_rng(2)
    for _ in range(5):
        vals = {wf: rng.uniform(8, 60), wc: rng.uniform(2.5, 5), ky1: rng.normal(0, 20), ky2: rng.normal(0, 10),
                y0: rng.normal(0, 0.2), v0: rng.normal(0, 0.5)}
        model = MajorAxisModel(float(vals[wc]), float(vals[wf]))
        kk = [float(vals[ky1]), float(vals[ky2])]
        np.testing.assert_allclose(_poly_coeffs(D.subs(vals), 2), model.characteristic(kk), rtol=1e-10)
        num = model.numerators(kk, float(vals[y0]), float(vals[v0]))
        np.testing.assert_allclose(_poly_coeffs(P_num.subs(vals), 2), num[0], rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(_poly_coeffs(Y_num.subs(vals), 2), num[1], rtol=1e-9, atol=1e-12)
    # eq. 19-20: the gains whose D_y has roots alpha, beta
    al, be = sp.symbols("alpha beta")
    sol = sp.solve(sp.Poly(D - sp.expand((s - al) * (s - be)), s).all_coeffs(), [ky1, ky2], dict=True)[0]
    for _ in range(3):
        vals = {wf: rng.uniform(8, 60), wc: rng.uniform(2.5, 5), al: -rng.uniform(1, 10), be: -rng.uniform(1, 80)}
        got = MajorAxisModel(float(vals[wc]), float(vals[wf])).gains_for_poles(float(vals[al]), float(vals[be]))
        np.testing.assert_allclose(got, [float(sol[ky1].subs(vals)), float(sol[ky2].subs(vals))], rtol=1e-10)


def _random_stable(rng, char, n_gains, scale):
    while True:
        k = rng.normal(0, scale, n_gains)
        if np.all(np.roots(char(k)).real < -0.3):
            return k


def test_closed_form_matches_integration_of_eq3_4_both_axes():
    rng = np.random.default_rng(3)
    t = np.linspace(0.0, 4.0, 81)
    for _ in range(6):
        omega_c, omega_f = rng.uniform(2.5, 5.0), rng.uniform(8.0, 60.0)
        minor = MinorAxisModel(omega_c, omega_f)
        k = _random_stable(rng, minor.characteristic, 3, [30.0, 60.0, 15.0])
        x0 = rng.normal(0, [0.03, 0.05, 0.3])
        Acl = minor.closed_loop(k)
        num = solve_ivp(lambda _t, x, Acl=Acl: Acl @ x, (0, 4), x0, t_eval=t, rtol=1e-12, atol=1e-14, method="DOP853")
        assert np.max(np.abs(minor.response(k, x0)(t) - num.y)) < 1e-6

        major = MajorAxisModel(omega_c, omega_f)
        ky = _random_stable(rng, major.characteristic, 2, [20.0, 10.0])
        y0, v0 = rng.normal(0, 0.2), rng.normal(0, 0.6)

        def f(_t, z, ky=ky, major=major):           # eq. 9 and eq. 10, input eq. 12
            r, yd, _y = z
            u = -ky[0] * r - ky[1] * yd
            return [-major.omega_f * r + yd + major.omega_f / major.omega_c ** 2 * u, u, yd]

        num = solve_ivp(f, (0, 4), [y0, v0, y0], t_eval=t, rtol=1e-12, atol=1e-14, method="DOP853")
        got = major.response(ky, y0, v0)(t)
        assert np.max(np.abs(got[1] - num.y[2])) < 1e-6                   # y
        assert np.max(np.abs(got[0] - (num.y[2] - num.y[0]))) < 1e-6      # pbar_y = y - r
        assert np.max(np.abs(got[2] - num.y[1])) < 1e-6                   # ydot


def test_gains_place_the_poles_asked_for():
    rng = np.random.default_rng(4)
    for _ in range(5):
        omega_c, omega_f = rng.uniform(2.5, 5.0), rng.uniform(8.0, 60.0)
        m = MinorAxisModel(omega_c, omega_f)
        re, im = -rng.uniform(0.5, 8.0), rng.uniform(0.0, 3.0)
        poles = np.array([-rng.uniform(5, 80), re + 1j * im, re - 1j * im])
        k = m.gains_for_poles(poles)
        np.testing.assert_allclose(k, place_poles(m.A, m.B, poles).gain_matrix[0], rtol=1e-7, atol=1e-8)
        np.testing.assert_allclose(np.sort_complex(np.linalg.eigvals(m.closed_loop(k))), np.sort_complex(poles),
                                   rtol=1e-7, atol=1e-8)
        M = MajorAxisModel(omega_c, omega_f)
        alpha, beta = -omega_c, -rng.uniform(1.1 * omega_c, 100.0)
        ky = M.gains_for_poles(alpha, beta)
        np.testing.assert_allclose(np.sort(np.linalg.eigvals(M.A - M.B @ ky.reshape(1, 2)).real), [beta, alpha],
                                   rtol=1e-9)
        np.testing.assert_allclose(ky, place_poles(M.A, M.B, [alpha, beta]).gain_matrix[0], rtol=1e-7)


def test_regulator_poles_are_the_care_closed_loop_and_survive_a_height_change():
    from scipy.linalg import solve_continuous_are

    m = MinorAxisModel(omega_of_height(0.74), 25.0)
    Q, R = [1.0, 10.0, 1.0], 0.1
    poles = lqr_poles(m, Q, R)
    P = solve_continuous_are(m.A, m.B, np.diag(Q), np.array([[R]]))
    K = m.B.T @ P / R
    np.testing.assert_allclose(np.sort_complex(poles), np.sort_complex(np.linalg.eigvals(m.A - m.B @ K)))
    assert np.all(poles.real < 0)
    low = MinorAxisModel(omega_of_height(0.62), 25.0)       # a crouched trigger height: other gains, same poles
    k_low = low.gains_for_poles(poles)
    assert not np.allclose(k_low, K[0])
    np.testing.assert_allclose(np.sort_complex(np.roots(low.characteristic(k_low))), np.sort_complex(poles),
                               rtol=1e-8)


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_alpha_minus_omega_c_gives_n1_zero_and_n2_opposite_to_the_capture_point(sign):
    rng = np.random.default_rng(5 if sign > 0 else 6)
    for _ in range(20):
        omega_c, omega_f = rng.uniform(2.5, 5.0), rng.uniform(8.0, 60.0)
        y0, v0 = rng.normal(0, 0.2), rng.normal(0, 0.6)
        if sign * (y0 + v0 / omega_c) <= 0:
            y0, v0 = -y0, -v0
        beta = -rng.uniform(1.05 * omega_c, 150.0)
        sol = solve_major(MajorAxisModel(omega_c, omega_f), -omega_c, beta, y0, v0)
        n1, n2, n3 = sol.n
        assert abs(n1) < 1e-12
        assert sign * n2 < 0 and sign * n3 > 0
        assert abs(n1 + n2 + n3) < 1e-12                               # pbar_y(0) = 0
        # our closed form of n3 (sympy above): capture point * wf (1 - wc/beta) / (wf + wc)
        cp = y0 + v0 / omega_c
        assert n3 == pytest.approx(cp * omega_f * (1 - omega_c / beta) / (omega_f + omega_c), rel=1e-10)
        # the printed n3 of eq. 16 agrees
        a, b, w = -omega_c, beta, omega_c ** 2
        printed = (((w * (1 + (a + b) / omega_f) + a * b) * y0 - (a + b + (w + a * b) / omega_f) * v0)
                   / ((1 - w / omega_f ** 2) * a * b))
        assert n3 == pytest.approx(printed, rel=1e-9)


def test_eq22_limit_and_lower_bound():
    omega_c, y0, v0 = 3.64, 0.05, 0.5
    cp = y0 + v0 / omega_c
    t = np.concatenate([np.linspace(0, 0.01, 2001), np.linspace(0.01, 8, 4000)])
    # eq. 22: omega_f -> inf, beta -> -inf: the ZMP approaches a step to y0 + ydot0/omega_c
    for omega_f, beta, tol in [(1e3, -1e3, 5e-3), (1e5, -1e5, 5e-5)]:
        sol = solve_major(MajorAxisModel(omega_c, omega_f), -omega_c, beta, y0, v0)
        assert abs(np.max(np.abs(sol.response(t)[0])) - cp) < tol
        assert abs(np.max(lipm_zmp(sol.response, omega_c)(t)[0]) - cp) < tol
    # for finite omega_f the generated CoG's LIPM ZMP never stays below eq. 22's bound; equality at beta = -omega_f
    for omega_f in (10.0, 25.0, 60.0):
        for beta in np.linspace(-3 * omega_f, -1.05 * omega_c, 25):
            sol = solve_major(MajorAxisModel(omega_c, omega_f), -omega_c, beta, y0, v0)
            assert np.max(lipm_zmp(sol.response, omega_c)(t)[0]) >= cp - 1e-9
        eq = solve_major(MajorAxisModel(omega_c, omega_f), -omega_c, -omega_f, y0, v0)
        assert eq.n3 == pytest.approx(cp, rel=1e-12)


def test_lipm_zmp_supremum_equals_n3_when_beta_within_omega_f():
    rng = np.random.default_rng(7)
    t = np.concatenate([np.linspace(0, 0.2, 4001), np.linspace(0.2, 12, 6000)])
    for _ in range(20):
        omega_c, omega_f = rng.uniform(2.5, 5.0), rng.uniform(8.0, 60.0)
        y0, v0 = rng.normal(0.1, 0.1), rng.uniform(0.0, 0.8)
        beta = -rng.uniform(1.05 * omega_c, omega_f)
        sol = solve_major(MajorAxisModel(omega_c, omega_f), -omega_c, beta, y0, v0)
        p = lipm_zmp(sol.response, omega_c)(t)[0]
        extreme = p.max() if sol.n3 > 0 else p.min()
        assert abs(extreme - sol.n3) < 1e-3
    # the paper's beta = -100 with omega_f = 30: the LIPM ZMP starts at -beta/omega_f (3.3x) n3
    sol = solve_major(MajorAxisModel(3.64, 30.0), -3.64, -100.0, 0.05, 0.5)
    p = lipm_zmp(sol.response, 3.64)
    assert p(0.0)[0] == pytest.approx(sol.n3 * 100 / 30, rel=1e-9)
    hi, lo = supremum_two_modes(p.constant[0], p.coefficients[0, 0].real, -3.64, p.coefficients[0, 1].real, -100.0)
    assert hi == pytest.approx(np.max(p(t)[0]), abs=1e-9) and lo == pytest.approx(np.min(p(t)[0]), abs=1e-6)


def test_no_zmp_continuous_start_with_alpha_minus_omega_c():
    """The LIPM ZMP's step at the take-over: p(0) = (omega_c - beta) / (omega_f + omega_c) * (y0 + ydot0/omega_c)
    (from eq. 16-17: p(0) = -beta n3 / omega_f). It vanishes only at beta = omega_c (unstable), so with
    alpha = -omega_c the stop cannot start at the pattern's ZMP (pbar_y(0) = 0); the smallest step,
    beta -> -omega_c, is 2 omega_c / (omega_f + omega_c) of eq. 22's bound, at n3 = 2 omega_f / (omega_f + omega_c)
    of it."""
    rng = np.random.default_rng(11)
    for _ in range(20):
        omega_c, omega_f = rng.uniform(2.5, 5.0), rng.uniform(8.0, 60.0)
        y0, v0 = rng.normal(0.1, 0.1), rng.uniform(0.0, 0.8)
        beta = -rng.uniform(1.001 * omega_c, omega_f)
        sol = solve_major(MajorAxisModel(omega_c, omega_f), -omega_c, beta, y0, v0)
        bound = y0 + v0 / omega_c
        assert lipm_zmp(sol.response, omega_c)(0.0)[0] == pytest.approx(
            (omega_c - beta) / (omega_f + omega_c) * bound, rel=1e-7, abs=1e-12)
    b, wc, wf, bd = sp.symbols("beta omega_c omega_f b", real=True)
    n3 = bd * wf * (1 - wc / b) / (wf + wc)
    assert sp.simplify(-b * n3 / wf - (wc - b) / (wf + wc) * bd) == 0
    assert sp.solve(sp.Eq(-b * n3 / wf, 0), b) == [wc]


def test_supremum_two_modes_finds_an_interior_extremum():
    t = np.linspace(0, 20, 200001)
    f = 0.1 + 0.5 * np.exp(-1.0 * t) - 0.7 * np.exp(-3.0 * t)      # rises, peaks, decays
    hi, lo = supremum_two_modes(0.1, 0.5, -1.0, -0.7, -3.0)
    assert hi == pytest.approx(f.max(), abs=1e-8) and lo == pytest.approx(f.min(), abs=1e-8)


def test_eq23_ends_at_zero_velocity_at_a_third_of_the_initial_speed_times_tb():
    rng = np.random.default_rng(8)
    th0, thd0, tb = rng.normal(size=6), rng.normal(0, 2, size=6), 0.4
    pos, vel = return_home(th0, thd0, tb, tb)
    np.testing.assert_allclose(pos, th0 + thd0 * tb / 3, atol=1e-14)
    np.testing.assert_allclose(vel, 0.0, atol=1e-14)
    p0, v0 = return_home(th0, thd0, tb, 0.0)
    np.testing.assert_allclose(p0, th0)
    np.testing.assert_allclose(v0, thd0)
    h = 1e-6
    for t in (0.05, 0.2, 0.35):
        np.testing.assert_allclose((return_home(th0, thd0, tb, t + h)[0] - return_home(th0, thd0, tb, t - h)[0])
                                   / (2 * h), return_home(th0, thd0, tb, t)[1], rtol=1e-6)
    acc = (return_home(th0, thd0, tb, tb - h)[1] - return_home(th0, thd0, tb, tb - 2 * h)[1]) / h
    np.testing.assert_allclose(acc, 0.0, atol=1e-4)                    # zero acceleration at T_b too
    after, vafter = return_home(th0, thd0, tb, 5.0)
    np.testing.assert_allclose(after, pos)
    np.testing.assert_allclose(vafter, 0.0)


def test_joint_stop_time_keeps_the_end_point_inside_the_limits():
    th0 = np.array([0.0, 0.7, -0.5])
    thd0 = np.array([1.0, 3.0, -0.3])
    lower, upper = np.full(3, -1.0), np.array([1.0, 0.75, 1.0])
    tb = stop_duration_within_limits(th0, thd0, lower, upper, 0.3)
    assert tb == pytest.approx(3 * 0.05 / 3.0)                          # the second joint binds
    end, _ = return_home(th0, thd0, tb, tb)
    assert np.all(end <= upper + 1e-12) and np.all(end >= lower - 1e-12)
    assert stop_duration_within_limits(th0, np.zeros(3), lower, upper, 0.3) == 0.3


def test_fit_zmp_lag_recovers_omega_f_from_synthetic_walking_data():
    rng = np.random.default_rng(9)
    dt, true = 0.002, 18.0
    t = np.arange(0, 6, dt)
    ref = 0.09 * np.sign(np.sin(2 * np.pi * t / 1.6)) + 0.02 * np.sin(2 * np.pi * 3 * t)   # ZMP swapping feet
    cop = np.empty_like(ref)
    cop[0] = ref[0]
    for i in range(1, len(t)):                       # forward Euler at 10x finer steps: not the fit's own scheme
        c = cop[i - 1]
        for _ in range(10):
            c += dt / 10 * true * (ref[i - 1] - c)
        cop[i] = c
    cop_noisy = cop + rng.normal(0, 0.002, size=len(t))
    omega, rms = fit_zmp_lag(t, ref, cop_noisy)
    assert omega == pytest.approx(true, rel=0.05)
    assert rms < 0.003
    with pytest.raises(ValueError):
        fit_zmp_lag(t[:2], ref[:2], cop[:2])


def test_bad_parameters_are_refused():
    with pytest.raises(StateSpaceError):
        MajorAxisModel(3.6, 3.6)
    with pytest.raises(StateSpaceError):
        solve_major(MajorAxisModel(3.6, 25.0), -3.6, -3.6, 0.1, 0.1)
    with pytest.raises(StateSpaceError):
        omega_of_height(0.0)
    m = MinorAxisModel(3.6, 25.0)
    with pytest.raises(StateSpaceError):
        m.response(m.gains_for_poles([-2.0, -2.0, -30.0]), [0, 0.01, 0.1], poles=[-2.0, -2.0, -30.0])
    assert math.isfinite(m.gains_for_poles([-2.0, -3.0, -30.0])[0])
