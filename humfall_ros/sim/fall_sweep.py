"""``humfall sweep``: paper 1's avoidance over push directions, for none / stepping / stepping_inertia.

Twelve push directions (every 30 deg; the angle is clockwise from +x seen from above, as in
DESIGN.md: 90 pushes to the right, -y), each at ``factor`` (1.2) x its own fall threshold,
on ``standing_push`` (0.1 s on the chest). The thresholds differ by direction (measured
210-370 N), so one magnitude would topple nothing between 30 and 120 deg: they are found once
by bisection (:func:`bisect_threshold`, standing balance only, no target) and stored in
``config/fall_thresholds.yaml`` with each direction's uncontrolled fall heading at
``factor`` x threshold. The target box is put 1.2 m from the initial CoP along that heading,
facing the robot. Every run is in process on the suite's ``ClosedLoop`` (``sim.fall_runs``), the
same ticks a ``humfall up`` run would give.

Output: a per-direction table (fall direction, the three avoidance angles, min target
distance, lead time, decision) on stdout, ``sweep.json`` and ``sweep_polar.png`` in ``--out``.
"""
from __future__ import annotations

import argparse
import json
import math
import pathlib
import sys
import time

import numpy as np
import yaml

from humfall_ros import paths

DIRECTIONS = tuple(range(0, 360, 30))
TARGET_DISTANCE = 1.2          # m from the initial CoP along the uncontrolled fall
TARGET_SIZE = (0.3, 0.6, 0.8)  # m, the standing_push box
THRESHOLDS_FILE = "fall_thresholds.yaml"


def push_force(magnitude: float, angle_deg: float) -> list[float]:
    """Horizontal push [N] of ``magnitude`` at ``angle_deg`` clockwise from +x."""
    a = math.radians(angle_deg)
    return [round(magnitude * math.cos(a), 6), round(-magnitude * math.sin(a), 6), 0.0]


def push_scenario(magnitude: float, angle_deg: float, target_heading_deg: float | None = None,
                  initial_cop=(0.0, 0.0), extra: list[str] | None = None) -> dict:
    """``standing_push`` with the push set and the target along ``target_heading_deg`` (None: no target)."""
    from humfall_ros import scenario

    ov = [f"push.0.force={push_force(magnitude, angle_deg)}"]
    if target_heading_deg is None:
        ov.append("obstacles=[]")
    else:
        h = math.radians(target_heading_deg)
        d = TARGET_DISTANCE + TARGET_SIZE[0] / 2  # the box's near face 1.2 m out
        x, y = initial_cop[0] + d * math.cos(h), initial_cop[1] + d * math.sin(h)
        ov.append(f"obstacles=[{{name: target, position: [{x:.4f}, {y:.4f}, {TARGET_SIZE[2] / 2}], "
                  f"size: {list(TARGET_SIZE)}, yaw: {h:.4f}, is_target: true}}]")
    return scenario.load("standing_push", ov + list(extra or []))


def falls(magnitude: float, angle_deg: float, duration: float = 2.5) -> tuple[bool, dict]:
    """Does the standing robot fall from this push (no fall controller, no target)?"""
    from humfall_ros.sim import fall_runs as runs

    sc = push_scenario(magnitude, angle_deg)
    r = runs.run(sc, "none", duration=duration, stop_after_landing_s=0.0)
    return bool(r.metrics["fell"]), r.metrics


def bisect_threshold(angle_deg: float, lo: float = 150.0, hi: float = 600.0, tol: float = 5.0,
                     log=print) -> dict:
    """The smallest push that topples the robot at ``angle_deg``, bracketed to ``tol`` [N]."""
    fell_lo, _ = falls(lo, angle_deg)
    if fell_lo:
        raise RuntimeError(f"{angle_deg} deg: {lo} N already topples the robot; lower the bracket")
    while True:
        fell_hi, _ = falls(hi, angle_deg)
        if fell_hi:
            break
        lo, hi = hi, hi * 1.5
    while hi - lo > tol:
        mid = 0.5 * (lo + hi)
        f, _ = falls(mid, angle_deg)
        log(f"  {angle_deg:5.0f} deg {mid:6.1f} N: {'falls' if f else 'recovers'}")
        lo, hi = (lo, mid) if f else (mid, hi)
    return {"recovers_n": round(lo, 2), "falls_n": round(hi, 2), "threshold_n": round(0.5 * (lo + hi), 2)}


