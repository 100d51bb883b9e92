"""Walking benchmarks (one JSON object): pattern (re)generation, per-tick tracking cost, optional sim walks.

    python benchmarks/bench_walking.py            # pattern + per-tick figures
    python benchmarks/bench_walking.py --sim      # + PyBullet walks at 0.5 ... 2.5 km/h (slow: minutes)
"""
from __future__ import annotations

import json
import pathlib
import sys
import time

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from humfall_ros.control.contract import CentroidalObservation, Observation
from humfall_ros.model.humanoid import load_model
from humfall_ros.walking.config import LocomotionConfig
from humfall_ros.walking.controller import LocomotionController
from humfall_ros.walking.footsteps import Footstep, WalkCommand
from humfall_ros.walking.pattern import WalkingPattern


def pattern_generation(repeats: int = 5) -> dict:
    """Gains + footsteps + timeline + ZMP reference of a 20-step walk (the online pattern's whole plan)."""
    cfg = LocomotionConfig()
    feet = {"l": Footstep("l", 0.0, 0.09, 0.0), "r": Footstep("r", 0.0, -0.09, 0.0)}
    ts, ts_plan = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        p = WalkingPattern(cfg, 0.002, 0.18, 0.025, feet, [0.015, 0.0, 0.742], WalkCommand(1.8 / 3.6, 0.0), 20)
        t1 = time.perf_counter()
        while not p.ended:
            p._plan_step()
        p._zmp_array()
        t2 = time.perf_counter()
        ts.append(t2 - t0)
        ts_plan.append(t2 - t1)
    return {"pattern_generation_20_steps_ms": round(1e3 * float(np.median(ts)), 2),
            "of_which_footsteps_and_zmp_ms": round(1e3 * float(np.median(ts_plan)), 2),
            "goal_ms": 50}


def tracking_tick(seconds: float = 6.0) -> dict:
    """Per control tick: pattern step + multi-body correction + stabiliser + IK, on exact observations."""
    m = load_model()
    c = LocomotionController(m)
    q = c.reference_configuration(c.standing_posture, 0.0, (0.0, 0.0))
    c.set_walk_command(1.8 / 3.6, 0.0, n_steps=20)
    times = []
    t = 0.0
    for _ in range(int(seconds / c.dt)):
        qq = q if c.q_ik is None else c.q_ik
        m.forward(qq)
        com = m.com(qq)
        fc = 0.5 * (m.frame_position("l_foot") + m.frame_position("r_foot"))
        g = np.array([com[0], com[1], 0.0])
        st = CentroidalObservation(com, np.zeros(3), g, g, np.zeros(3), np.zeros((0, 2)), fc, 0.0, 0.0, m.weight,
                                   True, True, False)
        obs = Observation(round(t * 1e9), qq[7:].copy(), np.zeros(m.njoints), st, "locomotion", {})
        t0 = time.perf_counter()
        c.step(obs)
        times.append(time.perf_counter() - t0)
        t += c.dt
    ts = np.array(times[int(1.0 / c.dt):]) * 1e3  # after the start (the first tick builds the walk)
    return {"tick_ms_median": round(float(np.median(ts)), 3), "tick_ms_p99": round(float(np.percentile(ts, 99)), 3),
            "walk_start_ms": round(1e3 * max(times), 1), "goal_ms": {"median": 1.0, "p99": 2.0}}


def main() -> None:
    out = {"pattern": pattern_generation(), "tracking": tracking_tick()}
    if "--sim" in sys.argv:
        from walk_loop import run_walk

        out["sim"] = {}
        for kmh in (0.5, 1.0, 1.35, 1.8, 2.5):
            try:
                res, _ = run_walk(kmh, 20)
                out["sim"][str(kmh)] = res.as_dict()
            except RuntimeError as e:  # refused
                out["sim"][str(kmh)] = {"refused": str(e)}
    print(json.dumps(out))


if __name__ == "__main__":
    main()
