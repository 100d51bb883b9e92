"""Safe fall (paper 1), functional core: geometry, FTB, stepping zone, search, inertia shaping, controller."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from humfall_ros import params
from humfall_ros.control.contract import CentroidalObservation, Observation
from humfall_ros.fall import step_search as ss
from humfall_ros.fall.controller import SafeFallConfig, SafeFallController
from humfall_ros.fall.ftb import TRANSITIONS, FtbConfig, FtbMonitor, FtbState, TriggerMode, features_of
from humfall_ros.fall.geometry import avoidance_angle, nearest_on_boundary, polygon_edges
from humfall_ros.fall.inertia_shaping import (
    ClearBox,
    ShapingConfig,
    box_distance,
    crb_inertia_and_jacobian,
    crb_inertia_vector,
    desired_angular_velocity,
    shaping_velocities,
)
from humfall_ros.fall.stepping_zone import stepping_zone
from humfall_ros.model.humanoid import load_model, point_in_polygon_margin, support_polygon
from humfall_ros.sim.world import STANDING_POSTURE

M = load_model()


def standing_q(base_xy=(0.0, 0.0)):
    qj = M.joint_vector(STANDING_POSTURE)
    q = M.configuration([0, 0, 0], [0, 0, 0, 1], qj)
    M.forward(q)
    z = -min(M.sole_corners(s)[:, 2].min() for s in "lr")
    q[:3] = [base_xy[0], base_xy[1], z]
    M.forward(q)
    return q


def state(com, vel, polygon, cop=None, feet_center=(0, 0, 0.105), normal_force=570.0):
    com = np.asarray(com, float)
    vel = np.asarray(vel, float)
    cop = np.array([com[0], com[1], 0.0]) if cop is None else np.asarray(cop, float)
    omega_inv = math.sqrt(com[2] / 9.81)
    cp = np.array([com[0] + omega_inv * vel[0], com[1] + omega_inv * vel[1], 0.0])
    d = com - cop
    lean = math.atan2(math.hypot(d[0], d[1]), d[2])
    return CentroidalObservation(com, vel, cop, cp, np.zeros(3), np.asarray(polygon, float), np.asarray(feet_center),
                                 lean, math.atan2(d[1], d[0]), normal_force, True, True, True)


SQUARE = np.array([[0.145, -0.16], [0.145, 0.16], [-0.095, 0.16], [-0.095, -0.16]])[::-1]  # CCW below
SQUARE = support_polygon(SQUARE)


# ---------------------------------------------------------------------- geometry
def test_avoidance_angle_geometry():
    p = np.zeros(2)
    assert float(avoidance_angle(p, [1, 0], [2, 0])) == pytest.approx(0.0)
    assert float(avoidance_angle(p, [1, 0], [-2, 0])) == pytest.approx(math.pi)
    assert float(avoidance_angle(p, [1, 0], [0, 3])) == pytest.approx(math.pi / 2)
    assert float(avoidance_angle([1, 1], [2, 2], [1, 3])) == pytest.approx(math.pi / 4)
    a = avoidance_angle(np.zeros((3, 2)), [[1, 0], [0, 1], [0, 0]], [[1, 1]] * 3)
    assert a[:2] == pytest.approx([math.pi / 4] * 2)
    assert math.isnan(a[2])   # P == Q: no fall direction


def test_polygon_edges_outward_and_nearest():
    e = polygon_edges(SQUARE)
    centre = SQUARE.mean(axis=0)
    assert np.all(np.sum((e.start - centre) * e.normal, axis=1) > 0)
    assert nearest_on_boundary([0.3, 0.0], SQUARE) == pytest.approx([0.145, 0.0])
    assert nearest_on_boundary([0.3, 0.3], SQUARE) == pytest.approx([0.145, 0.16])


# ---------------------------------------------------------------------- FTB
def test_ftb_features_separate_crest():
    still = features_of(state([0.02, 0, 0.75], [0, 0, 0], SQUARE))
    assert still.valid and still.separatrix_margin < 0
    # CoM 8.6 cm behind the toe edge: the crest speed is sqrt(2 g L (1 - cos theta)) ~ 0.31 m/s
    th = math.atan2(-0.086, 0.75)
    v_crest = math.sqrt(2 * 9.81 * math.hypot(0.086, 0.75) * (1 - math.cos(th))) * 0.75 / math.hypot(0.086, 0.75)
    slow = features_of(state([0.059, 0, 0.75], [0.95 * v_crest, 0, 0], SQUARE))
    fast = features_of(state([0.059, 0, 0.75], [1.05 * v_crest, 0, 0], SQUARE))
    assert slow.energy_ratio < 1 < fast.energy_ratio
    assert slow.separatrix_margin < 0 < fast.separatrix_margin
    assert fast.edge_normal == pytest.approx([1, 0])


def test_ftb_thin_strip_and_single_foot_edges_do_not_fire():
    # feet rocking on their toes: the touching corners are a strip a few mm deep; the CoM is behind it
    strip = support_polygon([[0.145, 0.16], [0.145, 0.02], [0.143, -0.02], [0.145, -0.16]])
    f = features_of(state([0.03, 0, 0.745], [0.1, 0, 0], strip))
    assert f.edge_normal[0] > 0.99 and f.separatrix_margin < 0
    # one foot loaded (the other just above the ground): the CoM over the gap is not a fall over the inner edge
    left = support_polygon([[0.145, 0.16], [0.145, 0.02], [-0.095, 0.02], [-0.095, 0.16]])
    f = features_of(state([0.02, 0.0, 0.74], [0.0, 0.0, 0.0], left))
    assert f.separatrix_margin < 0


def _obs(t, s, **inputs):
    return Observation(int(round(t * 1e9)), np.zeros(M.njoints), np.zeros(M.njoints), s, "", dict(inputs))


def test_ftb_state_machine_debounce_edge_reset():
    mon = FtbMonitor(FtbConfig(debounce_ms=10.0, robot_weight=570.0))
    falling = state([0.059, 0, 0.75], [0.5, 0, 0], SQUARE)
    quiet = state([0.02, 0, 0.75], [0, 0, 0], SQUARE)
    assert mon.step(_obs(0.0, quiet)).state is FtbState.BALANCED
    events = []
    for k in range(1, 12):
        st = mon.step(_obs(0.002 * k, falling))
        events.append(st.event)
        if k <= 5:
            assert st.state is FtbState.BALANCED  # 10 ms not yet held (first outside tick at 2 ms)
    assert sum(e is not None for e in events) == 1   # once, on the edge
    ev = next(e for e in events if e is not None)
    assert ev.trigger_mode == "ftb" and ev.fall_direction == pytest.approx(0.0) and math.isfinite(ev.control_duration)
    assert mon.state is FtbState.FALLING
    mon.reset()
    assert mon.state is FtbState.BALANCED and mon.event is None
    # sim time going back resets too
    for k in range(8):
        mon.step(_obs(1.0 + 0.002 * k, falling))
    assert mon.state is FtbState.FALLING
    assert mon.step(_obs(0.0, quiet)).state is FtbState.BALANCED
    assert {(t.source, t.target) for t in TRANSITIONS} >= {(FtbState.BALANCED, FtbState.FALLING),
                                                         (FtbState.FALLING, FtbState.FALLEN)}


def test_ftb_fixed_mode_and_config():
    cfg = FtbConfig.from_params({**params.defaults("ftb_monitor"), "mode": "fixed"})
    assert cfg.mode is TriggerMode.FIXED
    mon = FtbMonitor(cfg)
    quiet = state([0.02, 0, 0.75], [0, 0, 0], SQUARE)
    assert mon.step(_obs(0.64, quiet, push_end_time=0.6)).event is None
    ev = mon.step(_obs(0.65, quiet, push_end_time=0.6)).event
    assert ev is not None and ev.trigger_mode == "fixed"
    with pytest.raises(ValueError):
        FtbConfig.from_params({"no_such_key": 1})


# ---------------------------------------------------------------------- stepping zone
def test_stepping_zone_shape():
    q = standing_q()
    z1 = stepping_zone(M, q, "l", 0.15, [1, 0], M.com(q), hip_drop=0.08)
    z2 = stepping_zone(M, q, "l", 0.30, [1, 0], M.com(q), hip_drop=0.08)
    assert z2.half_extent_eq8 == pytest.approx(2 * z1.half_extent_eq8)          # eq. 8 is linear in dT
    legs = M.limits.velocity[[M.joint_index(f"{s}_{j}") for s in "lr" for j in ("hip_yaw", "knee")]]
    assert np.all(z1.gamma >= legs.min() - 1e-9) and np.all(z1.gamma <= legs.max() + 1e-9)
    c = z1.center[:2]
    assert z1.contains([c + [0.12, 0.05]], [z1.center[2]])[0]      # ahead: inside
    assert not z1.contains([c - [0.05, 0.0]], [z1.center[2]])[0]   # behind the separatrix
    assert not z1.contains([c + [1.0, 0.0]], [z1.center[2]])[0]    # beyond the legs
    assert not z1.contains([z1.stance_pose[:2] + [0.02, 0.0]], [0.0])[0]  # on the stance sole
    assert not z1.contains([c + [0.12, 0.0]], [z1.center[2] + 1.0])[0]  # beyond the hip yaw
    zr = stepping_zone(M, q, "r", 0.15, [1, 0], M.com(q), hip_drop=0.08)
    assert zr.reach_radius == pytest.approx(z1.reach_radius, abs=1e-3)
    assert zr.center[1] == pytest.approx(-z1.center[1], abs=1e-3)



def test_zone_cells_within_the_step_length_cap():
    q = standing_q()
    z = stepping_zone(M, q, "l", 0.25, [1, 0], M.com(q), hip_drop=0.08)
    M.forward(q)
    start = M.frame_placement(M.sole_frame["l"]).translation[:2].copy()   # the swing sole now
    cfg = ss.SearchConfig(cell_xy=0.03, cell_yaw=0.1)
    full = ss.zone_cells(z, cfg, [])
    capped = ss.zone_cells(z, dataclasses.replace(cfg, max_step_length=0.2), [], start)
    d_full = np.hypot(full[:, 0] - start[0], full[:, 1] - start[1])
    d_cap = np.hypot(capped[:, 0] - start[0], capped[:, 1] - start[1])
    assert d_full.max() > 0.2 and 0 < len(capped) < len(full)
    assert d_cap.max() <= 0.2 + 1e-12
    assert len(capped) == int(np.sum(d_full <= 0.2))              # exactly the full grid's cells within the cap
    assert len(ss.zone_cells(z, dataclasses.replace(cfg, max_step_length=0.2), [])) == len(full)   # no start: no cap

# ---------------------------------------------------------------------- search
def _reference(cells, pivot, q2, target, local):
    """Slow per-cell reference: hull, inside, nearest boundary point, alpha."""
    out = []
    for c in cells:
        corners = ss.sole_corners_at(c[None], local)[0]
        poly = support_polygon(np.vstack([corners, pivot]))
        if point_in_polygon_margin(q2, poly) > 0:
            out.append(1e3)
        else:
            p2 = nearest_on_boundary(q2, poly)
            out.append(float(avoidance_angle(p2, q2, target)))
    return np.array(out)


def test_search_picks_known_optimum():
    local = M.sole_corners_local["l"][:, :2]
    pivot = np.array([[0.145, -0.16]])
    q2 = np.array([0.30, 0.05])
    target = np.array([1.2, 0.0])
    rng = np.random.default_rng(3)
    cells = np.column_stack([rng.uniform(-0.1, 0.5, 400), rng.uniform(0.1, 0.6, 400), rng.uniform(-0.6, 0.6, 400)])
    ref = _reference(cells, pivot, q2, target, local)
    falls = ref < 1e3
    r = ss._cells(ss.StepCase.STEP_LEFT, cells[falls], pivot, q2, target, np.zeros(3), local, ss.SearchConfig())
    i = int(np.argmax(ref[falls]))
    assert r.landing == pytest.approx(cells[falls][i])
    assert r.alpha2 == pytest.approx(ref[falls][i], abs=1e-9)
    # with capturing cells present, a capture wins over every fall
    r2 = ss._cells(ss.StepCase.STEP_LEFT, cells, pivot, q2, target, np.zeros(3), local, ss.SearchConfig())
    assert r2.captured == bool(np.any(~falls))
    # hand-made: three landings; the one whose sole covers Q2 captures
    hand = np.array([[0.0, 0.45, 0.0], [0.30, 0.08, 0.0], [0.1, 0.6, 0.3]])
    r3 = ss._cells(ss.StepCase.STEP_LEFT, hand, pivot, q2, target, np.zeros(3), local, ss.SearchConfig())
    assert r3.captured and r3.landing == pytest.approx(hand[1])
    # the vectorised inside depth is a lower bound of the exact one
    pts = np.concatenate([ss.sole_corners_at(hand, local), np.broadcast_to(pivot, (3, 1, 2))], axis=1)
    exact = ss._inside_margin(pts[1:2], q2)[0]
    assert 0 < r3.margin <= exact + 1e-12


# ---------------------------------------------------------------------- inertia shaping
def test_delayed_capture_point_is_the_linear_pendulum_with_the_cop_held():
    """xi(t) = p + (xi0 - p) exp(omega t) against an integration of c'' = omega^2 (c - p); and predict_touchdown's
    cop_delay moves Q2 away from each case's pivot along pivot -> Q2 (0 leaves it as it was)."""
    from scipy.integrate import solve_ivp

    g, z, tau = 9.81, 0.74, 0.15
    w = math.sqrt(g / z)
    c0, v0, p = np.array([0.05, -0.02]), np.array([0.6, -0.15]), np.array([0.12, -0.08])
    sol = solve_ivp(lambda t, y: np.r_[y[2:], w * w * (y[:2] - p)], (0.0, tau), np.r_[c0, v0], rtol=1e-11, atol=1e-12)
    c, v = sol.y[:2, -1], sol.y[2:, -1]
    got = ss.delayed_capture_point((c0 + v0 / w)[None], p[None], np.array([z]), tau, g)[0]
    assert got == pytest.approx(c + v / w, abs=1e-8)
    com, vel = np.array([0.03, 0.0, 0.74]), np.array([0.5, -0.1, 0.0])
    pivots = [np.array([[0.12, 0.07]]), np.array([[0.12, -0.07]])]
    G0, _, Q0 = ss.predict_touchdown(com, vel, pivots, 0.25)
    G1, _, Q1 = ss.predict_touchdown(com, vel, pivots, 0.25, cop_delay=0.0)
    assert np.array_equal(Q0, Q1)
    _, _, Qd = ss.predict_touchdown(com, vel, pivots, 0.25, cop_delay=tau)
    for k, pv in enumerate(pivots):
        a, b = Q0[k] - pv[0], Qd[k] - pv[0]
        assert abs(a[0] * b[1] - a[1] * b[0]) < 1e-9 * np.linalg.norm(b) and b @ a > 0   # same ray from the pivot
        assert np.linalg.norm(b) / np.linalg.norm(a) == pytest.approx(math.exp(math.sqrt(g / G0[k, 2]) * tau))



