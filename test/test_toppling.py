"""Toppling pendulums (paper 1 §III-A): the elliptic control duration derived and checked numerically."""
from __future__ import annotations

import math

import numpy as np
import pytest
import sympy as sp
from scipy.integrate import solve_ivp

from humfall_ros.dynamics.pendulum import GRAVITY as G
from humfall_ros.dynamics.toppling import (
    FallOutcome,
    edge_pendulum,
    energy_ratio,
    lean_rate,
    separatrix_margin,
    simulate_spherical,
    spherical_rk4,
    time_to_lean,
)

L = 0.75


def test_elliptic_forms_derived_with_sympy():
    """d t / d theta of both closed forms equals 1 / theta' from the energy (so the integrals are right)."""
    th, e, w = sp.symbols("theta e omega0", positive=True)
    rate = w * sp.sqrt(2 * (e - sp.cos(th)))            # theta' from E = 1/2 I theta'^2 + m g L cos(theta)
    # over the crest: t(theta) = -sqrt(m)/omega0 F(pi/2 - theta/2 | m) + const, m = 2 / (e + 1)
    m = 2 / (e + 1)
    t_over = -sp.sqrt(m) / w * sp.elliptic_f(sp.pi / 2 - th / 2, m)
    ratio = (sp.diff(t_over, th) * rate) ** 2
    for ev, tv in [(1.3, 0.2), (1.01, -0.3), (2.0, 1.0)]:
        assert float(ratio.subs({e: ev, th: tv, w: 3.0})) == pytest.approx(1.0, rel=1e-12)
    # below the crest: t(theta) = -F(beta | m') / omega0, sin(beta) = cos(theta/2) / sqrt(m'), m' = (e + 1) / 2
    mp = (e + 1) / 2
    beta = sp.asin(sp.cos(th / 2) / sp.sqrt(mp))
    t_below = -sp.elliptic_f(beta, mp) / w
    ratio_b = (sp.diff(t_below, th) * rate) ** 2
    for ev, tv in [(0.95, 0.5), (0.99, 0.3), (0.5, 1.2)]:
        assert math.acos(ev) < tv  # beyond the turning point
        assert float(ratio_b.subs({e: ev, th: tv, w: 3.0})) == pytest.approx(1.0, rel=1e-12)


def _numeric_time(theta0, theta_dot0, theta_end, t_max=10.0):
    w2 = G / L

    def rhs(_t, y):
        return [y[1], w2 * math.sin(y[0])]

    def hit(_t, y):
        return y[0] - theta_end

    hit.terminal, hit.direction = True, 1

    def back(_t, y):  # swung back far onto the support side
        return y[0] + 1.0

    back.terminal = True
    sol = solve_ivp(rhs, (0, t_max), [theta0, theta_dot0], events=[hit, back], rtol=1e-11, atol=1e-12)
    return float(sol.t_events[0][0]) if sol.t_events[0].size else math.inf


@pytest.mark.parametrize("theta0,theta_dot0", [
    (-0.12, 0.60),     # CoM behind the edge, over the crest
    (-0.02, 0.08),     # just over the crest: slow, near the separatrix
    (0.05, 0.0),       # beyond the edge at rest
    (0.10, 0.40),      # beyond and moving on
    (0.15, -0.30),     # beyond, moving back, below the crest: turning point first
    (0.0, 0.05),       # on the crest line, moving
])
def test_elliptic_time_matches_numerical_integration(theta0, theta_dot0):
    theta_end = math.radians(20)
    r = time_to_lean(theta0, theta_dot0, theta_end, L)
    assert r.outcome is FallOutcome.FALLS
    t_num = _numeric_time(theta0, theta_dot0, theta_end)
    assert abs(r.time - t_num) < 1e-3, (r.time, t_num)
    # eq. 3 at the end, against the energy
    assert r.theta_dot_end == pytest.approx(math.sqrt(2 * G / L * (r.energy_ratio - math.cos(theta_end))), rel=1e-9)


