"""Campaign figures of issue 13; prints one JSON object.

    python benchmarks/bench_campaign.py --part threshold     # 12 directions x 3 heights to 5 N (~250 trials)
    python benchmarks/bench_campaign.py --part pushes        # 1,000 standing pushes on Ray, 2 workers
    python benchmarks/bench_campaign.py --part speedup --n 200   # the first N trials on Ray 1 / Ray 2 / local 2 workers
    python benchmarks/bench_campaign.py --part interrupt --repeats 5   # Ctrl-C at a random moment, processes left
    python benchmarks/bench_campaign.py --part all --quick   # everything, tiny (a few trials of 1 s)

Every run records the machine's load average before and after (the machine is shared)
and its folder under runs/bench_campaign/.
"""
from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import pathlib
import random
import signal
import subprocess
import sys
import time
import uuid

import numpy as np
import yaml

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from humfall_ros.campaign import spec as spec_mod
from humfall_ros.campaign.report import thresholds, write_report
from humfall_ros.campaign.runner import RunOptions, run_campaign
from humfall_ros.campaign.server import TAG_ENV, tagged_pids
from humfall_ros.campaign.store import comparable, load_results

OUT = ROOT / "runs" / "bench_campaign"


def stamp() -> str:
    return dt.datetime.now().strftime("%Y%m%d-%H%M%S")


def load() -> list[float]:
    return [round(x, 2) for x in os.getloadavg()]


def _with(spec, out: pathlib.Path, n: int | None = None, extra_set: list[str] | None = None,
          directions: int | None = None):
    upd = {"output": spec.output.model_copy(update={"dir": str(out)})}
    if n is not None:
        upd["design"] = spec.design.model_copy(update={"random": spec.design.random.model_copy(update={"n": n})})
    if extra_set:
        upd["set"] = [*spec.set, *extra_set]
    if directions is not None:
        grid = dict(spec.design.grid)
        grid["push.0.direction_deg"] = spec_mod.Circle(circle=directions)
        grid["push.0.height_m"] = [0.2]
        upd["design"] = spec.design.model_copy(update={"grid": grid})
    return spec.model_copy(update=upd)


def _run(spec, executor: str, workers: int) -> dict:
    l0, t0 = load(), time.monotonic()
    s = run_campaign(spec, RunOptions(executor=executor, workers=workers, progress=sys.stderr.isatty(),
                                      fresh=True))
    total = time.monotonic() - t0
    table, _ = load_results(s.results)
    rows = table.to_pylist()
    wall = np.array([r["wall_s"] for r in rows if r["wall_s"] is not None])
    cpu = np.array([r["cpu_s"] for r in rows if r["cpu_s"] is not None])
    hwm = np.array([r["server_hwm_mb"] for r in rows if r["server_hwm_mb"] is not None])
    wrss = np.array([r["worker_rss_mb"] for r in rows if r["worker_rss_mb"] is not None])
    return {"executor": executor, "workers": workers, "trials": s.ran, "status": s.status_counts,
            "campaign_wall_s": round(s.wall_s, 1), "wall_incl_startup_s": round(total, 1),
            "trials_per_minute": round(s.trials_per_minute, 2),
            "trial_wall_s_median": round(float(np.median(wall)), 3) if len(wall) else None,
            "trial_cpu_s_median": round(float(np.median(cpu)), 3) if len(cpu) else None,
            "trial_cpu_s_mean": round(float(np.mean(cpu)), 3) if len(cpu) else None,
            "trial_sim_s_mean": round(float(np.nanmean([r.get("m.sim_duration_s") or np.nan for r in rows])), 3),
            "trial_server_peak_rss_mb_max": round(float(hwm.max()), 1) if len(hwm) else None,
            "worker_rss_mb_median": round(float(np.median(wrss)), 1) if len(wrss) else None,
            "load_before": l0, "load_after": load(), "results": s.results,
            "started": dt.datetime.now().isoformat(timespec="seconds")}