def test_capture_offset_moves_q2_along_the_touchdown_velocity():
    """predict_touchdown's offset: Q2 moved exactly ``offset`` along the CoM's horizontal velocity at touchdown,
    G and the velocity untouched; 0 leaves Q2 as it was."""
    com, vel = np.array([0.03, 0.0, 0.74]), np.array([0.5, -0.1, 0.0])
    pivots = [np.array([[0.12, 0.07]]), np.array([[0.12, -0.07], [0.12, 0.07]])]
    G0, V0, Q0 = ss.predict_touchdown(com, vel, pivots, 0.25)
    G1, V1, Q1 = ss.predict_touchdown(com, vel, pivots, 0.25, offset=0.08)
    assert np.array_equal(G0, G1) and np.array_equal(V0, V1)
    for k in range(len(pivots)):
        d = Q1[k] - Q0[k]
        u = V0[k, :2] / np.linalg.norm(V0[k, :2])
        assert np.linalg.norm(d) == pytest.approx(0.08) and d @ u == pytest.approx(0.08)
    # at rest: no direction, no shift (never NaN)
    _, _, Qr = ss.predict_touchdown(np.array([0.0, 0.0, 0.74]), np.zeros(3), [np.array([[0.0, 0.0]])], 0.0,
                                    offset=0.08)
    assert np.allclose(Qr, 0.0)

