"""The e-stop planner (humfall_ros/estop/planner.py, frame.py, posture.py, config.py): plans from the pattern state."""
from __future__ import annotations

import dataclasses
import inspect
import math

import numpy as np
import pytest

from humfall_ros import params
from humfall_ros.estop.config import NODE_KEYS, EstopConfig, TriggerPhase
from humfall_ros.estop.frame import FootPose, PlanarMotion, StopFrame
from humfall_ros.estop.planner import EstopInputError, EstopPlanner, PatternState
from humfall_ros.estop.posture import configuration_from_feet
from humfall_ros.model.humanoid import load_model, point_in_polygon_margin
from humfall_ros.sim.world import STANDING_POSTURE

M = load_model()
COG = 0.742  # about the standing posture's CoG height


def walking_state(step: float, speed: float, lateral: float = 0.1) -> PatternState:
    """A double-support start: rear (right) foot at the origin, left foot ``step`` ahead, ZMP on the rear sole."""
    ah = M.ankle_height
    feet = {"l": FootPose.flat(step - 0.025, 0.09, 0.0, ah), "r": FootPose.flat(-0.025, -0.09, 0.0, ah)}
    zmp = feet["r"].sole_center(M, "r")
    return PatternState(np.array([0.35 * step, -0.02, COG]), np.array([speed, lateral, 0.0]),
                        np.array([zmp[0], zmp[1], 0.0]), feet, COG)


@pytest.fixture(scope="module")
def planner():
    return EstopPlanner(M)


def test_config_is_the_declared_one_and_refuses_unknown_keys():
    d = params.defaults("estop_planner")
    cfg = EstopConfig.from_params(d)
    assert {f.name for f in dataclasses.fields(EstopConfig)} == set(d) - NODE_KEYS   # the rest is the node's
    for f in dataclasses.fields(EstopConfig):           # the dataclass defaults are the declared ones
        declared = d[f.name]
        got = getattr(cfg, f.name)
        assert (tuple(declared) if isinstance(declared, list) else declared) == got == (
            tuple(f.default) if isinstance(f.default, tuple) else f.default), f.name
    with pytest.raises(ValueError, match="unknown"):
        EstopConfig.from_params({**d, "nope": 1})
    with pytest.raises(ValueError):
        EstopConfig.defaults(beta_policy="both")
    assert TriggerPhase.parse("ss_end") == TriggerPhase("ss", 0.95)
    assert TriggerPhase.parse("ss:0.3") == TriggerPhase("ss", 0.3)
    with pytest.raises(ValueError):
        TriggerPhase.parse("ss:1.5")


def test_frame_major_axis_from_right_to_left_sole_origin_under_the_zmp():
    feet = walking_state(0.4, 0.5).feet
    lc, rc = feet["l"].sole_center(M, "l"), feet["r"].sole_center(M, "r")
    zmp = np.array([0.1, -0.05])
    f = StopFrame.from_feet(lc, rc, zmp)
    np.testing.assert_allclose(f.major, (lc - rc)[:2] / np.linalg.norm((lc - rc)[:2]))
    assert f.minor[0] * f.major[1] - f.minor[1] * f.major[0] == pytest.approx(1.0)   # x, y, z right-handed
    assert f.to_local(rc)[0] == pytest.approx(0.0, abs=1e-12)          # the feet's centre line is x = 0
    assert f.to_local(lc)[0] == pytest.approx(0.0, abs=1e-12)
    assert f.to_local(zmp)[1] == pytest.approx(0.0, abs=1e-12)         # pbar_y(0) = 0
    p = np.array([0.3, 0.2])
    np.testing.assert_allclose(f.to_world(f.to_local(p)), p)


def test_frame_carried_onto_moved_feet_keeps_local_coordinates():
    rng = np.random.default_rng(3)
    lc, rc, zmp = np.array([0.3, 0.1]), np.array([0.0, -0.1]), np.array([0.05, -0.08])
    frame = StopFrame.from_feet(lc, rc, zmp)
    yaw, shift = -0.3, np.array([0.4, -0.2])
    R = np.array([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])
    mo = PlanarMotion.between_feet(lc, rc, R @ lc + shift, R @ rc + shift)
    assert mo.yaw == pytest.approx(yaw) and np.allclose(mo.translation, shift)
    moved = frame.moved(mo)
    # the moved frame is the frame of the moved feet, and a point moved with the feet keeps its local coordinates
    direct = StopFrame.from_feet(R @ lc + shift, R @ rc + shift, R @ zmp + shift)
    assert np.allclose(moved.origin, direct.origin) and np.allclose(moved.major, direct.major)
    p = rng.normal(size=(5, 2))
    assert np.allclose(moved.to_local(mo.apply(p)), frame.to_local(p))


