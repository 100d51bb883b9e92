"""Walking pattern: preview control (Kajita 2003), footsteps, swing, multi-body ZMP, controller inputs."""
from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import sympy as sp

from humfall_ros.model.humanoid import load_model
from humfall_ros.walking.config import LocomotionConfig
from humfall_ros.walking.footsteps import (
    Footstep,
    WalkCommand,
    plan_footsteps,
    step_width,
)
from humfall_ros.walking.multibody import multibody_zmp
from humfall_ros.walking.pattern import SupportPhase, WalkingPattern
from humfall_ros.walking.preview import PreviewController
from humfall_ros.walking.swing import swing_foot

DT = 0.002


def cart_zmp(states, z_c):
    return states[:, 0, :] - z_c / 9.81 * states[:, 2, :]


def test_preview_zero_steady_state_error_on_a_step():
    pc = PreviewController(DT, 0.70, 1.6)
    n = pc.n_preview
    k = int(4.0 / DT)
    ref = np.zeros((k + n, 2))
    ref[int(1.0 / DT):, 0] = 0.1
    ref[int(1.5 / DT):, 1] = -0.05
    st = pc.rollout(ref)
    p = cart_zmp(st, 0.70)
    assert np.allclose(p[-1], ref[k], atol=1e-6)
    assert np.allclose(st[-1, 1], 0.0, atol=1e-5)  # at rest over the new ZMP


def walking_like_reference(t):
    """0.3 m steps every 0.8 s forward with 0.1 s ramps (the ZMP moves 0.3 m per step)."""
    step = np.floor(np.maximum(t - 1.0, 0.0) / 0.8)
    ph = np.maximum(t - 1.0, 0.0) - 0.8 * step
    x = 0.3 * (step + np.clip(ph / 0.1, 0.0, 1.0)) * (t >= 1.0)
    y = np.where(step % 2 == 0, 1.0, -1.0) * 0.09 * (t >= 1.0)
    return np.stack([x, y], axis=1)


def test_cart_table_tracks_a_walking_pattern_within_1mm_rms():
    pc = PreviewController(DT, 0.70, 1.6, r=1e-7)
    n = pc.n_preview
    k = int(8.0 / DT)
    t = np.arange(k + n) * DT
    ref = walking_like_reference(t)
    # ramp the lateral too, so the reference is continuous (a ZMP cannot jump)
    ref[:, 1] = np.convolve(ref[:, 1], np.ones(50) / 50, mode="same")
    st = pc.rollout(ref)
    e = cart_zmp(st, 0.70) - ref[1:k + 1]
    settled = t[1:k + 1] > 2.0
    rms = np.sqrt(np.mean(np.sum(e[settled] ** 2, axis=1)))
    assert rms < 1e-3, rms


def test_online_step_equals_rollout():
    pc = PreviewController(DT, 0.70, 1.6)
    n = pc.n_preview
    t = np.arange(600 + n) * DT
    ref = walking_like_reference(t + 0.9)
    off = pc.rollout(ref)
    for k in range(600):
        pc.step(ref[k], ref[k + 1:k + 1 + n])
    assert np.allclose(pc.state, off[-1], atol=1e-12)


def test_gains_recomputed_when_the_com_height_changes():
    pc = PreviewController(DT, 0.742, 1.6)
    g0 = pc.gains
    assert not pc.set_com_height(0.742)
    assert pc.set_com_height(0.70)
    fresh = PreviewController(DT, 0.70, 1.6)
    assert pc.gains.com_height == 0.70
    assert np.allclose(pc.gains.gp, fresh.gains.gp) and np.isclose(pc.gains.gi, fresh.gains.gi)
    assert not np.allclose(g0.gp, pc.gains.gp)
    assert np.isclose(pc.C[2], -0.70 / 9.81)


def test_footstep_plan_straight_and_turning():
    width = step_width(load_model())
    assert width == pytest.approx(0.18)
    v, T = 1.0 / 3.6, 0.8
    steps = plan_footsteps((0.0, 0.0, 0.0), WalkCommand(v, 0.0), 20, T, width)
    assert len(steps) == 21 and steps[-1].stop
    assert [s.side for s in steps[:4]] == ["r", "l", "r", "l"]
    assert steps[-2].x == pytest.approx(20 * v * T) and steps[-1].x == pytest.approx(20 * v * T)
    assert all(abs(abs(s.y) - width / 2) < 1e-12 for s in steps)
    # a left turn: 10 deg/s, 12 steps -> 96 deg; the left foot leaves first; feet stay `width` apart
    yaw_rate = math.radians(10.0)
    turn = plan_footsteps((0.0, 0.0, 0.0), WalkCommand(v, yaw_rate), 12, T, width)
    assert turn[0].side == "l"
    assert turn[-1].yaw == pytest.approx(12 * yaw_rate * T)
    a, b = turn[-2], turn[-1]  # the stop step lands beside the last one
    assert math.hypot(a.x - b.x, a.y - b.y) == pytest.approx(width)
    # path length ~ 12 strides
    pts = [(0.0, 0.0)] + [((p.x + q.x) / 2, (p.y + q.y) / 2) for p, q in itertools.pairwise(turn)]
    assert turn[-1].yaw > math.radians(90)
    assert len(pts) == 13