def test_crb_inertia_jacobian_against_finite_differences():
    rng = np.random.default_rng(0)
    q = standing_q()
    q[3:7] = [0.05, 0.02, 0.1, 0.99]
    q[3:7] /= np.linalg.norm(q[3:7])
    q[7:] += 0.2 * rng.standard_normal(M.njoints)
    inertia, J = crb_inertia_and_jacobian(M, q)
    assert inertia == pytest.approx(M.crb_inertia(q), abs=1e-12)
    h = 1e-6
    fd = np.zeros_like(J)
    for j in range(M.njoints):
        qp, qm = q.copy(), q.copy()
        qp[7 + j] += h
        qm[7 + j] -= h
        fd[:, j] = (crb_inertia_vector(M.crb_inertia(qp)) - crb_inertia_vector(M.crb_inertia(qm))) / (2 * h)
    assert np.abs(J - fd).max() < 1e-6 * max(1.0, np.abs(fd).max())


def test_inertia_shaping_direction_and_progress():
    w = desired_angular_velocity([0, 0, 0], [1.2, 0, 0])
    assert w == pytest.approx([0, -1, 0])
    assert np.cross(w, [0, 0, 1])[0] < 0   # V_G = w x PG points away from T (eq. 11)
    q = standing_q()
    qd, info = shaping_velocities(M, q, [0.1, 0, 0], [1.2, 0, 0], 0.002)
    assert np.all(np.abs(qd) <= M.limits.velocity + 1e-9)
    assert info["residual"] < info["error"]


def test_box_distance_outside_inside_and_turned():
    box = ClearBox(np.array([1.0, 0.0, 0.4]), np.array([0.15, 0.3, 0.4]), 0.0)
    d, u = box_distance([[0.5, 0.0, 0.4], [1.0, 0.0, 1.0], [1.0, 0.0, 0.4], [0.85 - 0.3, 0.3 + 0.4, 0.4]], box)
    assert d[:3] == pytest.approx([0.35, 0.2, 0.0])
    assert d[3] == pytest.approx(0.5)
    assert u[0] == pytest.approx([-1, 0, 0]) and u[1] == pytest.approx([0, 0, 1])
    assert u[3] == pytest.approx([-0.6, 0.8, 0])
    turned = ClearBox(np.zeros(3), np.array([0.5, 0.1, 0.1]), math.pi / 2)   # long along y once turned
    d, u = box_distance([[0.0, 0.7, 0.0], [0.3, 0.0, 0.0]], turned)
    assert d == pytest.approx([0.2, 0.2])
    assert u[0] == pytest.approx([0, 1, 0]) and u[1] == pytest.approx([1, 0, 0])


def _sweep(q, qd, frames, horizon):
    """Each frame's shaping motion relative to the CoM over ``horizon``: (start, end) positions."""
    M.forward(q)
    Jg = M.com_jacobian(q)[:, 6:]
    out = {}
    for f in frames:
        J = M.frame_jacobian(q, f)[:3, 6:] - Jg
        p = M.frame_position(f)
        out[f] = (p, p + J @ qd * horizon)
    return out


