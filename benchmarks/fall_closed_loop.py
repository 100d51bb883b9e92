"""Safe fall in one process (``humfall_ros.sim.fall_runs`` on the suite's ClosedLoop): issue 11's experiments.

    .venv/bin/python benchmarks/fall_closed_loop.py push [SCALE] [KINDS] [OUT] [KEY=VALUE ...]  # standing_push
        (KEY=VALUE: scenario overrides, e.g. params.safe_fall_controller.balance_kd=0.1)
    .venv/bin/python benchmarks/fall_closed_loop.py band [SCALES] [KEY=VALUE ...]  # standing_push over 1.33-1.5x
    .venv/bin/python benchmarks/fall_closed_loop.py ftb [KEY=VALUE ...]         # 0.9x / 1.1x per direction
    .venv/bin/python benchmarks/fall_closed_loop.py quiet [SECONDS]             # standing_quiet, exact + noise
    .venv/bin/python benchmarks/fall_closed_loop.py small                       # small_push in 8 directions: FTB quiet?
    .venv/bin/python benchmarks/fall_closed_loop.py noise [SCALE] [KEY=VALUE ...]   # stepping_inertia, seeds 1-3
    .venv/bin/python benchmarks/fall_closed_loop.py repeat [SCALE] [KEY=VALUE ...]  # two lockstep runs identical?
    .venv/bin/python benchmarks/fall_closed_loop.py shaping [SCALE] [KEY=VALUE ...]  # stepping_inertia, diagnostics
    .venv/bin/python benchmarks/fall_closed_loop.py shaping_sweep [FACTOR] [VARIANTS]  # sweep pushes, shaping signs
    .venv/bin/python benchmarks/fall_closed_loop.py walk [SPEEDS] [KIND] [KEY=VALUE ...]  # walking.yaml: FTB triggers?
    .venv/bin/python benchmarks/fall_closed_loop.py walking_push [KINDS] [KEY=VALUE ...]  # walking_push.yaml

Each prints one JSON object. ``push`` also writes Fig. 9 / Fig. 11 PNGs into OUT (default runs/fall_figures).
The push angle of ``ftb`` is clockwise from +x; thresholds from config/fall_thresholds.yaml (``humfall sweep``).
"""
from __future__ import annotations

import json
import math
import pathlib
import sys
import time

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from humfall_ros import scenario  # noqa: E402
from humfall_ros.sim import fall_runs as runs, fall_sweep as sweep  # noqa: E402


def _push_overrides(scale: float) -> list[str]:
    sc = scenario.load("standing_push")
    f = [round(x * scale, 4) for x in sc["push"][0]["force"]]
    return [f"push.0.force={f}"]


def standing_push(kinds, scale: float = 1.0, out: str | None = "runs/fall_figures", overrides=()) -> dict:
    ov = _push_overrides(scale) + list(overrides)
    got, res = {}, {}
    for k in kinds:
        t0 = time.perf_counter()
        sc = scenario.load("standing_push", ov)
        r = runs.run(sc, k, keep_trace=out is not None)
        got[k] = r
        res[k] = {**runs.summary(r), "wall_s": round(time.perf_counter() - t0, 1)}
    if out:
        from humfall_ros.fall import plots

        d = pathlib.Path(out)
        d.mkdir(parents=True, exist_ok=True)
        obstacles = scenario.load("standing_push", ov)["obstacles"]
        res["figures"] = [str(plots.fig11(got, obstacles, d / f"fig11_scale{scale}.png"))]
        for k, r in got.items():
            if r.decision is not None:
                res["figures"].append(str(plots.fig9(r, obstacles, d / f"fig9_{k}_scale{scale}.png")))
    return {"scale": scale, "overrides": ov, **res}


def ftb_check(duration: float = 2.5, overrides: list[str] | None = None) -> dict:
    th = sweep.load_thresholds()
    rows = []
    for angle in (0, 30, 60, 90, 120, 150, 180, 270):
        if angle not in th:
            continue
        for factor in (0.9, 1.1):
            sc = sweep.push_scenario(factor * th[angle]["threshold_n"], angle, extra=overrides)
            r = runs.run(sc, "none", duration=duration)
            m = r.metrics
            rows.append({"angle_deg": angle, "factor": factor, "force_n": round(factor * th[angle]["threshold_n"], 1),
                         "fell": m["fell"], "triggered": r.fall_event is not None,
                         "trigger_time_s": m["fall_event_time_s"], "lead_time_s": m["lead_time_s"]})
    return {"rows": rows, "no_trigger_at_0.9": all(not r["triggered"] for r in rows if r["factor"] == 0.9),
            "trigger_at_1.1": all(r["triggered"] for r in rows if r["factor"] == 1.1)}


