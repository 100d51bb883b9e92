"""Walking runs through the suite's in-process loop (ClosedLoop) and their issue-10 metrics, against ground truth.

    python benchmarks/walk_loop.py [SPEED_KMH] [STEPS] [--set key=value ...]   # one JSON object

The scenario is config/scenarios/walking.yaml with ``walk.speed_kmh`` / ``walk.steps`` and the
given overrides; the controller is ``walking.controller.from_scenario`` (what the locomotion
node builds), run by ``ClosedLoop`` (what the ROS graph runs, tick for tick). Used by
benchmarks/bench_walking.py and test/test_walking_sim.py.
"""
from __future__ import annotations

import dataclasses
import math
import pathlib
import sys
import time

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))  # this checkout, not an installed copy

from humfall_ros import scenario as scenario_mod
from humfall_ros.dynamics.pendulum import GRAVITY
from humfall_ros.model.humanoid import SIDES, load_model, point_in_polygon_margin, support_polygon
from humfall_ros.sim.closed_loop import ClosedLoop
from humfall_ros.sim.sensors import SensorNoise
from humfall_ros.walking.controller import LocomotionController, from_scenario, yaw_of
from humfall_ros.walking.scenario import walk_schedule


@dataclasses.dataclass
class WalkResult:
    fell: bool
    speed_kmh: float
    steps: int
    zmp_rms_ss: float            # m, ground-truth CoP vs reference ZMP in single support
    zmp_max_ss: float
    zmp_rms_ss_est: float        # m, the estimator's CoP vs reference (what the stabiliser sees)
    zmp_rms_ss_foot: float       # m, ground-truth CoP vs reference, each relative to its stance sole (the true one
    zmp_max_ss_foot: float       # and the pattern's): the reference is a point on the footprint, not in the world
    cop_margin_ok_fraction: float  # walking ticks with the true CoP >= 1 cm inside the stance polygon
    distance: float              # m, walked (ground-truth feet centre, start to end)
    planned_distance: float
    lateral_drift: float         # m, off the planned line (straight walks)
    heading_drift_deg: float
    max_slip: float              # m, largest stance-foot slide during one single support
    touchdown_err_ms: float      # largest |actual - planned| touchdown time [ms]
    peak_speed_ratio: float      # max |joint velocity| / URDF limit
    peak_speed_joint: str
    est_com_err: float           # m, feet relative, max while walking
    est_cp_err: float            # the odometry's capture point (the fall trigger's), feet relative, max
    est_cp_fused_err: float      # capture_point_fused (the complementary filter's: walking, e-stop), max
    contact_delay_ms: float      # estimator contact flag vs ground truth (sole > its contact_force), at touchdown [ms]
    contact_delay_liftoff_ms: float  # and at lift-off
    tick_ms_median: float        # controller step only
    tick_ms_p99: float
    sim_time: float
    messages: list

    def as_dict(self) -> dict:
        d = dataclasses.asdict(self)
        return {k: (round(v, 5) if isinstance(v, float) else v) for k, v in d.items()}


def walking_scenario(speed_kmh: float = 1.0, steps: int = 20, overrides: list[str] | None = None,
                     name: str = "walking") -> dict:
    ov = [f"walk.speed_kmh={speed_kmh}", f"walk.steps={steps}", *(overrides or [])]
    return scenario_mod.load(name, ov)


def walk_duration(sc: dict, ctl: LocomotionController) -> float:
    c, w = ctl.cfg, sc["walk"]
    return w["start_time"] + c.crouch_duration + c.start_duration + (w["steps"] + 1) * c.step_period_for(
        w["speed_kmh"] / 3.6) \
        + c.stop_duration + c.settle_duration + 0.5