def test_swing_foot_apex_and_ends():
    start, end = np.array([0.0, -0.09, 0.0]), np.array([0.4, -0.09, 0.0])
    for tau in (0.0, 1.0):
        p, _, v, _ = swing_foot(start, end, 0.0, 0.2, 0.05, tau, 0.7)
        assert np.allclose(v, 0.0, atol=1e-12)
        assert np.allclose(p, start if tau == 0 else end)
    p, yaw, _, _ = swing_foot(start, end, 0.0, 0.2, 0.05, 0.5, 0.7)
    assert p[2] == pytest.approx(0.05) and yaw == pytest.approx(0.1)


def test_pattern_phases_and_references():
    cfg = LocomotionConfig()
    feet = {"l": Footstep("l", 0.0, 0.09, 0.0), "r": Footstep("r", 0.0, -0.09, 0.0)}
    p = WalkingPattern(cfg, DT, 0.18, 0.025, feet, [0.015, 0.0, 0.742], WalkCommand(1.0 / 3.6, 0.0), n_steps=3)
    samples = []
    while True:
        s = p.step()
        samples.append(s)
        if s.finished:
            break
    kinds = [s.support for s in samples]
    # crouch + start, then SS right swing (left stance), DS, ...
    first_ss = kinds.index(SupportPhase.SINGLE_LEFT)
    assert first_ss * DT == pytest.approx(cfg.crouch_duration + cfg.start_duration, abs=2 * DT)
    n_ss = sum(1 for a, b in itertools.pairwise(kinds) if a == SupportPhase.DOUBLE and b != SupportPhase.DOUBLE)
    assert n_ss == 4  # 3 steps + the stop step
    for s in samples:
        if s.support != SupportPhase.DOUBLE:
            stance = "l" if s.support == SupportPhase.SINGLE_LEFT else "r"
            assert s.feet[stance].position[2] == 0.0
            # in single support the reference ZMP is the stance sole's centre
            assert np.allclose(s.zmp[:2], [s.feet[stance].position[0] + 0.025, s.feet[stance].position[1]])
    # apex at mid-swing (plus half the landing height the swing ends at)
    assert max(s.feet["r"].position[2] for s in samples) == pytest.approx(cfg.swing_apex + cfg.landing_height / 2,
                                                                           abs=1e-4)
    # the swing ends landing_height above the ground, the foot is down landing_duration into the double support
    k = next(i for i, (a, b) in enumerate(itertools.pairwise(kinds)) if a == SupportPhase.SINGLE_LEFT
             and b == SupportPhase.DOUBLE)
    assert samples[k].feet["r"].position[2] == pytest.approx(cfg.landing_height, abs=2e-5)
    assert samples[k + 1].feet["r"].position[2] == pytest.approx(cfg.landing_height)
    assert 0 < samples[k + 2].feet["r"].position[2] < cfg.landing_height
    assert samples[k + 1 + round(cfg.landing_duration / DT)].feet["r"].position[2] == pytest.approx(0.0, abs=1e-9)
    end = samples[-1]
    assert end.com[2] == pytest.approx(cfg.com_height)
    assert np.linalg.norm(end.com_velocity) < 0.01
    assert end.com[0] == pytest.approx(3 * 1.0 / 3.6 * 0.8 + 0.025, abs=0.01)