def test_limb_sweep_guard_holds_the_joints_that_carry_a_limb_into_a_box():
    """The shaping alone swings a limb point; a box put where it would go makes the guard hold the joints carrying
    it there: every followed point then stays out of the clearance or moves away, and the shaping still acts."""
    q = standing_q()
    cfg = ShapingConfig()
    frames = ["l_shank", "r_shank", "l_forearm", "r_forearm", "l_hand", "r_hand"]
    qd0, info0 = shaping_velocities(M, q, [0.1, 0, 0], [1.2, 0, 0], 0.002, cfg=cfg)
    moves = _sweep(q, qd0, frames, cfg.sweep_horizon_s)
    name = max(frames, key=lambda f: np.linalg.norm(moves[f][1] - moves[f][0]))
    start, end = moves[name]
    assert np.linalg.norm(end - start) > 0.2   # the shaping moves it far enough for the test to mean something
    box = ClearBox(end + 0.08 * (end - start) / np.linalg.norm(end - start), np.full(3, 0.05))
    assert box_distance(start, box)[0][0] > cfg.sweep_clearance_m
    qd, info = shaping_velocities(M, q, [0.1, 0, 0], [1.2, 0, 0], 0.002, cfg=cfg, keep_clear=[box],
                                  sweep_frames=frames)
    assert info["swept"] and info["swept"][0][0] == name
    assert info["recruited"] < info0["recruited"]
    for f, (p0, p1) in _sweep(q, qd, frames, cfg.sweep_horizon_s).items():
        d0, d1 = box_distance(p0, box)[0][0], box_distance(p1, box)[0][0]
        assert d1 >= min(cfg.sweep_clearance_m, d0) - 1e-9, f
    assert np.abs(qd).max() > 0.1 and info["residual"] < info["error"]
    off = ShapingConfig(sweep_horizon_s=0.0)
    qd_off, _ = shaping_velocities(M, q, [0.1, 0, 0], [1.2, 0, 0], 0.002, cfg=off, keep_clear=[box],
                                   sweep_frames=frames)
    assert qd_off == pytest.approx(qd0)


# ---------------------------------------------------------------------- controller
def _controller_obs(t, inputs):
    q = standing_q()
    com = M.com(q)
    poly = support_polygon(np.vstack([M.sole_corners(s)[:, :2] for s in "lr"]))
    s = state(com + [0.04, 0, 0], [0.45, -0.1, 0.0], poly, cop=[0.144, 0.0, 0.0],
              feet_center=(M.frame_position("l_foot") + M.frame_position("r_foot")) / 2)
    return Observation(int(round(t * 1e9)), q[7:].copy(), np.zeros(M.njoints), s, "locomotion", inputs)


def _event(t):
    from humfall_ros.fall.ftb import FallEvent

    z = np.zeros(3)
    return FallEvent(int(round(t * 1e9)), "ftb", "test", z, z, False, z, z, 0.0, 0.8, 0.26, 1.001, 0.001, 0.1, z, z,
                     np.zeros((0, 2)))


TARGET = [{"name": "target", "position": [1.2, 0.0, 0.4], "size": [0.3, 0.6, 0.8], "yaw": 0.0, "is_target": True}]
IMU = (np.array([0.0, 0.0, 0.0, 1.0]), np.zeros(3))


def test_controller_releases_until_event_then_never():
    c = SafeFallController(config=SafeFallConfig.from_params(params.defaults("safe_fall_controller")))
    assert c.step(_controller_obs(0.5, {"obstacles": TARGET, "imu": IMU})) is None
    obs = _controller_obs(0.62, {"obstacles": TARGET, "imu": IMU, "fall_event": _event(0.62)})
    cmd = c.step(obs)
    assert cmd is not None and cmd.positions.shape == (M.njoints,)
    d = c.decision
    assert d.cell_count > 0 and d.case in {x.value for x in ss.StepCase}
    assert math.isfinite(d.touchdown_time) and d.search_time > 0
    for k in range(1, 5):  # keeps control, every tick a command
        assert c.step(_controller_obs(0.62 + 0.002 * k, {"obstacles": TARGET, "imu": IMU})) is not None


@pytest.mark.parametrize("obstacles,why", [
    ([], "no target"),
    ([{**TARGET[0], "position": [math.nan, 0.0, 0.4]}], "not finite"),
    ([{**TARGET[0], "position": [0.02, 0.0, 0.4]}], "inside the robot"),
])
def test_controller_bad_targets_do_not_step(obstacles, why):
    c = SafeFallController()
    cmd = c.step(_controller_obs(0.62, {"obstacles": obstacles, "imu": IMU, "fall_event": _event(0.62)}))
    assert cmd is not None
    assert c.decision.swing_side == "" and why in c.decision.reason


def test_controller_bad_events_and_inputs():
    c = SafeFallController()
    # an event from the future (sim time went back): ignored
    assert c.step(_controller_obs(0.3, {"obstacles": TARGET, "imu": IMU, "fall_event": _event(0.62)})) is None
    # a stale one: taken, noted, decided from now
    c.reset()
    assert c.step(_controller_obs(1.0, {"obstacles": TARGET, "imu": IMU, "fall_event": _event(0.62)})) is not None
    assert "old" in c.decision.reason
    # no IMU: holds the measured posture, never raises, never commandless
    c.reset()
    obs = _controller_obs(0.62, {"obstacles": TARGET, "fall_event": _event(0.62)})
    cmd = c.step(obs)
    assert cmd is not None and cmd.positions == pytest.approx(obs.joint_position)
    assert any("IMU" in r for r in c.reasons)


def test_inertia_shaping_turn_direction_turns_the_fall_away():
    """``turn`` (ours): V_G = omega_d x PG is across the fall direction PG, away from T (raises alpha)."""
    from humfall_ros.fall.geometry import avoidance_angle

    p, t = np.array([0.0, 0.0, 0.0]), np.array([1.2, 0.0, 0.0])
    for heading in np.radians([100.0, 146.0, -120.0, 60.0]):
        g = np.array([0.1 * math.cos(heading), 0.1 * math.sin(heading), 0.75])
        w = desired_angular_velocity(p, t, g, "turn")
        v = np.cross(w, g - p)
        assert abs(v[:2] @ (g - p)[:2]) < 1e-9                      # across the fall, not along it
        a0 = float(avoidance_angle(p[:2], g[:2], t[:2]))
        a1 = float(avoidance_angle(p[:2], g[:2] + 1e-3 * v[:2], t[:2]))
        assert a1 > a0                                                 # turns the fall away from T
    # falling straight at or away from T: the paper's direction
    g = np.array([0.1, 0.0, 0.75])
    assert desired_angular_velocity(p, t, g, "turn") == pytest.approx(desired_angular_velocity(p, t))
    with pytest.raises(ValueError):
        desired_angular_velocity(p, t, g, "sideways")


