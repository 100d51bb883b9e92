"""Online re-plans from a library of precomputed fall plans (issue 14's speed goal: <= 1 s for 10-50 J).
Prints one JSON object.

    python benchmarks/bench_multicontact_library.py [--library multicontact_library/standing_pushes.json.gz]
        [--queries 11,12,14,16,...,48,49] [--direction 1] [--wall 0] [--repeats 2] [--budget 10]
        [--set name=value,...] [--profile execution]

The planner is the node's (config/multicontact_planner.yaml) with ``library_file`` set: each query is a
``FallPlanner.plan`` request, answered by a warm re-plan of the nearest entry (or, when that is not
accepted, by the tree search: ``source``). The library's structures and warm-start solvers are built
first, as the node's warm-up does (``warm_up_s``, not in the query times). ``--set
warm_start_multipliers=false`` measures the primal-only warm start of sessions 20-24, ``--set
check_workers=0`` the check in process (before session 33).
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from humfall_ros.multicontact.planner import PROFILES, FallPlanner  # noqa: E402
from humfall_ros.params import parse_overrides  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--library", default="multicontact_library/standing_pushes.json.gz")
    ap.add_argument("--queries", default="11,12,14,16,17,19,21,24,26,29,31,34,36,39,41,44,46,48,49",
                    help="request energies (J); the default: between the shipped forward entries, 10-50 J")
    ap.add_argument("--direction", type=float, default=1.0, help="of every query: +1 forward, -1 backward")
    ap.add_argument("--wall", type=float, default=0.0, help="of every query: wall distance (m; 0 = none)")
    ap.add_argument("--repeats", type=int, default=2, help="each query this many times (the median is kept)")
    ap.add_argument("--budget", type=float, default=10.0,
                    help="each request's time budget (s): what the library does not answer goes to the tree search "
                         "for what is left of it (the node's default is 120 s; 10 keeps `make bench` short)")
    ap.add_argument("--set", default="", help="planner parameter overrides, name=value,...")
    ap.add_argument("--profile", default="", choices=("", *PROFILES),
                    help="a request profile's planner and library (planner.PROFILES; --library then ignored)")
    a = ap.parse_args(argv)
    if a.profile:
        a.library = PROFILES[a.profile].get("library_file", a.library)
    planner = FallPlanner.from_params(**{"library_file": a.library, **PROFILES.get(a.profile, {}),
                                         **parse_overrides(a.set)})
    t0 = time.perf_counter()
    planner.warm_up_library()
    warm_up = time.perf_counter() - t0
    rows = []
    for ke in (float(x) for x in a.queries.split(",") if x.strip()):
        req = {"kinetic_energy": ke, "direction": a.direction, "wall_distance": a.wall, "time_budget": a.budget}
        runs = [planner.plan(req) for _ in range(max(1, a.repeats))]
        r = runs[-1]
        rows.append({"ke": ke, "success": r["success"], "source": r["source"],
                     "entry": r["reason"].split(" (")[0] if r["source"] == "library" else None,
                     "sequence": " -> ".join(r["contact_sequence"]), "final_ke": r["final_ke"],
                     "time_s": round(statistics.median(x["total_time_s"] for x in runs), 3),
                     "times_s": [round(x["total_time_s"], 3) for x in runs],
                     "nlp_times_s": [round(t, 3) for t in r["nlp_times_s"]],
                     "iterations": [s.iterations for s in r["segments"]],
                     "primal_fallbacks": sum(len(s.attempt_log) > 1 for s in r["segments"])
                     if r["source"] == "library" else None,
                     "landings": [f"{x.limb}: {x.normal_speed:.2f} m/s normal, pre {x.pre_impact_ke:.1f} J"
                                  for x in r["landings"]],
                     "library_attempt": r.get("library_attempt")})
    lib_rows = [x for x in rows if x["source"] == "library" and x["success"]]
    times = [x["time_s"] for x in lib_rows]
    out = {"library": a.library, "profile": a.profile, "direction": a.direction, "wall": a.wall,
           "entries": [(e.kinetic_energy, e.direction, e.wall_distance) for e in planner.library.entries],
           "warm_start_multipliers": planner.opt.cfg.warm_start_multipliers,
           "library_check": planner.cfg.library_check, "check_workers": planner.cfg.check_workers,
           "library_max_entries": planner.cfg.library_max_entries,
           "warm_up_s": round(warm_up, 2), "time_budget_s": a.budget,
           "queries": rows, "answered_from_library": f"{len(lib_rows)}/{len(rows)}",
           "within_1s": f"{sum(t <= 1.0 for t in times)}/{len(rows)}",
           "median_s": round(statistics.median(times), 3) if times else None,
           "max_s": round(max(times), 3) if times else None,
           "load_average_1min_at_end": round(os.getloadavg()[0], 2)}
    print(json.dumps(out, indent=1, default=str))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