def test_plan_uses_only_the_pattern_state(planner):
    sig = inspect.signature(EstopPlanner.plan)
    assert list(sig.parameters)[:2] == ["self", "state"]
    assert {f.name for f in dataclasses.fields(PatternState)} == {"com", "com_velocity", "zmp", "feet", "cog_height"}
    # the same state gives the same plan whatever the walk would have done next: nothing else is read
    a = planner.plan(walking_state(0.3, 0.4))
    b = planner.plan(walking_state(0.3, 0.4))
    assert a.major.n == b.major.n and np.allclose(a.minor.gains, b.minor.gains)


def test_plan_is_continuous_and_ends_at_rest_at_n3(planner):
    st = walking_state(0.3, 0.4)
    plan = planner.plan(st)
    r0 = plan.sample(0.0)
    np.testing.assert_allclose(r0.com, st.com, atol=1e-12)
    np.testing.assert_allclose(r0.com_velocity[:2], st.com_velocity[:2], atol=1e-12)
    np.testing.assert_allclose(r0.zmp[:2], st.zmp[:2], atol=1e-12)        # the lagged ZMP starts at the reference
    assert plan.alpha == pytest.approx(-math.sqrt(9.81 / COG))
    assert abs(plan.major.n[0]) < 1e-12                                     # n1 = 0 (eq. 17-18)
    end = plan.sample(plan.end_time + 0.1)
    assert end.done and np.all(end.com_velocity == 0.0)                    # terminal velocity exactly 0
    local = plan.frame.to_local(end.com)
    assert local[1] == pytest.approx(plan.major.n3, abs=1e-12) and local[0] == pytest.approx(0.0, abs=1e-12)
    before = plan.sample(plan.end_time - 1e-9)                              # the hand-over to the end point
    assert np.linalg.norm(before.com - end.com) < 1e-4 and np.linalg.norm(before.com_velocity) < 1e-4
    ts = np.linspace(0, plan.end_time, 400)
    coms = np.array([plan.sample(t).com for t in ts])
    assert np.max(np.linalg.norm(np.diff(coms, axis=0), axis=1)) < 0.01    # no jumps along the way
    # the CoG speed falls below settle_speed by the predicted stop time
    assert np.linalg.norm(plan.sample(plan.stop_time + 1e-6).com_velocity) < planner.cfg.settle_speed


def test_predicted_zmp_inside_the_polygon_agrees_with_the_samples(planner):
    plan = planner.plan(walking_state(0.22, 0.28))
    assert plan.feasible
    ts = np.linspace(0, plan.end_time, 2000)
    margins = [point_in_polygon_margin(plan.sample(t).zmp, plan.support_polygon) for t in ts]
    assert min(margins) >= plan.min_zmp_margin - 2e-3
    assert plan.major.max_zmp == pytest.approx(plan.major.n3)           # eq. 21 with beta within omega_f
    assert plan.major.lower_bound <= plan.major.n3 + 1e-12


def test_too_fast_or_outside_the_polygon_is_infeasible(planner):
    plan = planner.plan(walking_state(0.2, 1.2))                         # capture point beyond the front sole
    assert not plan.feasible and "ZMP" in plan.reason
    assert plan.min_zmp_margin < planner.cfg.zmp_margin


def test_beta_policies():
    clamp = EstopPlanner(M, EstopConfig.defaults(major_beta=-100.0, omega_f=30.0, beta_policy="clamp"))
    sup = EstopPlanner(M, EstopConfig.defaults(major_beta=-100.0, omega_f=30.0, beta_policy="supremum"))
    st = walking_state(0.3, 0.4)
    a, b = clamp.plan(st), sup.plan(st)
    assert a.beta == -30.0 and b.beta == -100.0
    assert a.major.max_lipm_zmp == pytest.approx(a.major.n3)              # sup of the LIPM ZMP = n3
    assert b.major.max_lipm_zmp == pytest.approx(b.major.n3 * 100.0 / 30.0, rel=1e-9)   # the paper's jump
    assert b.min_zmp_margin < a.min_zmp_margin