@pytest.mark.parametrize("stood,only,sign,phase", [(0.005, False, -1.0, "shaping"), (0.6, False, 1.0, "shaping"),
                                                 (0.005, True, -1.0, "hold"), (0.6, True, 1.0, "shaping")])
def test_controller_slow_topple_after_a_captured_step_uses_the_settled_sign(stood, only, sign, phase):
    """Falling about the new support seen >= shaping_settled_s after touchdown: shaping_settled_sign; sooner:
    shaping_sign, or no shaping with shaping_settled_only."""
    cfg = SafeFallConfig.from_params({**params.defaults("safe_fall_controller"), "shaping_sign": -1.0,
                                      "shaping_settled_sign": 1.0, "shaping_settled_s": 0.2,
                                      "shaping_settled_only": only,
                                      # the constructed state's joints are the standing posture: the soles' hull
                                      # the capture balance reads the fall over is under the CoM, not behind it
                                      "capture_balance": False})
    c = SafeFallController(config=cfg)
    c.step(_controller_obs(0.62, {"obstacles": TARGET, "imu": IMU, "fall_event": _event(0.62)}))
    # as after the swing of a step predicted to capture: landed, waiting for the robot to fall
    t0 = 1.0
    c.phase, c.touchdown_at, c.falling_since = "landed", t0, None
    c.target = np.array([1.2, 0.0])
    c.hold = c.last_command.copy()
    q = standing_q()
    poly = support_polygon(np.vstack([M.sole_corners(s)[:, :2] for s in "lr"]))
    lean = math.radians(25.0)   # beyond shaping_lean_deg, falling back, away from the target
    cop = np.array([-0.095, 0.0, 0.0])
    com = cop + 0.75 * np.array([-math.sin(lean), 0.0, math.cos(lean)])
    s = state(com, [-0.3, 0.0, -0.1], poly, cop=cop)
    for k in range(7):
        t = t0 + stood + 0.002 * k
        cmd = c.step(Observation(int(round(t * 1e9)), q[7:].copy(), np.zeros(M.njoints), s, "safe_fall",
                                 {"obstacles": TARGET, "imu": IMU}))
        assert cmd is not None
    assert c.phase == phase and c.shaping_config.sign == sign
    assert any((f"sign {sign:+.0f}" if phase == "shaping" else "no inertia shaping") in r for r in c.reasons)


def test_shaping_recruit_sets_name_the_joints_shaping_may_move():
    """'all' (the paper, the default) moves every joint; 'pitch' the chest, hip and shoulder pitch; 'upper' leaves the
    legs alone (flexing the hips swings the legs: in walking_push the swinging foot kicked the target before the
    limb-sweep guard); an unknown set is refused."""
    from humfall_ros import params
    from humfall_ros.fall.controller import SafeFallConfig, SafeFallController

    d0 = params.defaults("safe_fall_controller")
    moved = {}
    for rec in ("all", "pitch", "upper"):
        c = SafeFallController(config=SafeFallConfig.from_params({**d0, "shaping_recruit": rec}))
        moved[rec] = {n for n, r in zip(c.m.joint_names, c._recruit) if r}
    assert any("hip_pitch" in n for n in moved["pitch"]) and any("chest_pitch" in n for n in moved["pitch"])
    assert moved["upper"] and moved["upper"] < moved["pitch"] < moved["all"] == set(c.m.joint_names)
    assert not any(k in n for n in moved["upper"] for k in ("hip", "knee", "ankle"))
    with pytest.raises(ValueError, match="shaping_recruit"):
        SafeFallController(config=SafeFallConfig.from_params({**d0, "shaping_recruit": "legs"}))


def test_sweep_summary_counts_steps_that_land_as_predicted():
    """``humfall sweep``'s summary: per controller, the steps whose touchdown (50 ms), landing (3 cm / 5 deg) and
    flatness (3 deg) are within issue 11's goals, and the worst of each; runs without a step are left out."""
    from humfall_ros.sim import fall_sweep as sweep

    def row(kind, angle, pred, fell=True):
        return {"controller": kind, "push_angle_deg": angle, "push_n": 300.0, "fell": fell, "fall_direction_deg": 0.0,
                "avoidance_angle_deg": 90.0 if fell else None, "avoidance_angle_p2_deg": 120.0 if fell else None,
                "predicted_avoidance_deg": None, "min_target_distance_m": 0.5, "lead_time_s": 1.0, "prediction": pred}

    good = {"touchdown_error_s": -0.02, "landing_error_m": 0.01, "landing_yaw_error_deg": 0.5, "landing_tilt_deg": 0.4}
    late = {**good, "touchdown_error_s": 0.08}
    short = {**good, "landing_error_m": 0.16}
    rows = [row("stepping", 0, good, fell=False), row("stepping", 30, late), row("stepping", 60, short),
            row("none", 0, None)]
    summ = sweep.summary(rows)
    p = summ["stepping"]["prediction"]
    assert (p["steps"], p["within_goals"]) == (3, 1)
    assert p["worst_touchdown_error_s"] == pytest.approx(0.08) and p["worst_landing_error_m"] == pytest.approx(0.16)
    assert "prediction" not in summ["none"] and summ["stepping"]["fell"] == 2
    assert "yes" in sweep.row_line(rows[0]) and "80" in sweep.row_line(rows[1])


def test_sweep_set_reaches_every_run_and_a_bad_key_is_refused_before_the_first(monkeypatch, tmp_path, capsys):
    """``humfall sweep --set KEY=VALUE``: the override is in every run's scenario; an unknown
    controller parameter ends the command (exit 2, the name in the message) before any run."""
    from humfall_ros.sim import fall_runs as runs, fall_sweep as sweep

    seen = []

    def fake_run(sc, kind, duration=None, **kw):
        seen.append((kind, sc["params"].get("safe_fall_controller", {}).get("capture_depth_m")))
        raise StopIteration   # no simulation: what reached the run is the point

    monkeypatch.setattr(runs, "run", fake_run)
    with pytest.raises(StopIteration):
        sweep.main(["--directions", "0", "--controller", "stepping", "--out", str(tmp_path),
                    "--set", "params.safe_fall_controller.capture_depth_m=0.08"])
    assert seen == [("stepping", 0.08)]
    with pytest.raises(SystemExit) as e:
        sweep.main(["--directions", "0", "--controller", "stepping", "--out", str(tmp_path),
                    "--set", "params.safe_fall_controller.capture_depht_m=0.08"])
    assert e.value.code == 2 and "capture_depht_m" in capsys.readouterr().err
    assert len(seen) == 1   # refused before a run
    assert not (tmp_path / "sweep.json").exists()