def part_threshold(quick: bool, workers: int) -> dict:
    spec = spec_mod.load(ROOT / "config" / "campaigns" / "threshold_map.yaml")
    if quick:
        spec = _with(spec, OUT / f"threshold-quick-{stamp()}", directions=2)
        spec = spec.model_copy(update={"study": spec.study.model_copy(update={"tolerance": 100.0})})
    else:
        spec = _with(spec, OUT / f"threshold-{stamp()}")
    r = _run(spec, "ray", workers)
    table, meta = load_results(r["results"])
    th = thresholds(table, meta["spec"])
    r["thresholds"] = [{"direction_deg": t.point.get("push.0.direction_deg"),
                        "height_m": t.point.get("push.0.height_m"), "low_n": t.low, "high_n": t.high,
                        "status": t.status,
                        "fall_direction_deg": None if t.fall_direction_deg is None else round(t.fall_direction_deg, 1)}
                       for t in th]
    r["report"] = str(write_report(r["results"]))
    return r


def part_pushes(quick: bool, workers: int, n: int | None) -> dict:
    """The 1,000-push campaign on Ray: wall time, trials per minute, memory."""
    spec = spec_mod.load(ROOT / "config" / "campaigns" / "standing_push_1000.yaml")
    n = 6 if quick else n
    extra = ["duration=1.0"] if quick else None
    a = _run(_with(spec, OUT / f"pushes-ray-{stamp()}", n, extra), "ray", workers)
    ta, _ = load_results(a["results"])
    fell = [x for x in ta.column("m.fell").to_pylist() if x is not None]
    a["fall_rate"] = round(sum(fell) / max(1, len(fell)), 3)
    a["report"] = str(write_report(a["results"]))
    return a


def part_speedup(quick: bool, n: int) -> dict:
    """The first n trials of the same design on 1 and 2 Ray workers, and on a local (no-Ray) pool of 2."""
    spec = spec_mod.load(ROOT / "config" / "campaigns" / "standing_push_1000.yaml")
    n = 4 if quick else n
    extra = ["duration=1.0"] if quick else None
    one = _run(_with(spec, OUT / f"speedup-ray1-{stamp()}", n, extra), "ray", 1)
    two = _run(_with(spec, OUT / f"speedup-ray2-{stamp()}", n, extra), "ray", 2)
    loc = _run(_with(spec, OUT / f"speedup-local2-{stamp()}", n, extra), "local", 2)
    tables = [comparable(load_results(r["results"])[0]) for r in (one, two, loc)]
    common = [c for c in tables[0].column_names if all(c in t.column_names for t in tables)]
    return {"n": n, "ray_1_worker": one, "ray_2_workers": two, "local_2_workers": loc,
            "speedup_1_to_2_campaign_wall": round(one["campaign_wall_s"] / two["campaign_wall_s"], 3),
            "speedup_1_to_2_incl_ray_startup": round(one["wall_incl_startup_s"] / two["wall_incl_startup_s"], 3),
            "identical_table_ray1_ray2_local": tables[0].equals(tables[1]) and tables[1].equals(tables[2]),
            # a commit landing between the runs can add metric columns: compare what all three have
            "identical_on_common_columns": all(t.select(common).equals(tables[0].select(common)) for t in tables),
            "columns_not_in_all": sorted({c for t in tables for c in t.column_names} - set(common))}


def _cmdline(pid: int) -> str:
    try:
        return pathlib.Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""


def _tree_pids(tag: str) -> list[int]:
    return tagged_pids(TAG_ENV, tag)


