"""fall.push_residual: the capture point's residual reads an external force on a LIPM, and nothing without one."""
import math

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from humfall_ros.dynamics.pendulum import GRAVITY
from humfall_ros.fall.push_residual import PushResidual

Z, MASS = 0.74, 40.0
OMEGA = math.sqrt(GRAVITY / Z)


def _lipm(force, cop, t_end, dt=0.002, c0=(0.0, 0.0), v0=(0.05, -0.02)):
    """A LIPM at height Z with the CoP ``cop(t)`` and the horizontal force ``force(t)`` [N], sampled every dt."""
    def f(t, y):
        c, v = y[:2], y[2:]
        return np.concatenate([v, OMEGA ** 2 * (c - cop(t)) + force(t) / MASS])
    ts = np.arange(round(t_end / dt) + 1) * dt
    t_end = float(ts[-1])
    sol = solve_ivp(f, (0.0, t_end), np.array([*c0, *v0]), t_eval=ts, rtol=1e-10, atol=1e-12, max_step=dt)
    return ts, sol.y[:2].T, sol.y[2:].T


def _feed(est, ts, c, v, cop):
    out = []
    for t, ci, vi in zip(ts, c, v):
        xi = ci + vi / OMEGA
        est.update(t, [*ci, Z], xi, cop(t))
        out.append(est.value().copy())
    return np.array(out)


def test_reads_the_force_while_it_acts_and_zero_after():
    push = np.array([300.0, -120.0])

    def force(t):
        return push if 0.1 <= t < 0.2 else np.zeros(2)

    def cop(t):
        return np.array([0.02 * math.sin(7 * t), 0.01])   # a moving CoP: no force, no residual

    ts, c, v = _lipm(force, cop, 0.35)
    r = _feed(PushResidual(0.02), ts, c, v, cop)
    expect = push / (MASS * OMEGA)
    mid = np.searchsorted(ts, 0.18)   # a full window inside the push
    assert np.allclose(r[mid], expect, rtol=0.02), (r[mid], expect)
    before, after = np.searchsorted(ts, 0.095), np.searchsorted(ts, 0.25)
    assert np.linalg.norm(r[before]) < 0.01
    assert np.linalg.norm(r[after]) < 0.01
    # half a window past the push's start: about half the force
    half = np.searchsorted(ts, 0.11)
    assert 0.3 < np.linalg.norm(r[half]) / np.linalg.norm(expect) < 0.7


def test_window_filters_tick_noise():
    rng = np.random.default_rng(0)

    def cop(t):
        return np.zeros(2)

    ts, c, v = _lipm(lambda t: np.zeros(2), cop, 0.3)
    noisy = PushResidual(0.02)
    one_tick = PushResidual(0.002)
    rn, r1 = [], []
    for t, ci, vi in zip(ts, c, v):
        xi = ci + vi / OMEGA + rng.normal(0.0, 0.003, 2)   # 3 mm of capture-point noise per tick
        noisy.update(t, [*ci, Z], xi, cop(t))
        one_tick.update(t, [*ci, Z], xi, cop(t))
        rn.append(noisy.magnitude())
        r1.append(one_tick.magnitude())
    assert np.nanmax(rn[20:]) < np.nanmax(r1[20:]) / 4


def test_bad_input_and_time_going_back():
    est = PushResidual(0.02)
    assert np.all(np.isnan(est.value())) and not est.ready
    est.update(0.0, [0, 0, Z], [0.0, 0.0], [0.0, 0.0])
    est.update(0.002, [0, 0, math.nan], [0.0, 0.0], [0.0, 0.0])   # skipped
    est.update(0.002, [0, 0, Z], [math.inf, 0.0], [0.0, 0.0])     # skipped
    assert len(est._buf) == 1
    for k in range(1, 12):
        est.update(0.002 * k, [0, 0, Z], [0.0, 0.0], [0.0, 0.0])
    assert est.ready and est.magnitude() == pytest.approx(0.0)
    est.update(0.001, [0, 0, Z], [0.0, 0.0], [0.0, 0.0])   # a new run: the window starts again
    assert not est.ready
    with pytest.raises(ValueError):
        PushResidual(0.0)
