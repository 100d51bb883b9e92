"""KE sweep of the multi-contact fall planner (paper 2, Sec. IV-B, Fig. 7) plus
the wall case (Fig. 4). Prints one JSON object.

    python benchmarks/bench_multicontact.py [--kes 10,20,...,80] [--wall 0.8 --wall-ke 40]
                                            [--budget 120] [--jobs 2] [--plots DIR] [--no-resim]
                                            [--set name=value,...] [--compare] [--initial-mode RF]

The planner is built from its declaration (config/multicontact_planner.yaml,
``FallPlanner.from_params``); ``--set`` overrides parameters by their yaml
names. ``--compare`` runs the sweep twice, with the paper's objective (the
declaration) and with the departure (``DEPARTURE``: post-impact objective and
frontier key, landings unlimited: the planner before issue 14), and prints a
side-by-side ``table``. Every case reports its landings (eq. 10 severity).

NLP structures are built on first use and then reused (as in the node); the
build time is reported separately ("build_s", and per NLP "nlp_build_s") and is
included in the sweep time and in "median_nlp_s"; "median_nlp_solve_s"
excludes it (what a warmed-up node pays per NLP).

``--initial-mode RF`` starts every sweep case on one foot, the other free on the ground beside it, as the
paper's own trees do (Figs. 1 and 3: RF); the wall case stays on two feet (the paper's Fig. 4). The default
LF/RF is the issue's two-foot start (docs/multicontact.md "Session 28").

``--jobs 2`` (default) runs the sweep cases in two worker processes, one case
at a time each, largest energies first (the machine has 2 cores and one IPOPT
run uses one: ``blas_threads`` 1 since session 14; before, casadi's OpenBLAS ran a
thread per core, so two workers ran four threads); every worker builds its own structures. ``--jobs 1`` runs the
cases in order in this process. Every returned plan is re-simulated
independently with pinocchio (``resim.py``) unless ``--no-resim``.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from humfall_ros.multicontact.modes import Environment, strategy_of  # noqa: E402
from humfall_ros.multicontact.planner import DEPARTURE, FallPlanner  # noqa: E402  (DEPARTURE: the planner before issue 14)
from humfall_ros.params import parse_overrides  # noqa: E402

PAPER = {10: "inertial shaping", 20: "inertial shaping", 30: "protective step", 40: "protective step",
         50: "protective step", 60: "hand contact", 70: "hand contact", 80: "hand contact"}
# issue 14's wording of the same ladder: 10-20 J "no new contact" (a foot lifted adds none), 60-80 J a hand lands
ISSUE = {"inertial shaping": {"inertial shaping", "foot lifted"}, "protective step": {"protective step"},
         "hand contact": {"hand contact", "protective step + hand contact"}}


def run_case(planner: FallPlanner, ke: float, wall: float, budget: float, resim: bool,
             initial_mode: str = "LF/RF") -> dict:
    r = planner.plan({"kinetic_energy": ke, "direction": 1.0, "wall_distance": wall, "time_budget": budget,
                      "initial_mode": initial_mode})
    times = r["nlp_times_s"]
    name = strategy_of(r["contact_sequence"])
    case = {
        "ke": ke, "initial_mode": initial_mode, "wall_distance": wall, "success": r["success"], "reason": r["reason"],
        "contact_sequence": r["contact_sequence"], "strategy": name,
        "paper_strategy": PAPER.get(int(ke)) if not wall else "hand contact on the wall",
        "matches_paper": (name == PAPER.get(int(ke))) if not wall else None,
        "matches_issue_ladder": (name in ISSUE.get(PAPER.get(int(ke)), ())) if not wall else None,
        "node_ke": [round(x, 3) for x in r["node_ke"]],
        "final_ke": r["final_ke"], "nlp_count": r["nlp_count"],
        "nlp_times_s": [round(t, 3) for t in times],
        "median_nlp_s": statistics.median(times) if times else None,
        "nlp_cpu_s": [round(t, 3) for t in r["nlp_cpu_s"]],
        "nlp_build_s": [round(t, 3) for t in r["nlp_build_s"]],
        "total_time_s": round(r["total_time_s"], 3), "tree_nodes": r["tree_nodes"],
        "deepest_depth": r["deepest_depth"],
    }
    case["landings"] = [{k: (round(v, 3) if isinstance(v, float) else v) for k, v in x.to_dict().items()}
                        for x in r.get("landings", [])]
    case["landings_within_limits"] = r.get("landings_within_limits", False)
    # every tree node in short (what a failed case reached): mode, depth, node / pre-impact KE,
    # touchdown normal speed of its landing, the energy its self-motion ended with (None: not popped)
    tree = r.get("tree") or {"nodes": []}
    case["tree_summary"] = [
        {"id": n["id"], "parent": n["parent"], "depth": n["depth"], "mode": n["mode"], "ke": round(n["ke"], 2),
         "pre_impact_ke": None if n["pre_impact_ke"] is None else round(n["pre_impact_ke"], 2),
         "touchdown_normal_mps": None if n["landing"] is None else round(n["landing"]["normal_speed"], 2),
         "over_limits": n["over_limits"], "key": round(n["priority"], 2),
         "self_motion_end_ke": None if n["self_motion"] is None else round(n["self_motion"]["final_ke"], 3),
         "self_motion_ok": None if n["self_motion"] is None else n["self_motion"]["success"],
         "rejected": n.get("rejected")}
        for n in tree["nodes"]]
    hands = [x for x in case["landings"] if x["limb"] in ("LH", "RH")]
    case["max_hand_touchdown_normal_speed"] = max((x["normal_speed"] for x in hands), default=None)
    case["max_pre_impact_ke_over_push"] = (round(max(x["pre_impact_ke"] for x in case["landings"]) / ke, 3)
                                           if case["landings"] else None)
    if r["success"]:
        # eq. 6 at the start of each child segment: the impact map (eq. 10) may
        # throw joints past their velocity limits (not bounded in the NLP, see docs)
        import numpy as np
        nodes = r["tree"]["nodes"]
        vmax = planner.model.v_max
        case["max_node_joint_velocity_over_limit"] = round(max(
            float(np.max(np.abs(np.asarray(nodes[i]["v"])[3:]) / vmax)) for i in r["search"].path), 3)
        case["seed_attempts"] = sum(e["attempts"] for e in r["tree"]["nlp_log"])
        case["pre_impact_ke"] = [None if nodes[i]["pre_impact_ke"] is None else round(nodes[i]["pre_impact_ke"], 2)
                                 for i in r["search"].path]
        # normal impulse on the limb that lands (N s), and as the velocity change it would give the whole robot
        imp = [nodes[i]["landing_impulse"] for i in r["search"].path]
        case["landing_impulse_Ns"] = [None if x is None else round(x, 1) for x in imp]
        case["landing_impulse_over_mass_mps"] = [None if x is None else round(x / planner.model.total_mass, 2)
                                                 for x in case["landing_impulse_Ns"]]
    if resim and r["success"]:
        from humfall_ros.multicontact.resim import check_segment
        checks = [check_segment(planner.model, s, r["env"], planner.cfg.check_feedback_omega) for s in r["segments"]]
        keys = ("dyn_residual_rel_mg", "contact_pos_max_m", "sim_local_q_error_max",
                "sim_local_force_error_max_mg", "sim_local_unilateral_violation_mg",
                "track_local_q_error_max", "track_local_force_error_max_mg", "track_local_feedback_max",
                "track_tracked_end_q_error_max", "track_tracked_feedback_max")
        case["resim_worst"] = {k: round(float(max(c[k] for c in checks)), 4) for k in keys}
        # the whole plan executed under joint tracking, segment by segment from
        # each segment's first state: the kinetic energy the last one ends with
        case["tracked_final_ke"] = round(float(checks[-1]["track_tracked_end_ke"]), 4)
    r.pop("search", None)
    case["_result"] = r
    return case


_PLANNER = None


def _worker_init(overrides: dict) -> None:
    global _PLANNER
    _PLANNER = FallPlanner.from_params(**overrides)


def _worker_case(args) -> dict:
    ke, wall, budget, resim, mode = args
    case = run_case(_PLANNER, ke, wall, budget, resim, mode)
    case["build_s_worker_total"] = round(sum(_PLANNER.opt.build_times.values()), 2)
    case["worker_pid"] = os.getpid()
    return case


def run_sweep(args, overrides: dict) -> dict:
    """One sweep (+ wall case) with the planner built from the declaration plus ``overrides``."""
    kes = [float(x) for x in args.kes.split(",") if x]
    resim = not args.no_resim
    jobs = [(ke, 0.0, args.budget, resim, args.initial_mode) for ke in kes]
    # the paper's wall case starts on two feet (Fig. 4)
    wall_job = (args.wall_ke, args.wall, args.budget, resim, "LF/RF") if args.wall > 0 else None
    t0 = time.perf_counter()
    if args.jobs > 1:
        import multiprocessing as mp
        order = sorted(range(len(jobs)), key=lambda i: -jobs[i][0])   # long cases first
        with mp.get_context("spawn").Pool(args.jobs, initializer=_worker_init, initargs=(overrides,)) as pool:
            done = {}
            for i, case in zip(order, pool.imap(_worker_case, [jobs[i] for i in order], chunksize=1)):
                done[i] = case
            sweep_time = time.perf_counter() - t0
            wall_case = pool.apply(_worker_case, (wall_job,)) if wall_job else None
        cases = [done[i] for i in range(len(jobs))]
        planner = FallPlanner.from_params(**overrides)
        per_worker: dict = {}
        for c in cases + ([wall_case] if wall_case else []):
            per_worker[c["worker_pid"]] = max(per_worker.get(c["worker_pid"], 0.0), c["build_s_worker_total"])
        build_total = sum(per_worker.values())
    else:
        _worker_init(overrides)
        cases = [_worker_case(j) for j in jobs]
        sweep_time = time.perf_counter() - t0
        wall_case = _worker_case(wall_job) if wall_job else None
        planner = _PLANNER
        build_total = sum(_PLANNER.opt.build_times.values())
    total_time = time.perf_counter() - t0
    every = cases + ([wall_case] if wall_case else [])
    all_times = [t for c in every for t in c["nlp_times_s"]]
    solve_times = [t - b for c in every for t, b in zip(c["nlp_times_s"], c["nlp_build_s"])]
    ok = [c for c in every if c["success"] and "resim_worst" in c]
    out = {
        "overrides": overrides,
        "transition_objective": planner.opt.cfg.transition_objective,
        "opt_config": {k: (v if not hasattr(v, "__dataclass_fields__") else vars(v))
                       for k, v in vars(planner.opt.cfg).items()},
        "planner_config": vars(planner.cfg),
        "sweep": [{k: v for k, v in c.items() if not k.startswith("_")} for c in cases],
        "wall": {k: v for k, v in wall_case.items() if not k.startswith("_")} if wall_case else None,
        "sweep_and_wall_time_s": round(total_time, 2),
        "sweep_time_s": round(sweep_time, 2),
        "sweep_all_final_ke_below_eps": all(c["success"] and c["final_ke"] < 0.1 for c in cases),
        "cases_matching_the_paper": f"{sum(bool(c['matches_paper']) for c in cases)}/{len(cases)}",
        "cases_matching_the_issue_ladder": f"{sum(bool(c['matches_issue_ladder']) for c in cases)}/{len(cases)}",
        "wall_ends_with_hand_on_wall": None if wall_case is None else bool(wall_case["success"] and any(
            h in wall_case["contact_sequence"][-1].split("/") for h in ("LH", "RH"))),
        "nlp_count": len(all_times),
        "median_nlp_s": round(statistics.median(all_times), 3) if all_times else None,
        "median_nlp_solve_s": round(statistics.median(solve_times), 3) if solve_times else None,
        "max_nlp_s": round(max(all_times), 3) if all_times else None,
        "median_nlp_cpu_s": round(statistics.median([t for c in every for t in c["nlp_cpu_s"]]), 3)
        if all_times else None,
        "resim_worst_over_plans": {k: max(c["resim_worst"][k] for c in ok) for k in ok[0]["resim_worst"]}
        if ok else None,
        "load_average_1min_at_end": round(os.getloadavg()[0], 2),
        "build_s": round(build_total, 2),
    }
    if args.library:
        out["library"] = library_figures(out, cases, overrides, [float(x) for x in args.library.split(",")],
                                         [float(x) for x in args.library_entries.split(",") if x.strip()],
                                         args.budget)
    if args.plots:
        from humfall_ros.multicontact import plots
        tag = "" if not overrides else "_" + out["transition_objective"]
        out["plots"] = plots.write_all(planner.model, [c["_result"] for c in cases],
                                       wall_case["_result"] if wall_case else None, args.plots + tag)
    return out


def library_figures(run: dict, cases: list, overrides: dict, queries: list[float],
                    extra_entries: list[float] = (), budget: float = 120.0) -> dict:
    """Online use: the sweep's plans (and plans of ``extra_entries`` J, searched here) as a library,
    re-planned warm at ``queries`` (J)."""
    from humfall_ros.multicontact.library import LibraryEntry, PlanLibrary
    entries = [LibraryEntry(c["ke"], 1.0, 0.0, c["contact_sequence"], c["_result"]["segments"])
               for c in cases if c["success"]]
    planner = FallPlanner.from_params(**overrides)
    t0 = time.perf_counter()
    extra = PlanLibrary.build(planner, extra_entries, time_budget=budget).entries if extra_entries else []
    extra_s = time.perf_counter() - t0
    lib = PlanLibrary(sorted(entries + extra, key=lambda e: e.kinetic_energy))
    t0 = time.perf_counter()
    for e in lib.entries:   # what a running node has done once: build the structures the library uses
        for s in e.segments:
            planner.opt.prepare_warm(s, Environment())
    out = {"entries": [e.kinetic_energy for e in lib.entries],
           "entry_sequences": {str(e.kinetic_energy): " -> ".join(e.contact_sequence) for e in lib.entries},
           "extra_entries_requested": list(extra_entries), "extra_entries_search_s": round(extra_s, 2),
           "warm_start_multipliers": planner.opt.cfg.warm_start_multipliers,
           "structure_build_s": round(time.perf_counter() - t0, 2), "queries": []}
    for ke in queries:
        r = lib.replan(planner, {"kinetic_energy": ke, "direction": 1.0})
        out["queries"].append({
            "ke": ke, "success": r.success, "reason": r.reason, "time_s": round(r.time_s, 3),
            "nlp_times_s": [round(t, 3) for t in r.nlp_times_s],
            "iterations": [sg.iterations for sg in r.segments],
            "primal_fallbacks": sum(len(sg.attempt_log) > 1 for sg in r.segments),
            "entry_ke": r.entry.kinetic_energy if r.entry else None,
            "sequence": r.entry.contact_sequence if r.entry else None, "final_ke": r.final_ke,
            "landings": [{k: (round(v, 3) if isinstance(v, float) else v) for k, v in x.to_dict().items()}
                         for x in r.landings]})
    ok = [q["time_s"] for q in out["queries"] if q["success"] and q["ke"] <= 50]
    out["max_time_s_10_50J_successful"] = max(ok) if ok else None
    out["success_10_50J"] = f"{len(ok)}/{sum(1 for q in out['queries'] if q['ke'] <= 50)}"
    return out


def _row(c: dict | None) -> dict | None:
    if c is None:
        return None
    return {"success": c["success"], "sequence": " -> ".join(c["contact_sequence"]) or c["reason"],
            "final_ke": c["final_ke"], "time_s": c["total_time_s"],
            "landings": [f"{x['limb']}: {x['normal_speed']:.2f} m/s, pre {x['pre_impact_ke']:.1f} J, "
                         f"absorbed {x['absorbed_energy']:.1f} J" for x in c["landings"]]}


def table(paper: dict, departure: dict) -> list[dict]:
    """The same cases side by side: paper's objective vs the departure."""
    rows = []
    for a, b in zip(paper["sweep"] + [paper["wall"]], departure["sweep"] + [departure["wall"]]):
        if a is None:
            continue
        rows.append({"ke": a["ke"], "wall_distance": a["wall_distance"], "paper": a["paper_strategy"],
                     "pre_impact_objective": _row(a), "post_impact_objective": _row(b)})
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--kes", default="10,20,30,40,50,60,70,80")
    ap.add_argument("--wall", type=float, default=0.8, help="wall distance for the wall case (<= 0: skip)")
    ap.add_argument("--wall-ke", type=float, default=40.0)
    ap.add_argument("--initial-mode", default="LF/RF",
                    help="contact mode of every sweep case's start (LF/RF: the issue's two feet; RF: one foot, "
                         "as the paper's Figs. 1 and 3)")
    ap.add_argument("--budget", type=float, default=120.0, help="time budget per case (s; the node default)")
    ap.add_argument("--plots", default="", help="directory for the figures (Fig. 1, 5-7 style)")
    ap.add_argument("--no-resim", action="store_true", help="skip the independent re-simulation of the plans")
    ap.add_argument("--resim", action="store_true", help="(default, kept for old command lines)")
    ap.add_argument("--jobs", type=int, default=2, help="worker processes for the cases (1: in order, in-process)")
    ap.add_argument("--set", "--opt", dest="set", default="",
                    help="parameter overrides by yaml name, e.g. max_iter=300,transition_objective=post_impact")
    ap.add_argument("--compare", action="store_true",
                    help="also run the departure (post-impact objective) and print both side by side")
    ap.add_argument("--library", default="",
                    help="after the sweep: use its plans as a library and re-plan warm at these energies (J), "
                         "e.g. 12,15,25,35,45")
    ap.add_argument("--library-entries", default="",
                    help="with --library: more library entries (J), each planned by the tree search, e.g. 15,25,35")
    args = ap.parse_args(argv)
    overrides = parse_overrides(args.set)
    if args.library and args.initial_mode != "LF/RF":
        ap.error("--library: the library's entries and queries are two-foot pushes (--initial-mode LF/RF)")
    out = {"machine_cpus": os.cpu_count(), "jobs": args.jobs,
           "goals": {"final_ke_J": 0.1, "sweep_time_s": 120.0, "hand_touchdown_normal_speed_mps": 1.5,
                     "pre_impact_ke_over_push": 1.0}}
    main_run = run_sweep(args, overrides)
    out.update(main_run)
    if args.compare:
        dep = run_sweep(args, {**overrides, **DEPARTURE})
        out["departure"] = dep
        out["table"] = table(main_run, dep)
    print(json.dumps(out, indent=1, default=str))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
