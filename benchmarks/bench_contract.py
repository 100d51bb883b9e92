"""Issue 9 figures: the suite's speed before and after the controller contract, and headroom.

Runs ``bench_suite.py`` of a base commit (default cc14160, the last commit before the
contract work; checked out in a temporary worktree, same venv) and of this checkout
alternately in one run, so both see the same machine; then this checkout with three
more idle per-tick controller nodes (``--standins 3``: lockstep sources answering every
tick with a release), as separate processes and composed (``--compose``). Prints one
JSON object: real-time factors (free-run as fast as it goes, at a 1.0 target, lockstep),
late ticks, CPU per simulated second per node.

    python benchmarks/bench_contract.py [--base cc14160] [--seconds 10] [--repeats 2] [--rounds 1] [--no-headroom]
"""
from __future__ import annotations

import argparse
import json
import os
import pathlib
import subprocess
import sys
import tempfile

REPO = pathlib.Path(__file__).resolve().parents[1]


def suite(repo: pathlib.Path, seconds: float, repeats: int, extra: list[str]) -> dict:
    cmd = [sys.executable, str(repo / "benchmarks" / "bench_suite.py"), "--seconds", str(seconds),
           "--repeats", str(repeats), *extra]
    env = dict(os.environ)
    env["PYTHONPATH"] = str(repo)
    p = subprocess.run(cmd, cwd=repo, env=env, capture_output=True, text=True)
    try:
        d = json.loads(p.stdout[p.stdout.index("{"):])
    except ValueError:
        return {"error": f"exit {p.returncode}", "stderr_tail": p.stderr[-1500:]}
    fr = d["free_run_max"]
    return {"load_average_1min_before": d["load_average_1min_before"],
            "free_run_max_rtf": [r["real_time_factor"] for r in fr["runs"]],
            "free_run_max_late_ticks": fr["uncontrolled_ticks"], "ticks": fr["ticks"],
            "free_run_target_1_rtf": d["free_run_target_1"]["real_time_factor"],
            "free_run_target_1_late_ticks": d["free_run_target_1"]["uncontrolled_ticks"],
            "lockstep_rtf": d["lockstep"]["real_time_factor"],
            "lockstep_tick_ms_median": (d["lockstep"].get("hops_ms") or {}).get("tick_total"),
            "cpu_cores_per_sim_second": d["cpu_cores_per_sim_second"]}


def sim_tick(repo: pathlib.Path) -> dict:
    """The simulator's own CPU per tick in ``repo`` (bench_sim_tick.py, this checkout's copy: the base has none)."""
    p = subprocess.run([sys.executable, str(REPO / "benchmarks" / "bench_sim_tick.py"), "--ticks", "1500",
                        "--repo", str(repo)], cwd=repo, capture_output=True, text=True)
    try:
        return json.loads(p.stdout[p.stdout.index("{"):])
    except ValueError:
        return {"error": f"exit {p.returncode}", "stderr_tail": p.stderr[-1500:]}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--base", default="cc14160")
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--rounds", type=int, default=1, help="base/head alternations")
    ap.add_argument("--no-headroom", action="store_true", help="only base vs head (no stand-in runs)")
    a = ap.parse_args()
    out: dict = {"benchmark": "contract", "cpu_count": os.cpu_count(), "base": a.base, "base_vs_head": []}
    with tempfile.TemporaryDirectory() as tmp:
        wt = pathlib.Path(tmp) / "base"
        subprocess.run(["git", "-C", str(REPO), "worktree", "add", "--detach", str(wt), a.base], check=True,
                       capture_output=True)
        try:
            for _ in range(a.rounds):
                out["base_vs_head"].append({"base": suite(wt, a.seconds, a.repeats, []),
                                            "head": suite(REPO, a.seconds, a.repeats, [])})
            # the simulator alone (physics, sensing, metrics), base and here: what of the difference is not the graph
            out["sim_tick_base"], out["sim_tick_head"] = sim_tick(wt), sim_tick(REPO)
        finally:
            subprocess.run(["git", "-C", str(REPO), "worktree", "remove", "--force", str(wt)], capture_output=True)
    if a.no_headroom:
        print(json.dumps(out, indent=2))
        return 0
    out["head_3_standins_separate"] = suite(REPO, a.seconds, a.repeats, ["--standins", "3"])
    out["head_3_standins_composed"] = suite(REPO, a.seconds, a.repeats, ["--standins", "3", "--compose"])
    out["head_composed"] = suite(REPO, a.seconds, a.repeats, ["--compose"])
    print(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