def run_walk(speed_kmh: float = 1.0, steps: int = 20, overrides: list[str] | None = None,
             noise: SensorNoise | None = None, trace: bool = False, sc: dict | None = None,
             inputs=None, on_tick=None) -> tuple[WalkResult, dict]:
    """Run the walking scenario in ClosedLoop; metrics against ground truth (module docstring)."""
    sc = sc or walking_scenario(speed_kmh, steps, overrides)
    model = load_model()
    ctl = from_scenario(sc, model)
    schedule = walk_schedule(sc)
    cmd = schedule[0][1] if schedule else None
    loop = ClosedLoop(sc, controllers=[ctl], noise=noise, inputs=inputs, track_errors=True)
    world = loop.world
    try:
        total = walk_duration(sc, ctl)
        zmp_err_ss, zmp_err_est, zmp_err_foot, margin_ok, margin_n = [], [], [], 0, 0
        tick_times = []
        peak = np.zeros(model.njoints)
        fell = False
        stance_anchor: dict = {}
        max_slip = 0.0
        tr = {k: [] for k in ("t", "cop", "cop_est", "zmp", "mbzmp", "com", "com_ref", "support",
                              "feet", "phase", "err_foot")} if trace else {}
        start_feet = None
        prev_support = "double"
        planned_td, actual_td = [], []
        contact_prev = {"l": True, "r": True}
        est_prev = {"l": True, "r": True}
        truth_ev, est_ev = [], []     # (time, side, touchdown?) of the true and the estimated contact flags
        orig_step = ctl.step

        def timed(obs):
            t0 = time.perf_counter()
            out = orig_step(obs)
            tick_times.append(time.perf_counter() - t0)
            return out

        ctl.step = timed
        while world.time < total:
            if start_feet is None and world.time >= sc["walk"]["start_time"] - 1e-9:
                model.forward(world.pinocchio_configuration())
                start_feet = {s: model.frame_placement(model.sole_frame[s]).copy() for s in SIDES}
            obs = loop.step()
            if on_tick is not None:
                on_tick(loop, ctl, obs)
            qj, vj, _ = world.joint_states()
            peak = np.maximum(peak, np.abs(vj))
            if world.trunk_tilt() > math.radians(30) or world.non_foot_contact():
                fell = True
                break
            st = ctl.state
            cop = world.ground_truth_cop()
            q_true = world.pinocchio_configuration()
            model.forward(q_true)
            # touchdowns: planned = the tick the pattern leaves single support; actual = the swing sole loaded
            contacts = {s: bool(c) for s, c in zip(SIDES, _sole_loaded(world, loop.estimator.contact_force))}
            if st.walking and prev_support != "double" and st.support == "double":
                planned_td.append((world.time, "r" if prev_support == "single_left" else "l"))
            for s in SIDES:
                if contacts[s] and not contact_prev[s] and st.walking:
                    actual_td.append((world.time, s))
                if contacts[s] != contact_prev[s] and st.walking:
                    truth_ev.append((world.time, s, contacts[s]))
            contact_prev = contacts
            for s in SIDES:
                e = bool(obs.state.contacts[s])
                if e != est_prev[s] and st.walking:
                    est_ev.append((world.time, s, e))
                est_prev[s] = e
            prev_support = st.support if st.walking else "double"
            if st.walking and cop is not None:
                if st.support != "double":
                    side = "l" if st.support == "single_left" else "r"
                    zmp_err_ss.append(np.linalg.norm(cop[:2] - st.zmp_ref[:2]))
                    err_foot = _foot_relative_error(model, side, cop, st)
                    zmp_err_foot.append(np.linalg.norm(err_foot))
                    zmp_err_est.append(np.linalg.norm(obs.state.cop[:2] - obs.state.feet_center[:2]
                                                      - (st.zmp_ref[:2] - _ref_feet_center(st))))
                    poly = support_polygon(model.sole_corners(side)[:, :2])
                    pos = model.frame_placement(model.sole_frame[side]).translation.copy()
                    if side not in stance_anchor:
                        stance_anchor = {side: pos}
                    max_slip = max(max_slip, float(np.linalg.norm(pos[:2] - stance_anchor[side][:2])))
                else:
                    poly = support_polygon(np.vstack([model.sole_corners(s)[:, :2] for s in SIDES]))
                    stance_anchor = {}
                margin_n += 1
                margin_ok += point_in_polygon_margin(cop, poly) >= 0.01
            if trace:
                tr["t"].append(world.time)
                tr["cop"].append(cop[:2] if cop is not None else [np.nan, np.nan])
                tr["cop_est"].append(obs.state.cop[:2].copy())
                tr["zmp"].append(st.zmp_ref[:2].copy())
                tr["mbzmp"].append(st.multibody_zmp[:2].copy())
                tr["com"].append(model.com(q_true))
                tr["com_ref"].append(st.com_ref.copy())
                tr["support"].append(st.support if st.walking else "stand")
                tr["phase"].append(st.phase_fraction)
                tr["err_foot"].append(err_foot if st.walking and cop is not None and st.support != "double"
                                      else np.full(2, np.nan))
                tr["feet"].append([model.frame_placement(model.sole_frame[s]).translation.copy() for s in SIDES])
        q_true = world.pinocchio_configuration()
        model.forward(q_true)
        end_feet = {s: model.frame_placement(model.sole_frame[s]) for s in SIDES}
        c0 = 0.5 * (start_feet["l"].translation + start_feet["r"].translation) if start_feet else np.zeros(3)
        c1 = 0.5 * (end_feet["l"].translation + end_feet["r"].translation)
        d = c1 - c0
        T = ctl.cfg.step_period_for(cmd.speed) if cmd else ctl.cfg.step_period
        turning = cmd is not None and abs(cmd.yaw_rate) > 1e-9
        planned = (cmd.n_steps * cmd.speed * T) if cmd else 0.0
        yaw1 = 0.5 * (yaw_of(end_feet["l"].rotation) + yaw_of(end_feet["r"].rotation))
        planned_yaw = math.degrees(cmd.yaw_rate * cmd.n_steps * T) if cmd else 0.0
        ratio = peak / model.limits.velocity
        j = int(np.argmax(ratio))
        ts = np.array(tick_times) * 1e3
        zr = np.array(zmp_err_ss) if zmp_err_ss else np.array([np.nan])
        ze = np.array(zmp_err_est) if zmp_err_est else np.array([np.nan])
        zf = np.array(zmp_err_foot) if zmp_err_foot else np.array([np.nan])
        td = _touchdown_errors(planned_td, actual_td)
        delay_td, delay_lo = _contact_delays(truth_ev, est_ev)
        est_com = loop.errors.get("com_error_feet_relative", float("nan"))  # max over the run (ClosedLoop)
        est_cp = loop.errors.get("capture_point_error_feet_relative", float("nan"))
        est_cp_fused = loop.errors.get("capture_point_fused_error_feet_relative", float("nan"))
        res = WalkResult(fell, sc["walk"]["speed_kmh"], sc["walk"]["steps"], float(np.sqrt(np.mean(zr ** 2))),
                         float(np.max(zr)), float(np.sqrt(np.mean(ze ** 2))),
                         float(np.sqrt(np.mean(zf ** 2))), float(np.max(zf)), margin_ok / max(margin_n, 1),
                         float(np.hypot(d[0], d[1]) if turning else d[0]), planned,
                         float("nan") if turning else float(abs(d[1])), math.degrees(yaw1) - planned_yaw,
                         max_slip, td, float(ratio[j]), model.joint_names[j], est_com, est_cp, est_cp_fused,
                         delay_td, delay_lo,
                         float(np.median(ts)), float(np.percentile(ts, 99)), world.time, list(ctl.messages))
        return res, tr
    finally:
        loop.close()