def compute_thresholds(directions=DIRECTIONS, factor: float = 1.2, tol: float = 5.0, log=print) -> dict:
    """Thresholds and the uncontrolled fall heading at ``factor`` x threshold, per direction."""
    from humfall_ros.sim import fall_runs as runs

    out = {}
    for a in directions:
        t0 = time.perf_counter()
        b = bisect_threshold(a, tol=tol, log=log)
        sc = push_scenario(factor * b["threshold_n"], a)
        r = runs.run(sc, "none", duration=3.0)
        m = r.metrics
        b["fall_heading_deg"] = None if m["fall_direction_deg"] is None else round(m["fall_direction_deg"], 2)
        b["initial_cop"] = [round(x, 4) for x in m["initial_cop"]]
        b["fall_event_time_s"] = m["fall_event_time_s"]
        b["lead_time_s"] = m["lead_time_s"]
        out[int(a)] = b
        log(f"{a:5.0f} deg: threshold {b['threshold_n']} N, {factor}x falls towards {b['fall_heading_deg']} deg "
            f"({time.perf_counter() - t0:.0f} s)")
    return out


def thresholds_path() -> pathlib.Path:
    return paths.config_path(THRESHOLDS_FILE)


def save_thresholds(data: dict, path: pathlib.Path, factor: float, tol: float) -> None:
    doc = {"description": ("per-direction fall thresholds of standing_push (0.1 s on the chest, standing balance, "
                           "no target), by bisection (humfall_ros/sim/fall_sweep.py); angle clockwise from +x; "
                           f"fall_heading_deg: uncontrolled fall at {factor} x threshold"),
           "factor": factor, "tolerance_n": tol, "directions": data}
    path.write_text(yaml.safe_dump(doc, sort_keys=False))


def load_thresholds(path: pathlib.Path | None = None) -> dict:
    doc = yaml.safe_load((path or thresholds_path()).read_text())
    return {int(k): v for k, v in doc["directions"].items()}


def sweep(thresholds: dict, controllers=("none", "stepping", "stepping_inertia"), factor: float = 1.2,
          directions=None, duration: float = 3.5, log=print, overrides=()) -> list[dict]:
    """One row per direction and controller (``sim.fall_runs.summary`` plus the push); ``overrides``: scenario
    overrides (``KEY=VALUE``) for every run, e.g. a controller parameter."""
    from humfall_ros.sim import fall_runs as runs

    rows = []
    for a in directions or sorted(thresholds):
        th = thresholds[a]
        heading = th["fall_heading_deg"]
        for kind in controllers:
            sc = push_scenario(factor * th["threshold_n"], a, heading, th["initial_cop"], list(overrides))
            t0 = time.perf_counter()
            r = runs.run(sc, kind, duration=duration)
            s = runs.summary(r)
            s.update({"push_angle_deg": a, "push_n": round(factor * th["threshold_n"], 1), "controller": kind,
                      "target_heading_deg": heading, "wall_s": round(time.perf_counter() - t0, 1)})
            rows.append(s)
            log(row_line(s))
    return rows


def _f(x, w=6, p=0):
    return f"{'-':>{w}}" if x is None else f"{x:{w}.{p}f}"


def _scaled(x, k):
    return None if x is None else x * k


def row_line(s: dict) -> str:
    d = s.get("decision") or {}
    p = s.get("prediction") or {}
    return (f"{s['push_angle_deg']:4d} {s['push_n']:6.1f} {s['controller']:16s} {_f(s['fall_direction_deg'])} "
            f"{_f(s['avoidance_angle_deg'])} {_f(s['avoidance_angle_p2_deg'])} {_f(s['predicted_avoidance_deg'])} "
            f"{_f(s['min_target_distance_m'], 6, 3)} {_f(s['lead_time_s'], 5, 2)} {d.get('case', '-'):>11s} "
            f"{'yes' if s.get('fell') is False else '-':>5s} {_f(_scaled(p.get('touchdown_error_s'), 1e3), 6)} "
            f"{_f(_scaled(p.get('landing_error_m'), 1e2), 6, 1)} {_f(p.get('landing_tilt_deg'), 5, 1)}")


HEADER = ("push    N  controller        fall  alpha  alpha2  pred  min_d  lead        case  capt  td_err  land  tilt\n"
          "(deg)                          (deg)  (deg)  (deg)  (deg)   (m)   (s)                     (ms)  (cm) (deg)")


def _worst(rows: list[dict], key: str) -> float | None:
    xs = [abs(r["prediction"][key]) for r in rows if (r.get("prediction") or {}).get(key) is not None]
    return None if not xs else float(max(xs))