@pytest.mark.parametrize("theta0,theta_dot0,outcome", [
    (-0.12, 0.30, FallOutcome.NEVER_FALLS),   # below the crest: swings back
    (-0.05, -0.10, FallOutcome.NEVER_FALLS),  # moving away from the edge
    (0.05, -0.60, FallOutcome.NEVER_FALLS),   # beyond, but back over the crest
    (0.0, 0.0, FallOutcome.CREST),            # on the crest at rest
])
def test_no_fall_cases_are_not_nan(theta0, theta_dot0, outcome):
    r = time_to_lean(theta0, theta_dot0, math.radians(20), L)
    assert r.outcome is outcome
    assert r.time == math.inf
    if outcome is FallOutcome.NEVER_FALLS:
        assert _numeric_time(theta0, theta_dot0, math.radians(20), t_max=5.0) == math.inf


def test_separatrix_state_is_crest_and_margin_signs():
    # exactly on the separatrix from behind the edge: theta'^2 = 2 g / L (1 - cos theta0)
    th0 = -0.1
    thd = math.sqrt(2 * G / L * (1 - math.cos(th0)))
    e = float(energy_ratio(th0, thd, L))
    assert abs(e - 1) < 1e-12
    assert time_to_lean(th0, thd, 0.3, L).outcome is FallOutcome.CREST
    margins = separatrix_margin([-0.1, -0.1, 0.1, 0.1], [0.6, 0.3, -0.6, -0.1],
                                energy_ratio([-0.1, -0.1, 0.1, 0.1], [0.6, 0.3, -0.6, -0.1], L))
    assert list(np.sign(margins)) == [1, -1, -1, 1]


def test_eq3_lean_rate():
    # point mass m, I = m L^2: E = 1/2 I w^2 + m g L cos
    m, th, w = 58.0, 0.2, 0.7
    inertia = m * L * L
    energy = 0.5 * inertia * w * w + m * G * L * math.cos(th)
    assert float(lean_rate(th, energy, m, L, inertia)) == pytest.approx(w)


def test_edge_pendulum_geometry():
    # CoM 8.6 cm behind a toe edge at x = 0.145, 0.75 m up, moving forward 0.4 m/s (the standing_push timeline)
    p = edge_pendulum([0.059, 0.02, 0.75], [0.4, 0.1, 0.0], [0.145, 0.3, 0.0], [1.0, 0.0])
    assert p.theta == pytest.approx(math.atan2(-0.086, 0.75))
    assert p.pivot == pytest.approx([0.145, 0.02, 0.0])
    assert p.com_at(p.theta) == pytest.approx([0.059, 0.02, 0.75])


def test_spherical_with_planar_velocity_equals_2d():
    th0, thd0, th_end = -0.08, 0.55, math.radians(25)
    r0 = L * np.array([math.sin(th0), 0.0, math.cos(th0)])
    v0 = L * thd0 * np.array([math.cos(th0), 0.0, -math.sin(th0)])
    sph = simulate_spherical(r0, v0, 5.0, th_end)
    planar = time_to_lean(th0, thd0, th_end, L)
    assert sph.reached_threshold
    assert abs(sph.time - planar.time) < 1e-3
    assert sph.position[1] == pytest.approx(0.0, abs=1e-9)
    assert sph.velocity == pytest.approx(L * planar.theta_dot_end * np.array([math.cos(th_end), 0, -math.sin(th_end)]),
                                         abs=1e-5)
    # rotated about the vertical: same time
    c, s = math.cos(1.1), math.sin(1.1)
    rz = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    sph2 = simulate_spherical(rz @ r0, rz @ v0, 5.0, th_end)
    assert sph2.time == pytest.approx(sph.time, abs=1e-6)


def test_rk4_batch_matches_solve_ivp():
    r0 = np.array([[0.05, 0.02, 0.73], [0.01, -0.06, 0.74]])
    v0 = np.array([[0.4, -0.15, 0.0], [0.2, 0.3, 0.0]])
    duration = np.array([0.6, 0.45])
    r, v = spherical_rk4(r0, v0, duration)
    for k in range(2):
        ref = simulate_spherical(r0[k], v0[k], float(duration[k]))
        assert np.linalg.norm(r[k] - ref.position) < 1e-3
        assert np.linalg.norm(v[k] - ref.velocity) < 5e-3
        assert np.linalg.norm(r[k]) == pytest.approx(np.linalg.norm(r0[k]))