def _fall_heading_reference(p2, polygon, com, com_velocity, horizon: float, g: float = 9.81) -> np.ndarray:
    """Slow reference of step_search._alpha_edge's heading, from the polygon itself: P2 inside an edge topples about
    that edge (the linear pendulum across it, none along it); P2 at a corner, the point pendulum. Unit (2,), NaN at
    rest on P2."""
    p2 = np.asarray(p2, float)[:2]
    c, v = np.asarray(com, float), np.asarray(com_velocity, float)[:2]
    w = math.sqrt(g / c[2])
    r, ch, sh = c[:2] - p2, math.cosh(w * horizon), math.sinh(w * horizon)
    out = r * ch + v / w * sh
    edges = polygon_edges(polygon)
    k = int(np.argmin(np.linalg.norm(np.array([nearest_on_boundary(p2, [a, b]) for a, b in
                                               zip(edges.start, edges.end)]) - p2, axis=1)))
    if min(np.linalg.norm(p2 - edges.start[k]), np.linalg.norm(p2 - edges.end[k])) >= 1e-3:
        n = edges.normal[k]
        e = np.array([-n[1], n[0]])
        out = e * (e @ r + (e @ v) * horizon) + n * ((n @ r) * ch + (n @ v) / w * sh)
    norm = np.linalg.norm(out)
    return out / norm if norm > 1e-12 else np.full(2, np.nan)


def _angle_to(h, p2, target) -> float:
    t = np.asarray(target, float) - p2
    return math.acos(float(np.clip(h @ t / (np.linalg.norm(h) * np.linalg.norm(t)), -1.0, 1.0)))


def test_fall_heading_against_the_edge_and_point_pendulums():
    """The alpha of the fall about the new support (step_search._alpha_edge) and its slow reference: toppling about
    an edge (the CoP follows the CoM along it: no acceleration along the edge) and about a corner (the point
    pendulum), against solve_ivp of the linear pendulum; at a corner and a long horizon, paper 1's P2 -> Q2."""
    from scipy.integrate import solve_ivp

    g, z, T = 9.81, 0.74, 0.5
    w2 = g / z
    square = np.array([[0.0, -0.1], [0.2, -0.1], [0.2, 0.1], [0.0, 0.1]])   # CCW
    com, vel = np.array([0.15, 0.02, z]), np.array([0.6, 0.35, 0.0])
    target = np.array([0.9, 0.8])
    # P2 on the front edge (x = 0.2), Q2 beyond it (P2 its nearest point): the pendulum acts along +x only
    p2, q2 = np.array([0.2, 0.03]), np.array([0.45, 0.03])
    sol = solve_ivp(lambda t, y: np.r_[y[2:], w2 * (y[0] - p2[0]), 0.0], (0, T), np.r_[com[:2], vel[:2]],
                    rtol=1e-11, atol=1e-12)
    want = sol.y[:2, -1] - p2
    assert _fall_heading_reference(p2, square, com, vel, T, g) == pytest.approx(want / np.linalg.norm(want), abs=1e-7)
    got = ss._alpha_edge(p2[:1], p2[1:], q2, com, vel, target, square[None], T, g)[0]
    assert got == pytest.approx(_angle_to(want, p2, target), abs=1e-7)
    # P2 at the corner (0.2, 0.1): the point pendulum
    p2, q2 = np.array([0.2, 0.1]), np.array([0.5, 0.3])
    sol = solve_ivp(lambda t, y: np.r_[y[2:], w2 * (y[:2] - p2)], (0, T), np.r_[com[:2], vel[:2]],
                    rtol=1e-11, atol=1e-12)
    want = sol.y[:2, -1] - p2
    assert _fall_heading_reference(p2, square, com, vel, T, g) == pytest.approx(want / np.linalg.norm(want), abs=1e-7)
    got = ss._alpha_edge(p2[:1], p2[1:], q2, com, vel, target, square[None], T, g)[0]
    assert got == pytest.approx(_angle_to(want, p2, target), abs=1e-7)
    xi = com[:2] + vel[:2] / math.sqrt(w2)
    far = ss._alpha_edge(p2[:1], p2[1:], q2, com, vel, target, square[None], 5.0, g)[0]
    assert far == pytest.approx(_angle_to(xi - p2, p2, target), abs=1e-4)
    # at rest on P2: no heading
    assert math.isnan(ss._alpha_edge(p2[:1], p2[1:], q2, [0.2, 0.1, z], [0, 0, 0], target, square[None], T, g)[0])
    assert np.all(np.isnan(_fall_heading_reference(p2, square, [0.2, 0.1, z], [0, 0, 0], T, g)))


def _falling_cells(seed: int, n: int):
    """Landing cells of a left step whose Q2 lies outside every cell's hull (a predicted fall for each), with P2 and
    the hull vertices per cell: (local sole, cells, pivot, G and dG/dt at touchdown, Q2, T, P2 x, P2 y, vertices)."""
    local = M.sole_corners_local["l"][:, :2]
    rng = np.random.default_rng(seed)
    cells = np.column_stack([rng.uniform(0.2, 0.45, n), rng.uniform(-0.35, 0.1, n), rng.uniform(-0.3, 0.3, n)])
    pivot = np.array([[0.145, -0.03], [0.145, -0.17]])
    g_td, v_td = np.array([0.2, -0.05, 0.72]), np.array([0.7, -0.4, -0.1])
    q2 = g_td[:2] + v_td[:2] / math.sqrt(9.81 / g_td[2]) + np.array([0.25, -0.2])   # outside every hull
    target = np.array([1.3, 0.2])
    p2x, p2y = ss._hull_core(cells, local, pivot, q2).p2()
    verts = np.concatenate([ss.sole_corners_at(cells, local), np.broadcast_to(pivot, (len(cells), 2, 2))], axis=1)
    return local, cells, pivot, g_td, v_td, q2, target, p2x, p2y, verts


def test_search_alpha_edge_equals_fall_heading_on_the_cells_polygon():
    """step_search's vectorised alpha of the fall about the new support (the edge's normal from Q2 - P2) equals the
    slow reference's angle to T on each cell's own hull (edge cells and corner cells alike)."""
    local, cells, pivot, g_td, v_td, q2, target, p2x, p2y, verts = _falling_cells(3, 40)
    got = ss._alpha_edge(p2x, p2y, q2, g_td, v_td, target, verts, 0.5)
    corners = 0
    for i, c in enumerate(cells):
        poly = support_polygon(np.vstack([ss.sole_corners_at(c[None], local)[0], pivot]))
        p2 = np.array([p2x[i], p2y[i]])
        hd = _fall_heading_reference(p2, poly, g_td, v_td, 0.5)
        assert got[i] == pytest.approx(_angle_to(hd, p2, target), abs=1e-6), i
        corners += np.min(np.linalg.norm(poly - p2, axis=1)) < 1e-3
    assert 0 < corners < len(cells)   # both kinds seen


