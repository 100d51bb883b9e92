"""Safe-fall timings (issue 11): FTB per message, control duration, the whole decision; prints one JSON object.

    .venv/bin/python benchmarks/bench_fall.py

The decision is timed on the real take-over state of ``standing_push`` (the loop runs until the
FTB fires, ~1 s): pendulum + stepping zones + search (``SafeFallDecision.search_time``), and apart
from it the eq.-9 IK check of the chosen landing. Goals: FTB <= 0.1 ms per message; decision
<= 2 ms median with >= 2,000 cells; halving the cell size changes the chosen alpha2 by <= 2 deg.
"""
from __future__ import annotations

import json
import math
import pathlib
import statistics
import sys
import time

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from humfall_ros import params, scenario  # noqa: E402
from humfall_ros.dynamics.toppling import time_to_lean  # noqa: E402
from humfall_ros.fall.controller import SafeFallConfig, SafeFallController  # noqa: E402
from humfall_ros.fall.ftb import FtbConfig, FtbMonitor  # noqa: E402


def _stats(xs: list[float]) -> dict:
    xs = sorted(xs)
    return {"median_ms": round(statistics.median(xs) * 1e3, 4), "p99_ms": round(xs[int(0.99 * (len(xs) - 1))] * 1e3, 4),
            "n": len(xs)}


def capture_takeover(name: str = "standing_push", overrides: list[str] | None = None):
    """(observations of the run up to the trigger, the trigger observation, the event), on ClosedLoop."""
    from humfall_ros.fall import runs
    from humfall_ros.sim.closed_loop import ClosedLoop

    sc = scenario.load(name, overrides)
    ctrls, monitors = runs.controllers_for(sc, "none")
    loop = ClosedLoop(sc, ctrls, monitors)
    seen = []
    try:
        for _ in range(int(1.5 * sc["sim"]["control_rate"])):
            obs = loop.step()
            seen.append(obs)
            st = obs.inputs["ftb/status"]
            if st.event is not None:
                return seen, obs, st.event
    finally:
        loop.close()
    raise RuntimeError("the FTB did not fire")


def main() -> None:
    seen, obs, ev = capture_takeover()
    # FTB per message over the recorded observations
    mon = FtbMonitor(FtbConfig.from_params(params.defaults("ftb_monitor")))
    ftb_t = []
    ftb_cpu = []
    for _ in range(3):
        mon.reset()
        for o in seen:
            t0, c0 = time.perf_counter(), time.thread_time()
            mon.step(o)
            ftb_t.append(time.perf_counter() - t0)
            ftb_cpu.append(time.thread_time() - c0)
    # control duration (elliptic)
    f = mon.step(obs).features
    cd_t = []
    for _ in range(2000):
        t0 = time.perf_counter()
        r = time_to_lean(f.theta, f.theta_dot, math.radians(15), f.pendulum_length)
        cd_t.append(time.perf_counter() - t0)
    # the whole decision
    obs.inputs["fall_event"] = ev
    cfg = SafeFallConfig.from_params(params.defaults("safe_fall_controller"))
    ctrl = SafeFallController(config=cfg)
    dec_t, ik_t, cpu_t = [], [], []
    for _ in range(30):
        ctrl.reset()
        t0, c0 = time.perf_counter(), time.thread_time()
        ctrl.step(obs)
        total = time.perf_counter() - t0
        cpu_t.append(time.thread_time() - c0)
        dec_t.append(ctrl.decision.search_time)
        ik_t.append(total - ctrl.decision.search_time)
    d = ctrl.decision
    # halved cells
    fine = SafeFallController(config=SafeFallConfig.from_params({**params.defaults("safe_fall_controller"),
                                                                 "cell_xy": cfg.cell_xy / 2,
                                                                 "cell_yaw": cfg.cell_yaw / 2}))
    fine.step(obs)
    fd = fine.decision

    def deg(x):
        return None if not math.isfinite(x) else round(math.degrees(x), 2)

    out = {
        "ftb_per_message": {**_stats(ftb_t), "goal_ms": 0.1, "cpu": _stats(ftb_cpu)},
        "control_duration": {**_stats(cd_t), "value_s": r.time, "outcome": r.outcome.value},
        "decision": {**_stats(dec_t), "goal_ms": 2.0, "cells": d.cell_count, "case": d.case,
                     "alpha2_deg": deg(d.alpha2), "captured": d.captured, "zone_size_m": d.zone_size.tolist()},
        "ik_check_and_start": _stats(ik_t),
        # CPU time of the whole take-over tick (decision + IK check + first swing command): what the
        # decision costs without the waits of a shared, overloaded machine
        "takeover_tick_cpu": _stats(cpu_t),
        "load_average": round(__import__("os").getloadavg()[0], 1),
        "halved_cells": {"cells": fd.cell_count, "case": fd.case, "alpha2_deg": deg(fd.alpha2), "captured": fd.captured,
                         "landing_change_m": float(np.linalg.norm(fd.landing[:2] - d.landing[:2]))
                         if np.all(np.isfinite(fd.landing)) and np.all(np.isfinite(d.landing)) else None,
                         "search_median_ms": round(fd.search_time * 1e3, 3)},
    }
    print(json.dumps(out))


if __name__ == "__main__":
    main()