def quiet(seconds: float = 60.0) -> dict:
    from humfall_ros.sim.sensors import TYPICAL_NOISE

    out = {}
    for name, noise in (("exact", None), ("typical_noise", TYPICAL_NOISE)):
        t0 = time.perf_counter()
        r = runs.run(scenario.load("standing_quiet"), "none", noise=noise, duration=seconds)
        out[name] = {"triggered": r.fall_event is not None, "fell": r.metrics["fell"],
                     "wall_s": round(time.perf_counter() - t0, 1)}
    return out


def small_pushes(duration: float | None = None) -> dict:
    """small_push.yaml's push turned into 8 directions (every 45 deg, clockwise from +x): the FTB must stay quiet."""
    sc0 = scenario.load("small_push")
    f = sc0["push"][0]["force"]
    mag = math.hypot(f[0], f[1])
    rows = []
    for angle in range(0, 360, 45):
        force = sweep.push_force(mag, angle)
        r = runs.run(scenario.load("small_push", [f"push.0.force={force}"]), "none", duration=duration)
        rows.append({"angle_deg": angle, "force_n": round(mag, 1), "triggered": r.fall_event is not None,
                     "fell": r.metrics["fell"]})
    return {"rows": rows, "no_trigger": all(not r["triggered"] for r in rows)}


BAND = (1.33, 1.36, 1.38, 1.4, 1.42, 1.45, 1.5)   # session 43: the standing pushes just past the last capture


def band(scales=BAND, overrides=()) -> dict:
    """``standing_push`` stepping and stepping_inertia over a band of scales (ours; session 43): each scale's alpha2,
    whether it was captured or touched the target, and over the falls the mean / worst alpha2 and the count meeting
    the standing figure (shaping >= 160 deg and >= 20 over stepping). The outcomes there flip from one scale to the
    next (docs/safe_fall.md, sessions 42-43): one push's figure says as much about the push as the controller."""
    rows, falls = [], {"stepping": [], "stepping_inertia": []}
    for s in scales:
        r = standing_push(["stepping", "stepping_inertia"], s, None, overrides)
        row = {"scale": s}
        for k in falls:
            m = r[k]
            a = m["avoidance_angle_p2_deg"]
            row[k] = {"captured": bool(m["captured"]), "alpha2_deg": None if a is None else round(a, 1),
                      "touched": m["min_target_distance_m"] is not None and m["min_target_distance_m"] < 0.05}
            if not m["captured"] and a is not None:
                falls[k].append(a)
        st, sh = row["stepping"]["alpha2_deg"], row["stepping_inertia"]["alpha2_deg"]
        row["figure_met"] = bool(st is not None and sh is not None and not row["stepping"]["captured"]
                                 and not row["stepping_inertia"]["touched"] and sh >= 160.0 and sh >= st + 20.0)
        rows.append(row)
    out = {"scales": list(scales), "overrides": list(overrides), "rows": rows,
           "figure_met": f"{sum(r['figure_met'] for r in rows)}/{len(rows)}",
           "touched": {k: [r["scale"] for r in rows if r[k]["touched"]] for k in falls}}
    for k, a in falls.items():
        out[k] = {"falls": len(a), "mean_alpha2_deg": round(float(np.mean(a)), 1) if a else None,
                  "worst_alpha2_deg": round(float(np.min(a)), 1) if a else None}
    return out


def noise_runs(scale: float = 1.0, kind: str = "stepping_inertia", overrides=()) -> dict:
    import dataclasses

    from humfall_ros.sim.sensors import TYPICAL_NOISE

    ov = _push_overrides(scale) + list(overrides)
    exact = runs.summary(runs.run(scenario.load("standing_push", ov), kind))
    keys = ("fell", "avoidance_angle_p2_deg", "min_target_distance_m", "decision_case")
    out = {"exact": {k: exact[k] for k in keys}}
    for seed in (1, 2, 3):
        s = runs.summary(runs.run(scenario.load("standing_push", ov), kind,
                                  noise=dataclasses.replace(TYPICAL_NOISE, seed=seed)))
        out[f"seed{seed}"] = {k: s[k] for k in keys}
        a, b = s["avoidance_angle_p2_deg"], exact["avoidance_angle_p2_deg"]
        out[f"seed{seed}"]["alpha2_change_deg"] = None if a is None or b is None else round(abs(a - b), 1)
    return out