def test_bad_states_are_refused(planner):
    st = walking_state(0.3, 0.4)
    with pytest.raises(EstopInputError, match="CoG height"):
        planner.plan(dataclasses.replace(st, cog_height=0.2))
    with pytest.raises(EstopInputError, match="non-finite"):
        planner.plan(dataclasses.replace(st, com_velocity=np.array([np.nan, 0.0, 0.0])))
    with pytest.raises(EstopInputError, match="speed"):
        planner.plan(dataclasses.replace(st, com_velocity=np.array([3.0, 0.0, 0.0])))
    with pytest.raises(EstopInputError, match="foot"):
        planner.plan(dataclasses.replace(st, feet={"l": st.feet["l"]}))


def _seed(st):
    return configuration_from_feet(M, M.joint_vector(STANDING_POSTURE), st.feet, "r")


def test_short_step_needs_no_crouch_and_the_posture_holds_the_feet(planner):
    st = walking_state(0.11, 0.14)
    plan = planner.plan_with_posture(st, _seed(st))
    assert plan.feasible and plan.crouch is None and plan.posture.reachable
    M.forward(plan.posture.q)
    for s in "lr":
        np.testing.assert_allclose(M.frame_position(M.foot_link[s]), st.feet[s].position, atol=1e-3)
    np.testing.assert_allclose(M.com(plan.posture.q)[:2], plan.final_com[:2], atol=1e-3)


def test_long_step_crouches_and_the_crouch_is_in_the_zmp_prediction(planner):
    st = walking_state(0.4, 0.5)
    nominal = planner.posture_solver.solve(_seed(st), st.feet, planner.plan(st).final_com, st.ground_height)
    assert not nominal.reachable                                  # the stretched rear leg cannot hold the CoG there
    plan = planner.plan_with_posture(st, _seed(st))
    assert plan.feasible and plan.crouch is not None and plan.crouch.end_height < COG - 0.01
    assert plan.posture.reachable
    assert plan.posture.cog_height_reached == pytest.approx(plan.crouch.end_height, abs=2e-3)
    lo = M.limits.lower + planner.cfg.joint_margin - 1e-6
    hi = M.limits.upper - planner.cfg.joint_margin + 1e-6
    assert np.all(plan.posture.q[7:] >= lo) and np.all(plan.posture.q[7:] <= hi)
    mid = plan.sample(0.5 * plan.crouch.duration)
    assert mid.omega_c != pytest.approx(plan.omega_c)             # omega_c follows the vertical motion
    assert plan.sample(plan.end_time + 1).com[2] == pytest.approx(st.ground_height + plan.crouch.end_height)


def test_the_crouch_keeps_its_clearance_below_what_the_legs_reach_with_the_upper_body_held(planner):
    """The posture check moves the CoG with the legs (the stop's IK holds the upper body); the crouch ends
    ``crouch_clearance`` below the highest height the check reaches, to the IK's tolerance."""
    st = walking_state(0.4, 0.5)
    seed = _seed(st)
    plan = planner.plan_with_posture(st, seed)
    c = planner.cfg
    upper = np.array([not any(k in n for k in ("hip", "knee", "ankle")) for n in M.joint_names])
    assert np.max(np.abs(plan.posture.q[7:][upper] - seed[7:][upper])) < 5e-3   # chest and arms where they were
    solver = planner.posture_solver
    xy = plan.final_com[:2]
    top = plan.crouch.end_height + c.crouch_clearance
    below = solver.solve(plan.posture.q, st.feet, np.array([*xy, st.ground_height + top - 3 * c.ik_tolerance]),
                         st.ground_height)
    above = solver.solve(plan.posture.q, st.feet, np.array([*xy, st.ground_height + top + 3 * c.ik_tolerance]),
                         st.ground_height)
    assert below.reachable and not above.reachable
    # a crouch floor between the top and the top less the clearance: not feasible (the clearance is not optional)
    tight = EstopPlanner(M, EstopConfig.defaults(crouch_min_cog_height=top - 0.5 * c.crouch_clearance,
                                                 fallback="none")).plan_with_posture(st, seed)
    assert not tight.feasible and "clearance does not fit" in tight.reason