def summary(rows: list[dict]) -> dict:
    out = {}
    for kind in {r["controller"] for r in rows}:
        rs = [r for r in rows if r["controller"] == kind]
        a2 = [r["avoidance_angle_p2_deg"] for r in rs if r["avoidance_angle_p2_deg"] is not None]
        a = [r["avoidance_angle_deg"] for r in rs if r["avoidance_angle_deg"] is not None]
        hit = [r["push_angle_deg"] for r in rs if (r["min_target_distance_m"] or 0.0) < 0.05]
        out[kind] = {"runs": len(rs), "mean_alpha2_deg": None if not a2 else round(float(np.mean(a2)), 1),
                     "worst_alpha2_deg": None if not a2 else round(float(np.min(a2)), 1),
                     "mean_alpha_deg": None if not a else round(float(np.mean(a)), 1),
                     "target_hit_directions": hit, "fell": sum(bool(r["fell"]) for r in rs)}
        # the step's prediction against the outcome (issue 11: touchdown 50 ms, landing 3 cm / 5 deg, flat 3 deg)
        stepped = [r for r in rs if (r.get("prediction") or {}).get("touchdown_error_s") is not None]
        if stepped:
            ok = [r for r in stepped if abs(r["prediction"]["touchdown_error_s"]) <= 0.05
                  and (r["prediction"].get("landing_error_m") or 0.0) <= 0.03
                  and abs(r["prediction"].get("landing_yaw_error_deg") or 0.0) <= 5.0
                  and (r["prediction"].get("landing_tilt_deg") or 0.0) <= 3.0]
            out[kind]["prediction"] = {
                "steps": len(stepped), "within_goals": len(ok),
                "worst_touchdown_error_s": _worst(stepped, "touchdown_error_s"),
                "worst_landing_error_m": _worst(stepped, "landing_error_m"),
                "worst_landing_yaw_error_deg": _worst(stepped, "landing_yaw_error_deg"),
                "worst_landing_tilt_deg": _worst(stepped, "landing_tilt_deg")}
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="humfall sweep", description=__doc__.split("\n\n")[0])
    ap.add_argument("--controller", default="none,stepping,stepping_inertia",
                    help="comma-separated: none, stepping, stepping_inertia")
    ap.add_argument("--directions", default=None, help="comma-separated push angles [deg] (default: all 12)")
    ap.add_argument("--factor", type=float, default=1.2, help="push = factor x the direction's threshold")
    ap.add_argument("--thresholds", default=None, help=f"thresholds file (default config/{THRESHOLDS_FILE})")
    ap.add_argument("--recompute-thresholds", action="store_true", help="bisect the thresholds and write the file")
    ap.add_argument("--out", default="runs/sweep", help="folder for sweep.json and sweep_polar.png")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="scenario override for every run (repeatable), e.g. "
                         "params.safe_fall_controller.capture_depth_m=0.08")
    a = ap.parse_args(argv)
    kinds = [k.strip() for k in a.controller.split(",") if k.strip()]
    from humfall_ros.sim.fall_runs import CONTROLLERS

    bad = [k for k in kinds if k not in CONTROLLERS]
    if bad:
        ap.error(f"unknown controller(s) {bad}; choose from {list(CONTROLLERS)}")
    dirs = [int(x) for x in a.directions.split(",")] if a.directions else list(DIRECTIONS)
    path = pathlib.Path(a.thresholds) if a.thresholds else thresholds_path()
    if a.recompute_thresholds or not path.is_file():
        print(f"bisecting the fall thresholds of {len(dirs)} directions -> {path}", flush=True)
        save_thresholds(compute_thresholds(dirs, a.factor), path, a.factor, 5.0)
    th = load_thresholds(path)
    missing = [d for d in dirs if d not in th]
    if missing:
        ap.error(f"{path} has no threshold for {missing}; run with --recompute-thresholds")
    if a.overrides:   # a bad key or value fails here, before the first run (as the runs' own node_params would)
        from humfall_ros import params as params_mod, scenario
        from humfall_ros.suite import node_params

        try:
            sc = scenario.load("standing_push", list(a.overrides))
            for node in sc["params"]:
                node_params(sc, node)
        except (scenario.ScenarioError, params_mod.ParamError) as e:
            ap.error(str(e))
    print(HEADER, flush=True)
    rows = sweep(th, kinds, a.factor, dirs, log=lambda s: print(s, flush=True), overrides=a.overrides)
    out = pathlib.Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    summ = summary(rows)
    (out / "sweep.json").write_text(json.dumps({"rows": rows, "summary": summ, "factor": a.factor,
                                                "overrides": a.overrides}, indent=1, default=str))
    try:
        from humfall_ros.fall import plots

        png = plots.sweep_polar(rows, out / "sweep_polar.png")
        print(f"polar plot: {png}")
    except Exception as e:  # noqa: BLE001 - the table matters more than the plot
        print(f"polar plot failed: {e}", file=sys.stderr)
    print(json.dumps(summ, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