@pytest.mark.parametrize("ranking", ["paper", "edge"])
def test_falls_rank_by_the_configured_alpha2(ranking):
    """``fall_ranking``: the best fall cell is the one with the largest paper angle or alpha2_edge; the candidates
    come out in that order, and an unknown ranking is refused."""
    local, cells, pivot, g_td, v_td, q2, target, p2x, p2y, verts = _falling_cells(5, 60)
    paper = ss._alpha(p2x, p2y, q2, target)
    edge = ss._alpha_edge(p2x, p2y, q2, g_td, v_td, target, verts, 0.5)
    want = {"paper": paper, "edge": edge}[ranking]
    assert np.argmax(paper) != np.argmax(edge)    # the two models disagree on this case, so the ranking matters
    cfg = ss.SearchConfig(fall_ranking=ranking, fall_heading_horizon=0.5)
    got = ss.ranked_cells(ss.StepCase.STEP_LEFT, cells, pivot, q2, target, g_td, local, cfg, limit=10, v_td=v_td)
    assert not got[0].captured
    assert got[0].alpha2 == pytest.approx(want.max(), abs=1e-9)
    assert np.allclose(got[0].landing, cells[np.argmax(want)])
    assert all(a.alpha2 >= b.alpha2 - 1e-12 for a, b in zip(got, got[1:]))
    best = ss._cells(ss.StepCase.STEP_LEFT, cells, pivot, q2, target, g_td, local, cfg)   # no velocity: the paper's
    assert best.alpha2 == pytest.approx(paper.max(), abs=1e-9)
    with pytest.raises(ValueError, match="fall_ranking"):
        ss.SearchConfig(fall_ranking="sideways")


def test_hip_flexion_profile_rises_holds_and_releases():
    from humfall_ros.control.standing import hip_flexion_profile

    args = (0.3, 0.15, 0.6, 1.0)
    assert hip_flexion_profile(-0.01, *args) == 0.0 and hip_flexion_profile(0.0, *args) == 0.0
    assert hip_flexion_profile(0.075, *args) == pytest.approx(0.15)       # half way up a half cosine
    assert hip_flexion_profile(0.15, *args) == pytest.approx(0.3) == hip_flexion_profile(0.74, *args)
    assert hip_flexion_profile(0.75 + 0.5, *args) == pytest.approx(0.15)
    assert hip_flexion_profile(1.76, *args) == 0.0 and hip_flexion_profile(0.5, 0.0, 0.15, 0.6, 1.0) == 0.0
    ts = np.linspace(0.0, 2.0, 401)
    f = np.array([hip_flexion_profile(t, *args) for t in ts])
    assert np.all(f >= 0.0) and np.all(f <= 0.3 + 1e-12) and np.max(np.abs(np.diff(f))) < 0.3 * 0.005 * 3.2 / 0.15


@pytest.mark.parametrize("target", ["middle", "spine"])
def test_capture_balance_settle_target_and_hip_strategy(target):
    """After a captured step the balance holds the CoM at the soles' middle, or (``settle_target: spine``) at the
    point of the segment between the soles' centres nearest the capture point; the hip strategy
    (``balance_hip_flex_rad``) flexes both hips by its profile on top and changes no other joint."""
    base = {**params.defaults("safe_fall_controller"), "settle_s": 0.0, "settle_target": target}
    cmds = {}
    for flex in (0.0, 0.3):
        c = SafeFallController(config=SafeFallConfig.from_params({**base, "balance_hip_flex_rad": flex}))
        c.step(_controller_obs(0.62, {"obstacles": TARGET, "imu": IMU, "fall_event": _event(0.62)}))
        c.phase, c.touchdown_at, c.target = "landed", 1.0, np.array([1.2, 0.0])
        c.hold = c.last_command.copy()
        q = standing_q()
        poly = support_polygon(np.vstack([M.sole_corners(s)[:, :2] for s in "lr"]))
        feet = (M.frame_position("l_foot") + M.frame_position("r_foot")) / 2
        com = M.com(q)
        # the capture point ahead and to the left: (com + [0.1, 0.05]) + [0.0, 0.02]
        s = state(com + [0.1, 0.05, 0.0], [0.0, 0.2 / math.sqrt(9.81 / com[2]) * 0.1, 0.0], poly, feet_center=feet)
        out = []
        for t in (1.0, 1.0 + 0.15 + 0.3):
            out.append(c.step(Observation(int(round(t * 1e9)), q[7:].copy(), np.zeros(M.njoints), s, "safe_fall",
                                          {"obstacles": TARGET, "imu": IMU})).positions)
        cmds[flex] = out
        centres = [M.sole_corners(sd)[:, :2].mean(axis=0) for sd in "lr"]
        if target == "middle":
            want = np.vstack([M.sole_corners(sd)[:, :2] for sd in "lr"]).mean(axis=0)
        else:   # the soles side by side: the segment runs along y, at the capture point's y
            cp = np.asarray(s.capture_point)[:2]
            assert centres[1][1] < cp[1] < centres[0][1]
            want = np.array([centres[0][0] + (centres[1][0] - centres[0][0]) * (cp[1] - centres[0][1])
                             / (centres[1][1] - centres[0][1]), cp[1]])
        assert np.allclose(c.balancer.reference + feet[:2], want, atol=1e-9)
    hips = [M.joint_index(f"{sd}_hip_pitch") for sd in "lr"]
    others = [i for i in range(M.njoints) if i not in hips]
    assert np.allclose(cmds[0.3][0], cmds[0.0][0])                        # the profile starts at 0
    assert np.allclose(cmds[0.3][1][hips], cmds[0.0][1][hips] - 0.3)      # held, flexed (pitch < 0)
    assert np.allclose(cmds[0.3][1][others], cmds[0.0][1][others])