def part_interrupt(repeats: int, max_delay: float) -> dict:
    """Start a campaign subprocess (Ray, 2 workers), SIGINT its process group at a random moment, count leftovers."""
    spec = spec_mod.load(ROOT / "config" / "campaigns" / "standing_push_1000.yaml")
    out = []
    rng = random.Random()
    for k in range(repeats):
        d = OUT / f"interrupt-{stamp()}-{k}"
        spec_k = _with(spec, d, 40, ["duration=1.5"])
        d.mkdir(parents=True, exist_ok=True)
        spec_path = d.parent / f"{d.name}.yaml"
        spec_path.write_text(yaml.safe_dump(spec_k.model_dump(mode="json")))
        tag = uuid.uuid4().hex
        env = {**os.environ, TAG_ENV: tag, "PYTHONPATH": str(ROOT)}
        p = subprocess.Popen([sys.executable, "-m", "humfall_ros.campaign.cli", str(spec_path), "--workers", "2",
                              "--no-progress", "--fresh"], env=env, cwd=str(ROOT), start_new_session=True,
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        delay = rng.uniform(0.5, max_delay)
        time.sleep(delay)
        before = len(_tree_pids(tag))
        os.killpg(p.pid, signal.SIGINT)
        try:
            p.wait(90)
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)
        t_exit = time.monotonic()
        left = _tree_pids(tag)
        left_10 = None
        while left and time.monotonic() - t_exit < 60:
            time.sleep(0.5)
            left = _tree_pids(tag)
            if left_10 is None and time.monotonic() - t_exit >= 10:
                left_10 = [_cmdline(q)[:80] for q in left]
        try:
            done = load_results(d)[0].num_rows
        except FileNotFoundError:
            done = 0
        out.append({"delay_s": round(delay, 2), "processes_before": before, "exit": p.returncode,
                    "processes_left_after_10s": len(left_10 or []), "left_after_10s": left_10 or [],
                    "processes_left_after_60s": len(left),
                    "seconds_to_none_left": None if left else round(time.monotonic() - t_exit, 1),
                    "trials_finished": done})
    return {"repeats": out, "max_left_10s": max(r["processes_left_after_10s"] for r in out),
            "max_left_60s": max(r["processes_left_after_60s"] for r in out)}


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--part", choices=["threshold", "pushes", "speedup", "interrupt", "all"], default="all")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--n", type=int, default=None, help="trials for pushes (default 1000) / speedup (default 200)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--max-delay", type=float, default=30.0, help="latest Ctrl-C moment [s] (Ray starts in ~10 s)")
    a = ap.parse_args()
    OUT.mkdir(parents=True, exist_ok=True)
    res = {"machine": {"cores": os.cpu_count(), "load_at_start": load()}}
    if a.part in ("threshold", "all"):
        res["threshold_map"] = part_threshold(a.quick, a.workers)
    if a.part in ("pushes", "all"):
        res["pushes"] = part_pushes(a.quick, a.workers, a.n)
    if a.part in ("speedup", "all"):
        res["speedup"] = part_speedup(a.quick, a.n or 200)
    if a.part in ("interrupt", "all"):
        res["interrupt"] = part_interrupt(1 if a.quick else a.repeats, 15.0 if a.quick else a.max_delay)
    runs = [r for r in (res.get("pushes"), res.get("speedup", {}).get("ray_2_workers")) if r]
    if runs:
        best = max(runs, key=lambda r: r["trials"])
        per_core_hour = best["trials_per_minute"] * 60.0 / best["workers"]
        # on a shared machine the wall-clock rate is the other jobs' business; the CPU a trial takes is not
        per_cpu_hour = 3600.0 / best["trial_cpu_s_mean"]
        res["scale"] = {"from": best["results"], "trials_per_hour_per_core_wall": round(per_core_hour, 1),
                        "trials_per_cpu_hour": round(per_cpu_hour, 1),
                        "cores_for_1e6_trials_in_10h_wall": int(np.ceil(1e6 / (10.0 * per_core_hour))),
                        "cores_for_1e6_trials_in_10h_cpu": int(np.ceil(1e6 / (10.0 * per_cpu_hour)))}
    res["machine"]["load_at_end"] = load()
    print(json.dumps(res, indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