def _foot_relative_error(model, side: str, cop, st) -> np.ndarray:
    """(true CoP in the true stance sole's frame) - (reference ZMP in the pattern's stance sole frame), xy [m]."""
    M = model.frame_placement(model.sole_frame[side])
    yaw = yaw_of(M.rotation)
    c, s = math.cos(yaw), math.sin(yaw)
    d = cop[:2] - M.translation[:2]
    true_local = np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1]])
    f = st.left_foot if side == "l" else st.right_foot
    c, s = math.cos(f[3]), math.sin(f[3])
    d = st.zmp_ref[:2] - np.array(f[:2])
    ref_local = np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1]])
    return true_local - ref_local


def _ref_feet_center(st) -> np.ndarray:
    return 0.5 * (np.array(st.left_foot[:2]) + np.array(st.right_foot[:2]))


def _sole_loaded(world, threshold: float) -> list[bool]:
    """Each sole carries more than ``threshold`` [N] (ground truth, the simulator's contact forces). The walk passes
    the estimator's own ``contact_force``, so the contact delays measure its detection, not the load ramp between two
    thresholds (with 30 N the new servos' slow lift-off read 100-150 ms, docs/walking.md "Session 21")."""
    return [float(np.linalg.norm(world.foot_wrench(s)[0])) > threshold for s in SIDES]