def test_hip_strategy_shrinks_with_the_capture_points_margin_in_the_soles_hull():
    """``balance_hip_margin_m``: the hip strategy's flexion is scaled by 1 - margin / balance_hip_margin_m (clipped
    to [0, 1]), the margin being the capture point's inside both soles' hull when the balance starts."""
    # (no inertia shaping: the capture point 20 cm ahead reads as falling about the soles, and shaping would take
    # over from the balance)
    base = {**params.defaults("safe_fall_controller"), "settle_s": 0.0, "inertia_shaping": False}
    q = standing_q()
    poly = support_polygon(np.vstack([M.sole_corners(s)[:, :2] for s in "lr"]))
    feet = (M.frame_position("l_foot") + M.frame_position("r_foot")) / 2
    com = M.com(q)
    hips = [M.joint_index(f"{sd}_hip_pitch") for sd in "lr"]
    seen = []
    for dx in (0.0, 0.06, 0.2):   # the capture point 0 / 6 / 20 cm ahead of the CoM
        s = state(com, [dx / math.sqrt(com[2] / 9.81), 0.0, 0.0], poly, feet_center=feet)
        margin = point_in_polygon_margin(np.asarray(s.capture_point)[:2], poly)
        got = {}
        for flex, scale in ((0.0, 0.1), (0.3, 0.1)):
            c = SafeFallController(config=SafeFallConfig.from_params({**base, "balance_hip_flex_rad": flex,
                                                                      "balance_hip_margin_m": scale}))
            c.step(_controller_obs(0.62, {"obstacles": TARGET, "imu": IMU, "fall_event": _event(0.62)}))
            c.phase, c.touchdown_at, c.target, c.falling_since = "landed", 1.0, np.array([1.2, 0.0]), None
            c.hold = c.last_command.copy()
            for t in (1.0, 1.45):
                cmd = c.step(Observation(int(round(t * 1e9)), q[7:].copy(), np.zeros(M.njoints), s, "safe_fall",
                                         {"obstacles": TARGET, "imu": IMU})).positions
            assert c.phase == "landed"
            assert c.balance_margin == pytest.approx(margin, abs=1e-9)
            got[flex] = cmd
        want = 0.3 * min(1.0, max(0.0, 1.0 - margin / 0.1))
        seen.append(want)
        assert np.allclose(got[0.0][hips] - got[0.3][hips], want, atol=1e-9)
    assert seen[0] == 0.0 and 0.0 < seen[1] < 0.3 and seen[2] == 0.3   # deep / shallow / outside


def test_capture_balance_lateral_roll_option():
    """``balance_lateral_gain`` (off by default): the multi-contact executor's lateral balance on top of the capture
    balance: both ankle rolls get ``lateral_roll`` of the sensed soles' centres, the hip rolls its negative, nothing
    else changes."""
    from humfall_ros.control.standing import lateral_roll

    base = {**params.defaults("safe_fall_controller"), "settle_s": 0.0, "inertia_shaping": False}
    q = standing_q()
    poly = support_polygon(np.vstack([M.sole_corners(s)[:, :2] for s in "lr"]))
    feet = (M.frame_position("l_foot") + M.frame_position("r_foot")) / 2
    com = M.com(q)
    s = state(com, [0.0, 0.1, 0.0], poly, feet_center=feet)
    # the robot rolled 0.2 rad (the IMU): its CoM sideways of both soles, past the end of their segment
    from scipy.spatial.transform import Rotation

    imu = (Rotation.from_euler("x", 0.2).as_quat(), np.zeros(3))
    out = {}
    for gain in (0.0, 1.5):
        c = SafeFallController(config=SafeFallConfig.from_params({**base, "balance_lateral_gain": gain}))
        c.step(_controller_obs(0.62, {"obstacles": TARGET, "imu": IMU, "fall_event": _event(0.62)}))
        c.phase, c.touchdown_at, c.target, c.falling_since = "landed", 1.0, np.array([1.2, 0.0]), None
        c.hold = c.last_command.copy()
        out[gain] = c.step(Observation(int(round(1.0 * 1e9)), q[7:].copy(), np.zeros(M.njoints), s, "safe_fall",
                                       {"obstacles": TARGET, "imu": imu})).positions
    from humfall_ros.control.step_control import configuration_from_sensors

    M.forward(configuration_from_sensors(M, q[7:], imu[0], com))
    left, right = (M.sole_corners(sd)[:, :2].mean(axis=0) for sd in "lr")
    assert min(abs(com[1] - left[1]), abs(com[1] - right[1])) > 0.03 and (com[1] - left[1]) * (com[1] - right[1]) > 0
    d = lateral_roll(com, s.com_velocity, left, right, 1.5, 0.2, 0.2)
    assert abs(d) > 0.01
    ankles = [M.joint_index(f"{sd}_ankle_roll") for sd in "lr"]
    hips = [M.joint_index(f"{sd}_hip_roll") for sd in "lr"]
    others = [i for i in range(M.njoints) if i not in ankles + hips]
    np.testing.assert_allclose(out[1.5][ankles] - out[0.0][ankles], d, atol=1e-9)
    np.testing.assert_allclose(out[1.5][hips] - out[0.0][hips], -d, atol=1e-9)
    np.testing.assert_allclose(out[1.5][others], out[0.0][others])


def test_sensed_soles_rebuild_the_true_soles_from_joints_imu_and_com():
    """``step_control.sensed_soles`` (the safe fall's decision, the give-up's hull, the capture balance, the lateral
    roll): a robot pitched 0.3 rad onto its toes and rolled 0.1 rad, its IMU reading the true orientation and the
    CoM the true one, gives the true sole corners; no usable IMU gives None."""
    import pinocchio as pin

    from humfall_ros.control.step_control import sensed_soles
    from humfall_ros.model.humanoid import SIDES

    joints = M.joint_vector(STANDING_POSTURE)
    quat = pin.Quaternion(pin.rpy.rpyToMatrix(0.1, 0.3, 0.2)).coeffs()
    q_true = M.configuration([0.4, -0.2, 0.7], quat, joints)
    M.forward(q_true)
    truth = {sd: M.sole_corners(sd)[:, :2].copy() for sd in SIDES}
    imu = M.frame_placement(M.imu_frame).rotation.copy()
    com = pin.centerOfMass(M.model, M.data, q_true).copy()
    M.forward(M.configuration([0, 0, 0], [0, 0, 0, 1], joints))   # the model left elsewhere
    q, soles = sensed_soles(M, joints, (pin.Quaternion(imu).coeffs(), np.zeros(3)), com)
    for sd in SIDES:
        np.testing.assert_allclose(soles[sd], truth[sd], atol=1e-9)
    np.testing.assert_allclose(q[:3], q_true[:3], atol=1e-9)
    M.forward(M.configuration(q_true[:3], [0, 0, 0, 1], joints))   # the same robot upright: other soles
    assert np.max(np.abs(M.sole_corners("l")[:, :2] - truth["l"])) > 0.05
    assert sensed_soles(M, joints, None, com) is None
    assert sensed_soles(M, joints, (np.full(4, np.nan), np.zeros(3)), com) is None