def repeat(scale: float = 1.0, kind: str = "stepping_inertia", overrides=()) -> dict:
    ov = _push_overrides(scale) + list(overrides)
    a = runs.run(scenario.load("standing_push", ov), kind, stop_after_landing_s=None, duration=2.5)
    b = runs.run(scenario.load("standing_push", ov), kind, stop_after_landing_s=None, duration=2.5)
    return {"identical_joint_states": bool(np.array_equal(a.joint_positions, b.joint_positions)),
            "identical_decisions": bool(a.decision.case == b.decision.case
                                        and np.array_equal(a.decision.landing, b.decision.landing)),
            "ticks": len(a.joint_positions)}


def shaping(scale: float = 1.0, overrides: tuple[str, ...] = (), kind: str = "stepping_inertia",
            seed: int | None = None) -> dict:
    """standing_push with inertia shaping and ``params.safe_fall_controller.KEY=VALUE`` overrides: what it adds, why.

    Per shaping tick (wrapping the controller's ``shaping_velocities``): the velocity scale the joint
    speed limits forced (>= 1: saturated), the joints recruited after the position limits, the inertia
    error and residual; and the fall heading seen from the measured P2 (alpha(t) = angle(P2 -> CoM,
    P2 -> T)) at touchdown, at the shaping start and at the trunk's landing. ``seed``: TYPICAL_NOISE with it.
    CLI: ``shaping SCALE [kind=stepping] [seed=N] [KEY=VALUE ...]``.
    """
    import dataclasses

    from humfall_ros.sim.sensors import TYPICAL_NOISE

    from humfall_ros.fall import controller as fc
    from humfall_ros.fall.geometry import avoidance_angle
    from humfall_ros.fall.inertia_shaping import ShapingConfig

    log = []
    orig = fc.shaping_velocities

    def spy(model, q, cop, target, dt, *args, **kwargs):
        # forwards whatever the controller passes: a spy with a stale signature made every shaping tick fail
        # (TypeError, "holding the last command") and reported a run without shaping (session 10's 135.6 deg)
        qd, info = orig(model, q, cop, target, dt, *args, **kwargs)
        cfg = kwargs.get("cfg") or ShapingConfig()
        vmax = cfg.velocity_fraction * model.limits.velocity
        log.append({"scale": float(np.max(np.abs(qd) / vmax)), "recruited": info["recruited"],
                    "error": info["error"], "residual": info["residual"], "q": np.asarray(q, float)[7:].copy()})
        return qd, info

    ov = _push_overrides(scale) + [f"params.safe_fall_controller.{x}" for x in overrides]
    fc.shaping_velocities = spy
    try:
        t0 = time.perf_counter()
        noise = None if seed is None else dataclasses.replace(TYPICAL_NOISE, seed=seed)
        r = runs.run(scenario.load("standing_push", ov), kind, keep_trace=True, noise=noise)
    finally:
        fc.shaping_velocities = orig
    s = runs.summary(r)
    out = {"overrides": list(overrides), "kind": kind, "seed": seed, "wall_s": round(time.perf_counter() - t0, 1),
           **{k: s.get(k) for k in ("avoidance_angle_p2_deg", "avoidance_angle_deg", "min_target_distance_m",
                                    "landing_time_s", "decision_case", "measured_p2")},
           "touchdown_s": (s.get("prediction") or {}).get("touchdown_time_s"),
           "shaping": [x for x in r.reasons if "shaping" in x or "fallen" in x],
           "tick_failures": [x for x in r.reasons if "tick failed" in x]}   # must be empty for a valid figure
    target = np.asarray(scenario.load("standing_push", ov)["obstacles"][0]["position"], float)[:2]
    p2 = s.get("measured_p2")
    if p2 is not None:
        heading = [(t, float(avoidance_angle(np.asarray(p2), np.asarray(com)[:2], target)))
                   for t, com, *_ in r.trace]
        out["alpha_from_p2_deg"] = {f"{t:.2f}": round(math.degrees(a), 1) for t, a in heading[::50]
                                    if math.isfinite(a)}
    if log:
        from humfall_ros.model.humanoid import load_model

        names = load_model().joint_names
        dq = log[-1]["q"] - log[0]["q"]
        out["shaping_ticks"] = len(log)
        out["saturated_fraction"] = round(float(np.mean([x["scale"] >= 0.999 for x in log])), 3)
        out["recruited_first_last"] = [log[0]["recruited"], log[-1]["recruited"]]
        ratio = [x["residual"] / max(x["error"], 1e-12) for x in log]
        out["residual_over_error_mean"] = round(float(np.mean(ratio)), 3)
        out["joint_change_rad"] = {names[i]: round(float(dq[i]), 3) for i in np.argsort(-np.abs(dq))[:8]}
    return out


