"""E-stop planner timing (paper 3, issue 12): trigger to complete plan, and the feasibility IK apart.

Prints one JSON object. "plan" is :meth:`EstopPlanner.plan` (frame, Minor-axis gains re-placed
at the trigger height, Major-axis gains eq. 19-20, closed forms eq. 6-7/16, the ZMP check on
``samples`` points against the double-support polygon) from a pattern state at a double-support
start; goal <= 0.5 ms median. "posture" is the final-posture IK with the crouch search
(:func:`humfall_ros.estop.planner.settle_posture`), timed apart. Per walking speed (step length
= speed x 0.8 s period) the plan's n3, crouch and feasibility are reported too.

    python benchmarks/bench_estop.py [--repeats N]
"""
from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))   # the source tree, not an installed copy

from humfall_ros.estop.frame import FootPose
from humfall_ros.estop.planner import EstopPlanner, PatternState
from humfall_ros.estop.posture import configuration_from_feet
from humfall_ros.model.humanoid import load_model
from timing import timing_ms  # benchmarks/timing.py

PERIOD = 0.8      # s per step, as paper 3's Fig. 8
COG = 0.742       # m, the standing posture's CoG height


def state_at(model, speed_kmh: float) -> PatternState:
    """A double-support start after a step at ``speed_kmh`` (synthetic: rear sole at the origin, ZMP on it)."""
    v = speed_kmh / 3.6
    step = v * PERIOD
    ah = model.ankle_height
    feet = {"l": FootPose.flat(step - 0.025, 0.09, 0.0, ah), "r": FootPose.flat(-0.025, -0.09, 0.0, ah)}
    zmp = feet["r"].sole_center(model, "r")
    return PatternState(np.array([0.35 * step, -0.02, COG]), np.array([v, 0.1, 0.0]),
                        np.array([zmp[0], zmp[1], 0.0]), feet, COG)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=2000)
    args = ap.parse_args()
    from humfall_ros.sim.world import STANDING_POSTURE  # only for the IK seed of this benchmark

    m = load_model()
    planner = EstopPlanner(m)
    joints = m.joint_vector(STANDING_POSTURE)
    out: dict = {"goal_plan_median_ms": 0.5, "speeds": {}}
    plan_times: list[float] = []
    for speed in (0.5, 1.0, 1.35, 1.8, 2.5):
        st = state_at(m, speed)
        planner.plan(st)                                          # warm
        times = []
        for _ in range(max(1, args.repeats // 5)):
            t0 = time.perf_counter()
            planner.plan(st)
            times.append(time.perf_counter() - t0)
        plan_times += times
        q = configuration_from_feet(m, joints, st.feet, "r")
        t0 = time.perf_counter()
        full = planner.plan_with_posture(st, q)
        posture_s = time.perf_counter() - t0
        out["speeds"][str(speed)] = {
            "plan": timing_ms(times, extra=("min",)), "posture_ms": round(posture_s * 1e3, 2),
            "n3_m": round(full.major.n3, 4), "lower_bound_m": round(full.major.lower_bound, 4),
            "max_zmp_minor_m": round(full.minor.max_zmp, 4), "min_zmp_margin_m": round(full.min_zmp_margin, 4),
            "crouch_to_m": round(full.crouch.end_height, 3) if full.crouch else None,
            "feasible": full.feasible, "fallback": full.fallback, "reason": full.reason}
    out["plan"] = timing_ms(plan_times, extra=("min",))
    out["plan_meets_goal"] = out["plan"]["median_ms"] <= 0.5
    print(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