def _touchdown_errors(planned: list, actual: list) -> float:
    """Largest |actual - planned| [ms] over the planned touchdowns (nearest actual of the same foot)."""
    worst = 0.0
    for t, s in planned:
        cand = [ta for ta, sa in actual if sa == s and abs(ta - t) < 0.3]
        if not cand:
            return float("inf")
        worst = max(worst, min(abs(ta - t) for ta in cand))
    return 1e3 * worst


def _contact_delays(truth: list, est: list, window: float = 0.1, settle: float = 0.05) -> tuple[float, float]:
    """Largest delay [ms] of the estimator's contact flag behind the true one (each true change of a sole matched
    to the nearest estimated change of the same sole and kind within ``window`` [s]; an estimated change before
    the true one counts as 0; none within the window: inf), at touchdowns and at lift-offs. Only true changes
    after the sole kept its state ``settle`` [s] count (a touchdown bounce's brief unload and reload do not)."""
    out = {True: 0.0, False: 0.0}
    last: dict = {}
    kept = []
    for t, s, on in truth:
        if t - last.get(s, -math.inf) >= settle:
            kept.append((t, s, on))
        last[s] = t
    for t, s, on in kept:
        cand = [te for te, se, eo in est if se == s and eo == on and -window < te - t < window]
        d = min((te - t for te in cand), key=abs) if cand else float("inf")
        out[on] = max(out[on], 1e3 * max(d, 0.0))
    return out[True], out[False]


def momentum_check(speed_kmh: float = 1.0, steps: int = 3) -> dict:
    """Single-support means of (measured CoP - reference ZMP), (ZMP of the actual motion - reference) and the
    reported contact force vs the momentum rate: the ground-truth state's centroidal momentum rate (pinocchio,
    backward difference) against PyBullet's reported contact wrench (docs/walking.md, "the CoP bias")."""
    import pinocchio as pin

    from humfall_ros.walking.multibody import MomentumZmp

    model = load_model()
    mz, data = MomentumZmp(model, 0.002), model.model.createData()
    rows, prev = [], [None]

    def on_tick(loop, ctl, obs):
        w, st = loop.world, ctl.state
        q, v = w.pinocchio_state()
        p = mz.update(q, v)
        pin.computeCentroidalMomentum(model.model, data, q, v)
        h = data.hg.linear.copy()
        dh, prev[0] = (None if prev[0] is None else (h - prev[0]) / 0.002), h
        if p is None or dh is None or not st.walking or st.support == "double":
            return
        f = np.zeros(3)
        for cp in w.ground_contacts():
            f += cp[9] * np.array(cp[7]) + cp[10] * np.array(cp[11]) + cp[12] * np.array(cp[13])
        cop = w.ground_truth_cop()
        rows.append([*(cop[:2] - st.zmp_ref[:2]), *(p[:2] - st.zmp_ref[:2]), f[0] - dh[0], f[2] - dh[2]
                     - model.total_mass * 9.81])

    run_walk(speed_kmh, steps, on_tick=on_tick)
    r = np.array(rows)
    return {"cop_minus_ref_mean_m": r[:, :2].mean(0).round(4).tolist(),
            "actual_motion_zmp_minus_ref_mean_m": r[:, 2:4].mean(0).round(4).tolist(),
            "contact_force_minus_momentum_rate_mean_N": {"x": round(float(r[:, 4].mean()), 1),
                                                          "z": round(float(r[:, 5].mean()), 1)}}


