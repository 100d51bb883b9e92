"""The multicontact executor's cost per control tick (issue 14); prints one JSON object.

    .venv/bin/python benchmarks/bench_multicontact_exec_tick.py [--plan multicontact_push_30J] [--plan ...]

Replays stored plans (``config/multicontact_plans``) after their push in process and times
``MulticontactExecutor.step`` on every tick after the take-over, split by what the tick did: a task-space swing
(the shared IK of paper 1's step controller, ``swing_control: task``) or joint tracking. The node runs at the
control rate (500 Hz: 2 ms a tick for the whole loop), so the goal for the executor's share is well under 1 ms.
"""
from __future__ import annotations

import argparse
import json
import os
import pathlib
import sys
import time

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from humfall_ros import scenario  # noqa: E402
from humfall_ros.multicontact.executor import MulticontactExecutor, StoredPlan  # noqa: E402
from humfall_ros.nodes.multicontact_executor import plan_path  # noqa: E402
from humfall_ros.sim.multicontact_run import execute  # noqa: E402
from timing import timing_ms  # noqa: E402  (benchmarks/timing.py)


def time_plan(name: str) -> dict:
    plan = StoredPlan.load(plan_path(name))
    f = plan.meta["push_force"]
    sc = scenario.load("multicontact_push", [f"push.0.force=[{f[0]}, {f[1]}, {f[2]}]"])
    sc["controllers"] = []
    swing, track = [], []
    original = MulticontactExecutor.step

    def timed(self, obs):
        t0 = time.perf_counter()
        out = original(self, obs)
        dt = time.perf_counter() - t0
        if self.take_over_time is not None and obs.time > self.take_over_time + 1e-9:
            swinging = any(a <= self._seg <= b for _, a, b in self._swings) and obs.inputs.get("imu") is not None
            (swing if swinging else track).append(dt)
        return out

    MulticontactExecutor.step = timed
    try:
        r = execute(sc, segments=plan.segments, start_time=plan.take_over_time)
    finally:
        MulticontactExecutor.step = original
    return {"plan": name, "contact_sequence": plan.meta.get("contact_sequence"),
            "task_swing_ticks": timing_ms(swing, extra=("max",)), "tracking_ticks": timing_ms(track, extra=("max",)),
            "final_mode": r.get("final_mode")}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--plan", action="append", default=None, help="stored plan name (repeatable)")
    a = ap.parse_args(argv)
    names = a.plan or ["multicontact_push_30J", "multicontact_push_20J"]
    out = {"load_average_start": os.getloadavg(), "goal_ms": 1.0, "plans": [time_plan(n) for n in names]}
    out["load_average_end"] = os.getloadavg()
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
