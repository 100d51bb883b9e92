"""Multi-contact plans executed on the 3-D robot in PyBullet (issue 14). Prints one JSON object.

    python benchmarks/bench_multicontact_exec.py [--kes 20,40,60] [--objective paper|departure] [--planar-defaults]
                                                 [--budget 120] [--save-plans DIR] [--plots DIR]
                                                 [--calibrate 300,400,500] [--set name=value,...]
                                                 [--replay DIR] [--pitch-gain 1.0] [--run name=value,...]
                                                 [--walking-push 450,550]

Per case: the push of ``config/scenarios/multicontact_push.yaml`` with the force that gives the
requested sagittal kinetic energy at the push's end (found by a few secant steps on KE ~ F^2, each a
0.6 s run to the push's end; the table is in the output), then ``humfall_ros.sim.multicontact_run.execute``:
plan at the push's end from the measured state (simulator paused while planning), execute, measure:
final 3-D KE, final contact mode vs the plan's, links touching the ground besides the planned
extremities, planned vs executed contact times and positions, peak contact force per limb.

``--pitch-gain`` is the executor's base pitch feedback on the stance hips (``ExecutorConfig.base_pitch_gain``,
default 1; 0: open loop, the executor before session 24).

The plans are made for the 3-D robot: the planner's declaration with ``FOR_EXECUTION``
(``humfall_ros.multicontact.planner``: a foot landing's capture point 0.25 m inside the toe; session 42, before: the
declaration alone). ``--planar-defaults`` plans with the declaration alone (the KE sweep's planner: 0.12 m).
``--objective paper`` (default since session 42; before: departure) is the paper's pre-impact objective;
``--objective departure`` plans with the post-impact objective and frontier key, landings unlimited, no
touchdown-speed constraint (``DEPARTURE``, which sets its own step options). ``--save-plans DIR`` writes each
executed plan as ``multicontact_push_<KE>J.json`` (``StoredPlan``; the executor node's ``plan_file``).
``--calibrate F,...`` only prints the push -> KE table for those forces.

``--walking-push F,...`` (session 28) executes instead from single support: ``walking_push`` (1.0 km/h, the push at
the start of a right swing) with F N forward and its obstacle removed; the executor takes over at the push's end in
the stance mode LF and plans from it (``execute(initial_mode="LF")``); ``--hold`` defaults to ``measured`` there (the
gait's lateral weight shift stays; ``planar`` would put every hip and ankle roll back to 0 under a robot on one foot).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import pathlib
import sys
import time

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from humfall_ros import params  # noqa: E402
from humfall_ros import scenario as scenario_mod  # noqa: E402
from humfall_ros.multicontact.executor import ExecutorConfig, StoredPlan  # noqa: E402
from humfall_ros.multicontact.planner import DEPARTURE, FOR_EXECUTION, FallPlanner  # noqa: E402
from humfall_ros.sim import multicontact_run as mr  # noqa: E402

SCENARIO = "multicontact_push"
WALKING_SCENARIO = "walking_push"


def ke_of_force(sc: dict, force: float) -> dict:
    s = mr.with_push(sc, force)
    row = mr.state_at(s, mr.push_end_time(s))
    row["force"] = force
    return row


def force_for_energy(sc: dict, ke: float, f0: float = 500.0, tol: float = 0.02, steps: int = 5) -> tuple[float, list]:
    """The forward push force [N, rounded to 1 N] whose sagittal (planar) KE at the push's end is ``ke`` within
    ``tol`` (before the rounding)."""
    table = []
    f = f0
    for _ in range(steps):
        row = ke_of_force(sc, f)
        table.append(row)
        if abs(row["ke_planar"] - ke) <= tol * ke:
            break
        f = f * math.sqrt(ke / max(row["ke_planar"], 1e-6))   # KE ~ F^2 for a short push
    best = min(table, key=lambda r: abs(r["ke_planar"] - ke))
    f = float(round(best["force"]))           # a force one can type: --set push.0.force=[F, 0, 0]
    if f != best["force"]:
        table.append(ke_of_force(sc, f))
    return f, table


def plots(case: dict, path: pathlib.Path) -> None:
    """Kinetic energy, base pitch, the feet's heights, the CoM and capture point against the feet's toes (plan vs
    executed) and the contact forces over time."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    s = case["series"]
    plan = s.get("plan") or {}
    fig, (a, p, h, x, b) = plt.subplots(5, 1, figsize=(8, 12), sharex=True)
    a.plot(s["t"], s["ke"], label="executed (3-D, PyBullet)")
    curve = case["plan"].get("ke_curve") or []
    if curve:
        a.plot([c[0] for c in curve], [c[1] for c in curve], "o--", label="plan (planar)")
    a.set_ylabel("kinetic energy (J)")
    a.legend()
    a.set_title(f"{case['target_ke']:g} J: {' -> '.join(case['plan'].get('contact_sequence') or [])}")
    if s.get("base_pitch"):
        p.plot(s["t"], s["base_pitch"], label="executed")
    if plan.get("t"):
        p.plot(plan["t"], plan["base_pitch"], "--", label="plan")
    p.set_ylabel("base pitch (rad)")
    p.legend(fontsize=7)
    for e, color in (("LF", "C0"), ("RF", "C1")):
        if s.get("foot_height"):
            h.plot(s["t"], s["foot_height"][e], color=color, label=f"{e} executed")
        if plan.get("t"):
            h.plot(plan["t"], plan["foot_height"][e], "--", color=color, label=f"{e} plan")
    h.set_ylabel("lowest sole point (m)")
    h.legend(fontsize=7, ncol=2)
    # where a stop is won or lost: the capture point against the front toe (paper 1 eq. 1-2)
    for key, color, name in (("com_x", "C2", "CoM"), ("capture_point_x", "C3", "capture point")):
        if s.get(key):
            x.plot(s["t"], s[key], color=color, label=f"{name} executed")
        if plan.get(key):
            x.plot(plan["t"], plan[key], "--", color=color, label=f"{name} plan")
    for e, color in (("LF", "C0"), ("RF", "C1")):
        if s.get("toe_x"):
            x.plot(s["t"], s["toe_x"][e], ":", color=color, label=f"{e} toe executed")
        if plan.get("toe_x"):
            x.plot(plan["t"], plan["toe_x"][e], "-.", color=color, lw=0.7, label=f"{e} toe plan")
    x.set_ylabel("x (m)")
    x.legend(fontsize=7, ncol=3)
    for e, f in s["limb_force"].items():
        b.plot(s["t"], f, label=e)
    for n, f in s["other_force"].items():
        b.plot(s["t"], f, ":", label=n)
    for ev in case.get("contact_events", []):
        for ax in (h, x, b):
            ax.axvline(ev["planned_time"], color="k", lw=0.5, ls="--")
    b.set_xlabel("time from take-over (s)")
    b.set_ylabel("contact force (N)")
    b.legend(fontsize=7, ncol=3)
    a.set_xlim(min(-0.1, max(s["t"][0], -1.0)), s["t"][-1])   # a walking run starts seconds before its take-over
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def walking_case(planner, run_cfg, force: float, a) -> dict:
    """One ``walking_push`` of ``force`` N executed from single support (the left foot: the push comes at the start
    of a right swing)."""
    t0 = time.perf_counter()
    sc = scenario_mod.load(WALKING_SCENARIO, [f"push.0.force=[{force}, 0.0, 0.0]", "obstacles=[]"])
    sc["controllers"] = []
    r = mr.execute(sc, planner=planner, cfg=run_cfg, initial_mode="LF")
    r.pop("_segments", None)
    if a.plots and "series" in r:
        r["target_ke"] = r.get("state_at_plan", {}).get("ke_planar_projected", 0.0)
        pathlib.Path(a.plots).mkdir(parents=True, exist_ok=True)
        plots(r, pathlib.Path(a.plots) / f"multicontact_exec_walking_{force:g}N.png")
    if not a.series:
        r.pop("series", None)
    r["push_force_n"] = force
    r["wall_s"] = time.perf_counter() - t0
    print(f"# walking_push {force:g} N: plan {r['plan'].get('success')} {r['plan'].get('contact_sequence')} "
          f"(KE {r['plan'].get('initial_ke')}), final mode {r.get('final_mode')} (plan {r.get('planned_final_mode')}), "
          f"others {sorted(r.get('other_links_touching') or {})}, success {r.get('success')}, {r['wall_s']:.0f} s",
          file=sys.stderr)
    return r


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--kes", default="20,40,60")
    ap.add_argument("--objective", choices=("paper", "departure"), default="paper")
    ap.add_argument("--planar-defaults", action="store_true",
                    help="plan with the planner's declaration alone, without FOR_EXECUTION (the KE sweep's planner)")
    ap.add_argument("--budget", type=float, default=120.0)
    ap.add_argument("--save-plans", default="")
    ap.add_argument("--plots", default="")
    ap.add_argument("--calibrate", default="")
    ap.add_argument("--hold", choices=("planar", "measured"), default=None,
                    help="joints the plan lacks (default: planar; measured with --walking-push)")
    ap.add_argument("--replay", default="", help="execute the stored plans of DIR (multicontact_push_<KE>J.json) "
                    "with their pushes instead of planning")
    ap.add_argument("--no-velocity-feedforward", action="store_true", help="ExecutorConfig.velocity_feedforward off")
    ap.add_argument("--speed-limit", choices=mr.SPEED_LIMITS, default="motor",
                    help="RunConfig.speed_limit (solver: SimWorld's clamp, what ROS runs; not momentum-conserving)")
    ap.add_argument("--blend", type=float, default=0.0, help="ExecutorConfig.blend_time [s]")
    ap.add_argument("--pitch-gain", type=float, default=ExecutorConfig.base_pitch_gain,
                    help="ExecutorConfig.base_pitch_gain (0: open loop, the executor before session 24)")
    ap.add_argument("--latency", type=float, default=0.0, help="RunConfig.plan_latency [s]")
    ap.add_argument("--one-hand", action="store_true", help="ExecutorConfig.both_hands off")
    ap.add_argument("--set", default="", help="planner parameters name=value,... (yaml names)")
    ap.add_argument("--run", default="", help="RunConfig fields name=value,... (e.g. swing_control=task)")
    ap.add_argument("--series", action="store_true", help="keep the per-tick series in the JSON")
    ap.add_argument("--plan-from", choices=("truth", "sensors"), default="truth",
                    help="plan from the simulator's state at the push's end, or from the sensors and the estimator "
                         "(multicontact.live, as the executor node's plan_live)")
    ap.add_argument("--walking-push", default="", help="forces [N] of walking_push, executed from one foot (LF)")
    a = ap.parse_args()
    if a.hold is None:
        a.hold = "measured" if a.walking_push else "planar"
    if a.walking_push and (a.replay or a.calibrate or a.save_plans):
        ap.error("--walking-push plans live: not with --replay, --calibrate or --save-plans")
    sc = scenario_mod.load(SCENARIO)
    sc["controllers"] = []          # in process the executor is built here
    out: dict = {"scenario": SCENARIO, "load_average_start": os.getloadavg()}
    if a.calibrate:
        out["push_table"] = [ke_of_force(sc, float(f)) for f in a.calibrate.split(",")]
        out["load_average_end"] = os.getloadavg()
        print(json.dumps(out, indent=1))
        return 0
    overrides = {**({} if a.planar_defaults else FOR_EXECUTION), **(DEPARTURE if a.objective == "departure" else {})}
    for kv in filter(None, a.set.split(",")):
        k, v = kv.split("=", 1)
        overrides[k] = json.loads(v) if v[:1] in "[{0123456789-tf" and v not in ("true", "false") else v
        if v in ("true", "false"):
            overrides[k] = v == "true"
    out["objective"] = a.objective
    out["planner_overrides"] = overrides
    planner = None if a.replay else FallPlanner.from_params(**overrides)
    run_cfg = mr.RunConfig.of(**{"time_budget": a.budget, "hold": a.hold, "both_hands": not a.one_hand,
                                 "plan_latency": a.latency, "velocity_feedforward": not a.no_velocity_feedforward,
                                 "speed_limit": a.speed_limit, "blend_time": a.blend, "base_pitch_gain": a.pitch_gain,
                                 **params.parse_overrides(a.run)})
    out["run_config"] = dataclasses.asdict(run_cfg)
    if a.walking_push:
        out["scenario"] = WALKING_SCENARIO
        out["cases"] = [walking_case(planner, run_cfg, float(f), a) for f in a.walking_push.split(",")]
        out["load_average_end"] = os.getloadavg()
        print(json.dumps(out, indent=1, default=float))
        return 0
    cases = []
    for ke in [float(x) for x in a.kes.split(",")]:
        t0 = time.perf_counter()
        if a.replay:
            stored = StoredPlan.load(pathlib.Path(a.replay) / f"multicontact_push_{ke:g}J.json")
            force, table = stored.meta["push_force"][0], []
            s = mr.with_push(sc, force)
            # the plan was made from the state at take_over - its own latency; --latency delays it from there
            planned_at = stored.take_over_time - float(stored.meta.get("plan_latency", 0.0))
            r = mr.execute(s, segments=stored.segments, start_time=planned_at, cfg=run_cfg)
            r["plan"].update({k: stored.meta.get(k) for k in ("contact_sequence", "objective")})
        else:
            force, table = force_for_energy(sc, ke)
            s = mr.with_push(sc, force)
            r = mr.execute(s, planner=planner, cfg=run_cfg, plan_from=a.plan_from)
        r["target_ke"] = ke
        r["push_force_n"] = force
        r["push_table"] = table
        r["wall_s"] = time.perf_counter() - t0
        r["load_average"] = os.getloadavg()
        if a.plots and "series" in r:
            pathlib.Path(a.plots).mkdir(parents=True, exist_ok=True)
            plots(r, pathlib.Path(a.plots) / f"multicontact_exec_{ke:g}J.png")
        if a.save_plans and not a.replay and r.get("take_over_time") is not None and r["plan"].get("success"):
            pathlib.Path(a.save_plans).mkdir(parents=True, exist_ok=True)
            segs = r.pop("_segments")
            StoredPlan(segs, r["take_over_time"], {
                "scenario": SCENARIO, "push_force": [force, 0.0, 0.0], "target_ke": ke,
                "objective": a.objective, "planner_overrides": overrides, "both_hands": not a.one_hand,
                "plan_latency": a.latency,
                "state_at_plan": r["state_at_plan"],
                "contact_sequence": r["plan"]["contact_sequence"]}).save(
                pathlib.Path(a.save_plans) / f"multicontact_push_{ke:g}J.json")
        r.pop("_segments", None)
        if not a.series:
            r.pop("series", None)
        cases.append(r)
        print(f"# {ke:g} J: F {force:.0f} N, plan {r['plan'].get('success')} "
              f"{r['plan'].get('contact_sequence')}, final KE {r.get('final_ke')}, mode {r.get('final_mode')} "
              f"(plan {r.get('planned_final_mode')}), others {sorted(r.get('other_links_touching') or {})}, "
              f"momentum err {r.get('momentum_error_ns_max')}, ke max {r.get('ke_max')}, "
              f"touching {r.get('final_mode_touching')}, success {r.get('success')}, "
              f"{r['wall_s']:.0f} s", file=sys.stderr)
    out["cases"] = cases
    out["load_average_end"] = os.getloadavg()
    print(json.dumps(out, indent=1, default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
