"""Build a library of fall plans (``library.py``) by the tree search, or merge library files:
``python -m humfall_ros.multicontact.build_library --kes 10,15,20,25,30,35 --out FILE``."""
from __future__ import annotations

import time

from humfall_ros.multicontact.library import PlanLibrary
from humfall_ros.multicontact.planner import FallPlanner
from humfall_ros.params import parse_overrides


def main(argv=None) -> int:
    """Build a library file: ``python -m humfall_ros.multicontact.build_library --kes 10,15,20,25,30,35
    --out FILE [--directions 1] [--walls 0] [--budget 120] [--set name=value,...] [--add LIB ...]
    [--densify STEP] [--probe] [--plot PNG]``
    (the planner from config/multicontact_planner.yaml, ``--set`` overrides by parameter name; ``--add``
    takes the entries of existing library files too, which must fit the planner; ``--densify STEP`` adds,
    between neighbouring entries without a wall, the energies STEP J apart as accepted warm re-plans of their
    neighbours (``PlanLibrary.densify``); ``--probe`` re-plans
    every entry half way to its neighbours and stores the outcome, for the online ranking:
    ``PlanLibrary.probe``). Pushes without a plan are left out and listed."""
    import argparse
    import sys

    ap = argparse.ArgumentParser(prog="python -m humfall_ros.multicontact.build_library", description=main.__doc__)
    ap.add_argument("--kes", default="", help="push kinetic energies (J), comma-separated")
    ap.add_argument("--add", action="append", default=[], help="a library file whose entries to include")
    ap.add_argument("--directions", default="1", help="+1 forward, -1 backward, comma-separated")
    ap.add_argument("--walls", default="0", help="wall distances (m; 0 = no wall), comma-separated")
    ap.add_argument("--budget", type=float, default=120.0, help="tree-search budget per push (s)")
    ap.add_argument("--set", default="", help="planner parameter overrides, name=value,... (YAML values)")
    ap.add_argument("--out", required=True)
    ap.add_argument("--densify", type=float, default=0.0,
                    help="add entries this many J apart between neighbouring entries without a wall, each an "
                         "accepted warm re-plan of its neighbours (0: none)")
    ap.add_argument("--probe", action="store_true",
                    help="re-plan each entry half way to its neighbours and store whether it was accepted")
    ap.add_argument("--plot", default="", help="also draw what the library holds (its landings) to this PNG")
    a = ap.parse_args(argv)
    overrides = parse_overrides(a.set)
    floats = lambda text: [float(x) for x in text.split(",") if x.strip()]  # noqa: E731
    if not floats(a.kes) and not a.add:
        ap.error("nothing to put in the library: give --kes and/or --add")
    planner = FallPlanner.from_params(**overrides)
    t0 = time.perf_counter()
    lib = PlanLibrary.build(planner, floats(a.kes), floats(a.directions), floats(a.walls), a.budget)
    # one file holds plans of one capture-cost weight (its re-plans solve with it): the searched plans' and
    # the added files' (a merge without a search keeps the files' weight, whatever the planner's)
    weights = {"this build's searches": lib.capture_weight} if floats(a.kes) else {}
    margin_said = bool(floats(a.kes))   # the searches' margin is the planner's; so is any added file's that says
    for path in a.add:
        other = PlanLibrary.load(path)
        other.check_compatible(planner.opt.cfg)
        margin_said = margin_said or "step_capture_margin" in other.built_with
        if other.capture_weight is not None:
            weights[path] = other.capture_weight
        lib.entries += other.entries
    if len(set(weights.values())) > 1:
        raise SystemExit("plans of different step_capture_weight cannot share a library: "
                         + ", ".join(f"{k} {w:g}" for k, w in weights.items()))
    if weights:
        lib.built_with["step_capture_weight"] = next(iter(weights.values()))
    else:   # only files that do not say: neither does the merge (their re-plans use the planner's weight)
        lib.built_with.pop("step_capture_weight", None)
    if not margin_said:   # likewise the step capture margin (check_compatible: a file's that says is the planner's)
        lib.built_with.pop("step_capture_margin", None)
    lib.entries.sort(key=lambda e: (e.wall_distance, -e.direction, e.kinetic_energy))
    if a.densify > 0:
        t1 = time.perf_counter()
        new = lib.densify(planner, a.densify, log=print)
        print(f"densify: {len(new)} entries added, {time.perf_counter() - t1:.1f} s")
    if a.probe:
        t1 = time.perf_counter()
        lib.probe(planner, log=print)
        fails = sum(not ok for e in lib.entries for ok in e.probes.values())
        print(f"probes: {sum(len(e.probes) for e in lib.entries)} re-plans, {fails} not accepted, "
              f"{time.perf_counter() - t1:.1f} s")
    lib.save(a.out)
    have = {(e.kinetic_energy, e.direction, e.wall_distance) for e in lib.entries}
    missing = [k for k in ((ke, d, w) for w in floats(a.walls) for d in floats(a.directions)
                           for ke in floats(a.kes)) if k not in have]
    for e in lib.entries:
        print(f"{e.kinetic_energy:g} J, direction {e.direction:+g}, wall {e.wall_distance:g} m: "
              f"{' -> '.join(e.contact_sequence)}"
              + (f" (re-solved from {e.derived_from:g} J)" if e.derived_from is not None else ""))
    for ke, d, w in missing:
        print(f"{ke:g} J, direction {d:+g}, wall {w:g} m: no plan (left out)", file=sys.stderr)
    print(f"{len(lib.entries)} plans in {time.perf_counter() - t0:.1f} s -> {a.out}")
    if a.plot:
        from humfall_ros.multicontact.plots import plot_library
        print(plot_library(planner.model, lib, a.plot, planner.opt.cfg.landing_limits))
    return 0 if lib.entries else 1


if __name__ == "__main__":
    raise SystemExit(main())