def shaping_sweep(variants: dict[str, tuple[str, list[str]]], directions=(0, 30, 60, 90, 120),
                  factor: float = 1.2) -> dict:
    """The sweep's pushes (``factor`` x each direction's threshold, target along its uncontrolled fall) for
    controller variants ``{name: (kind, [KEY=VALUE of safe_fall_controller])}``: alpha2, alpha, clearance."""
    th = sweep.load_thresholds()
    rows = []
    for a in directions:
        t = th[a]
        for name, (kind, ov) in variants.items():
            sc = sweep.push_scenario(factor * t["threshold_n"], a, t["fall_heading_deg"], t["initial_cop"],
                                     extra=[f"params.safe_fall_controller.{x}" for x in ov])
            s = runs.summary(runs.run(sc, kind))
            rows.append({"push_angle_deg": a, "variant": name, "alpha2_deg": s["avoidance_angle_p2_deg"],
                         "alpha_deg": s["avoidance_angle_deg"], "min_target_distance_m": s["min_target_distance_m"],
                         "case": s["decision_case"]})
    return {"factor": factor, "rows": rows}


SHAPING_VARIANTS = {"stepping": ("stepping", []), "stepping_inertia": ("stepping_inertia", []),
                    "shaping_sign-1": ("stepping_inertia", ["shaping_sign=-1.0", "shaping_settled_sign=-1.0",
                                                            "shaping_settled_only=false"]),
                    "shaping_sign+1": ("stepping_inertia", ["shaping_sign=1.0", "shaping_settled_sign=1.0",
                                                            "shaping_settled_only=false"])}


def walk(speeds=(0.5, 1.0, 1.35, 1.8), kind: str = "stepping", overrides: tuple[str, ...] = ()) -> dict:
    """walking.yaml (20 steps) at each speed with the FTB (gait-referenced) and the safe-fall controller present:
    does the FTB trigger? Per speed: the trigger (time, reason), steps walked, the largest capture point error
    relative to the feet and its tick, the largest P->G lean, the largest separatrix margin, fell."""
    from humfall_ros.sim.closed_loop import ClosedLoop

    rows = []
    for v in speeds:
        t0 = time.perf_counter()
        sc = scenario.load("walking", [f"walk.speed_kmh={v}", "params.ftb_monitor.use_walking_state=true",
                                       *overrides])
        ctrls, mons = runs.controllers_for(sc, kind)
        loop = ClosedLoop(sc, ctrls, mons)
        ftb, loco = mons[0], ctrls[0]
        err, lean, margin, steps = (0.0, 0.0), 0.0, -math.inf, 0
        first = None   # the first fall event, also one the FTB's recovery cleared later
        try:
            for _ in range(int(round(sc["duration"] * sc["sim"]["control_rate"]))):
                loop.step()
                first = first or ftb.event
                f = loop.outputs["ftb/status"][-1].features
                if math.isfinite(f.capture_point_error) and f.capture_point_error > err[0]:
                    err = (f.capture_point_error, loop.world.time)
                if math.isfinite(f.lean_angle):
                    lean = max(lean, f.lean_angle)
                if math.isfinite(f.separatrix_margin):
                    margin = max(margin, f.separatrix_margin)
                steps = max(steps, loco.state.step_index)
            m = loop.metrics()
        finally:
            loop.close()
        ev = first
        rows.append({"speed_kmh": v, "triggered": ev is not None, "trigger_time_s": None if ev is None else ev.time,
                     "reason": None if ev is None else ev.reason, "steps": steps, "fell": m["fell"],
                     "max_capture_point_error_m": round(err[0], 4), "at_s": round(err[1], 3),
                     "max_lean_deg": round(math.degrees(lean), 1), "max_separatrix_margin": round(margin, 4),
                     "wall_s": round(time.perf_counter() - t0, 1)})
    return {"kind": kind, "overrides": list(overrides), "rows": rows,
            "no_trigger": all(not r["triggered"] for r in rows)}