def test_unreachable_stop_runs_the_fallback_or_not():
    st = walking_state(0.65, 0.8)
    fb = EstopPlanner(M).plan_with_posture(st, _seed(st))
    assert not fb.feasible and fb.fallback == "min_n3_crouch" and "fallback" in fb.reason
    assert fb.beta == pytest.approx(-fb.omega_f)
    none = EstopPlanner(M, EstopConfig.defaults(fallback="none")).plan_with_posture(st, _seed(st))
    assert not none.feasible and none.fallback == "" and none.crouch is None


def test_result_section_from_the_plan_played_back(planner):
    from humfall_ros.estop.metrics import estop_result

    plan = planner.plan(walking_state(0.22, 0.28))
    t = np.arange(0.0, plan.end_time + 0.5, 0.002)
    refs = [plan.sample(x) for x in t]
    com = np.array([r.com for r in refs])
    cop = np.array([r.zmp for r in refs])
    margin = np.array([point_in_polygon_margin(p, plan.support_polygon) for p in cop])
    res = estop_result(plan, t + 1.0, com, cop, margin, 1.0, False)
    assert res["final_cog_major_m"] == pytest.approx(plan.major.n3, abs=1e-9)
    assert res["final_cog_minor_m"] == pytest.approx(0.0, abs=1e-9)
    assert res["stop_time_s"] == pytest.approx(plan.stop_time, abs=0.02)
    assert res["max_cop_minor_m"] == pytest.approx(abs(plan.minor.max_zmp), abs=2e-3)
    assert res["min_cop_margin_m"] >= plan.min_zmp_margin - 2e-3 and res["feasible"] and not res["fell"]


def test_result_stop_time_is_not_moved_by_a_small_step_of_the_odometry(planner):
    """A 60 um jump of the estimated CoG (a leg-odometry contact switch) 2 s after the stop is 0.015 m/s over two
    ticks: the stop time reads the CoG's displacement over 20 ms, so it stays the plan's; a real slow
    drift above the settle speed still counts as moving."""
    from humfall_ros.estop.metrics import estop_result

    plan = planner.plan(walking_state(0.22, 0.28))
    t = np.arange(0.0, plan.end_time + 3.0, 0.002)
    com = np.array([plan.sample(x).com for x in t])
    cop = np.array([plan.sample(x).zmp for x in t])
    margin = np.zeros(len(t))
    jump = com.copy()
    jump[t >= plan.stop_time + 2.0, 0] += 6e-5
    res = estop_result(plan, t, jump, cop, margin, 0.0, False)
    assert res["stop_time_s"] == pytest.approx(plan.stop_time, abs=0.02)
    one_tick = estop_result(plan, t, jump, cop, margin, 0.0, False, speed_window=0.0)
    assert one_tick["stop_time_s"] > plan.stop_time + 1.9          # what the central difference made of it
    drift = com.copy()
    late = t >= plan.stop_time + 1.0
    drift[late, 0] += 0.02 * (t[late] - plan.stop_time - 1.0)       # 2 cm/s from 1 s after the stop on
    assert math.isnan(estop_result(plan, t, drift, cop, margin, 0.0, False)["stop_time_s"])   # never stopped


def test_beta_policy_omega_c_scales_with_the_trigger_height_and_shrinks_the_lipm_zmp_step():
    from humfall_ros.dynamics.pendulum import GRAVITY

    pl = EstopPlanner(M, EstopConfig.defaults(beta_policy="omega_c", major_beta_ratio=2.0))
    for z in (0.65, 0.74):
        wc = (GRAVITY / z) ** 0.5
        assert pl.choose_beta(wc) == pytest.approx(-2.0 * wc)
        assert pl.choose_beta(wc, requested=-1000.0) == pytest.approx(-pl.cfg.omega_f)   # the fallback's beta
    plan = pl.plan(walking_state(0.2, 0.3))
    assert plan.beta == pytest.approx(-2.0 * plan.omega_c)                    # what plan() uses
    # beyond omega_f it is clamped like "clamp"
    assert EstopPlanner(M, EstopConfig.defaults(beta_policy="omega_c", major_beta_ratio=50.0)).choose_beta(3.6) \
        == pytest.approx(-EstopConfig.defaults().omega_f)