def substep_check(speed_kmh: float = 1.0, steps: int = 2) -> dict:
    """The contact chatter behind the old CoP bias (docs/walking.md, phase 3): per physics substep, the
    reported contact force vs that substep's linear momentum rate (PyBullet's link masses and COM
    velocities, pushes none), and the last substep vs the tick's mean, over the middle of the walk [N]."""
    import pybullet as pb

    from humfall_ros.sim.world import SimWorld

    rows, orig, state = [], SimWorld.step_control, {}

    def momentum(w):
        c = w.client
        if "m" not in state:
            state["m"] = [pb.getDynamicsInfo(w.robot, k, physicsClientId=c)[0]
                          for k in range(-1, pb.getNumJoints(w.robot, physicsClientId=c))]
        m = state["m"]
        p = m[0] * np.array(pb.getBaseVelocity(w.robot, physicsClientId=c)[0])
        for mk, s in zip(m[1:], pb.getLinkStates(w.robot, list(range(len(m) - 1)), computeLinkVelocity=1,
                                                 physicsClientId=c)):
            p += mk * np.array(s[6])
        return p

    def fsum(cps):
        return sum((cp[9] * np.array(cp[7]) + cp[10] * np.array(cp[11]) + cp[12] * np.array(cp[13]) for cp in cps),
                   np.zeros(3))

    def step_control(self):
        n, p0 = self.substeps, state.get("p") if state.get("p") is not None else momentum(self)
        self.substeps, row = 1, []
        try:
            for _ in range(n):
                orig(self)
                p1 = momentum(self)
                f = fsum(pb.getContactPoints(self.robot, self.ground, physicsClientId=self.client))
                row.append((f, (p1 - p0) / self.dt + np.array([0, 0, GRAVITY * sum(state["m"])])))
                p0 = p1
        finally:
            self.substeps = n
        state["p"] = p0
        rows.append(row)

    SimWorld.step_control = step_control
    try:
        run_walk(speed_kmh, steps)
    finally:
        SimWorld.step_control = orig
    r = np.array(rows[int(0.3 * len(rows)):int(0.8 * len(rows))])      # ticks x substeps x (f, dP) x 3
    f, dp = r[:, :, 0], r[:, :, 1]
    return {"substep_force_minus_momentum_rate_abs_mean_N": np.abs(f - dp).mean((0, 1)).round(2).tolist(),
            "tick_mean_force_minus_momentum_rate_abs_mean_N": np.abs(f.mean(1) - dp.mean(1)).mean(0).round(2).tolist(),
            "last_substep_minus_tick_momentum_rate_mean_N": (f[:, -1] - dp.mean(1)).mean(0).round(1).tolist(),
            "substep_to_substep_force_jump_median_N": np.median(np.abs(f[:, -1] - f[:, 0]), 0).round(1).tolist()}


if __name__ == "__main__":
    import json

    args = [a for a in sys.argv[1:] if not a.startswith("--")]
    sets = [a.split("=", 1)[1] for a in sys.argv[1:] if a.startswith("--set=")]
    kmh = float(args[0]) if args else 1.0
    n = int(args[1]) if len(args) > 1 else 20
    if "--substeps" in sys.argv:
        print(json.dumps(substep_check(kmh, n)))
    elif "--momentum" in sys.argv:
        print(json.dumps(momentum_check(kmh, n)))
    else:
        res, _ = run_walk(kmh, n, sets)
        print(json.dumps(res.as_dict()))