def test_multibody_zmp_formula_derived():
    """p on z = 0 where the contact wrench has no horizontal moment (sympy), against multibody_zmp."""
    cx, cy, cz, fx, fy, fz, Lx, Ly, px, py = sp.symbols("cx cy cz fx fy fz Lx Ly px py")
    c, f, p = sp.Matrix([cx, cy, cz]), sp.Matrix([fx, fy, fz]), sp.Matrix([px, py, 0])
    # the contact force f acts at p; about the CoM: (p - c) x f + dL/dt_contact ... the momentum balance
    # dL/dt = (p - c) x f (+ a free vertical moment): horizontal components give p
    dL = sp.Matrix([Lx, Ly, 0])
    eq = ((p - c).cross(f) - dL)[:2]
    sol = sp.solve(eq, [px, py], dict=True)[0]
    vals = {cx: 0.1, cy: -0.02, cz: 0.7, fx: 30.0, fy: -12.0, fz: 600.0, Lx: 4.0, Ly: -7.0}
    m = 58.0
    got = multibody_zmp([0.1, -0.02, 0.7], [30.0, -12.0, 600.0 - m * 9.81], [4.0, -7.0, 0.0], m)
    assert got[0] == pytest.approx(float(sol[px].subs(vals)))
    assert got[1] == pytest.approx(float(sol[py].subs(vals)))


def test_step_period_depends_on_the_speed():
    cfg = LocomotionConfig.from_params()
    assert cfg.step_period_for(1.0 / 3.6) == pytest.approx(cfg.step_period)
    assert cfg.step_period_for(cfg.fast_step_speed_kmh / 3.6) == pytest.approx(cfg.step_period)
    assert cfg.step_period_for(1.8 / 3.6) == pytest.approx(cfg.fast_step_period) != cfg.step_period
    off = LocomotionConfig.from_params({"fast_step_period": 0.0})
    assert off.step_period_for(1.8 / 3.6) == pytest.approx(off.step_period)
    feet = {"l": Footstep("l", 0.0, 0.09, 0.0), "r": Footstep("r", 0.0, -0.09, 0.0)}
    # a walk at 1.0 km/h that speeds up to 1.8 km/h: the steps planned after the change are shorter in time
    # and advance speed * period each
    p = WalkingPattern(cfg, DT, 0.18, 0.025, feet, [0.015, 0.0, 0.70], WalkCommand(1.0 / 3.6, 0.0))
    p.set_command(WalkCommand(1.8 / 3.6, 0.0))
    ss = [ph for ph in (p.single_support_phase(k) for k in range(1, 12))]
    durations = [ph.ticks * DT for ph in ss]
    slow = [d for d in durations if abs(d - (cfg.step_period - cfg.double_support)) < 1e-9]
    fast = [d for d in durations if abs(d - (cfg.fast_step_period - cfg.double_support)) < 1e-9]
    assert slow and fast and len(slow) + len(fast) == len(durations)
    assert durations.index(fast[0]) == len(slow)            # once fast, it stays fast
    xs = [ph.swing_to.x for ph in ss]
    assert xs[-1] - xs[-2] == pytest.approx(1.8 / 3.6 * cfg.fast_step_period, abs=1e-6)


def test_rear_foot_liftoff_at_the_end_of_the_double_support():
    """liftoff_height: the rear sole rises in the last liftoff_duration of a step's double support, the swing
    starts from there (continuous), and the start double support has none (no foot swung before it)."""
    import dataclasses

    cfg = dataclasses.replace(LocomotionConfig(), liftoff_height=1e-4, liftoff_duration=0.03)
    feet = {"l": Footstep("l", 0.0, 0.09, 0.0), "r": Footstep("r", 0.0, -0.09, 0.0)}
    p = WalkingPattern(cfg, DT, 0.18, 0.025, feet, [0.015, 0.0, 0.70], WalkCommand(1.0 / 3.6, 0.0), n_steps=3)
    samples = []
    while not (samples and samples[-1].finished):
        samples.append(p.step())
    kinds = [s.support for s in samples]
    first = kinds.index(SupportPhase.SINGLE_LEFT)                    # the first swing (right) starts at 0
    assert samples[first].feet["r"].position[2] == pytest.approx(0.0, abs=1e-6)
    assert all(s.feet["r"].position[2] == 0.0 for s in samples[:first])
    # the double support after it: the left foot (rear, it swings next) lifts at the end, the right is down
    k = next(i for i in range(first, len(kinds)) if kinds[i] == SupportPhase.SINGLE_RIGHT)  # next swing: left
    ds = samples[k - round(cfg.double_support / DT):k]
    n_lift = round(cfg.liftoff_duration / DT)
    assert all(s.feet["l"].position[2] == 0.0 for s in ds[:len(ds) - n_lift])
    assert ds[-1].feet["l"].position[2] == pytest.approx(1e-4, rel=0.05)
    assert np.all(np.diff([s.feet["l"].position[2] for s in ds]) >= 0)
    assert samples[k].feet["l"].position[2] == pytest.approx(1e-4, abs=2e-6)   # the swing continues from there
    assert ds[-1].feet["r"].position[2] == 0.0