def walking_push(kinds=runs.CONTROLLERS, overrides: tuple[str, ...] = (), out: str | None = None) -> dict:
    """walking_push.yaml for each controller: the acceptance figures (``runs.summary``)."""
    res, got = {}, {}
    for k in kinds:
        t0 = time.perf_counter()
        r = runs.run(scenario.load("walking_push", list(overrides)), k, keep_trace=out is not None)
        got[k] = r
        res[k] = {**runs.summary(r), "wall_s": round(time.perf_counter() - t0, 1)}
    if out:
        from humfall_ros.fall import plots

        d = pathlib.Path(out)
        d.mkdir(parents=True, exist_ok=True)
        obstacles = scenario.load("walking_push", list(overrides))["obstacles"]
        res["figures"] = [str(plots.fig11(got, obstacles, d / "fig11_walking_push.png"))]
        for k, r in got.items():
            if r.decision is not None:
                res["figures"].append(str(plots.fig9(r, obstacles, d / f"fig9_{k}_walking_push.png")))
    return {"overrides": list(overrides), **res}


def main(argv: list[str]) -> None:
    what = argv[0] if argv else "push"
    if what == "push":
        scale = float(argv[1]) if len(argv) > 1 else 1.0
        kinds = argv[2].split(",") if len(argv) > 2 else list(runs.CONTROLLERS)
        rest = argv[3:]
        folders = [a for a in rest if "=" not in a]   # an override is never taken for the figures' folder
        out = standing_push(kinds, scale, folders[0] if folders else "runs/fall_figures",
                            [a for a in rest if "=" in a])
    elif what == "band":
        scales = tuple(float(x) for x in argv[1].split(",")) if len(argv) > 1 and "=" not in argv[1] else BAND
        out = band(scales, [a for a in argv[1:] if "=" in a])
    elif what == "ftb":
        out = ftb_check(overrides=[a for a in argv[1:] if "=" in a])
    elif what == "small":
        out = small_pushes()
    elif what == "quiet":
        out = quiet(float(argv[1]) if len(argv) > 1 else 60.0)
    elif what == "noise":
        out = noise_runs(float(argv[1]) if len(argv) > 1 else 1.0, overrides=[a for a in argv[2:] if "=" in a])
    elif what == "repeat":
        out = repeat(float(argv[1]) if len(argv) > 1 else 1.0, overrides=[a for a in argv[2:] if "=" in a])
    elif what == "shaping_sweep":
        names = argv[2].split(",") if len(argv) > 2 else list(SHAPING_VARIANTS)
        out = shaping_sweep({k: SHAPING_VARIANTS[k] for k in names}, factor=float(argv[1]) if len(argv) > 1 else 1.2)
    elif what == "shaping":
        opts = dict(a.split("=", 1) for a in argv[2:] if a.split("=", 1)[0] in ("kind", "seed"))
        rest = tuple(a for a in argv[2:] if a.split("=", 1)[0] not in ("kind", "seed"))
        out = shaping(float(argv[1]) if len(argv) > 1 else 1.0, rest, opts.get("kind", "stepping_inertia"),
                      int(opts["seed"]) if "seed" in opts else None)
    elif what == "walk":
        speeds = tuple(float(x) for x in argv[1].split(",")) if len(argv) > 1 else (0.5, 1.0, 1.35, 1.8)
        out = walk(speeds, argv[2] if len(argv) > 2 else "stepping", tuple(argv[3:]))
    elif what == "walking_push":
        kinds = argv[1].split(",") if len(argv) > 1 else list(runs.CONTROLLERS)
        rest = [a for a in argv[2:] if not a.startswith("out=")]
        figs = [a.split("=", 1)[1] for a in argv[2:] if a.startswith("out=")]
        out = walking_push(kinds, tuple(rest), figs[0] if figs else None)
    else:
        raise SystemExit(f"unknown experiment {what!r}")
    print(json.dumps(out, default=str))


if __name__ == "__main__":
    main(sys.argv[1:])
