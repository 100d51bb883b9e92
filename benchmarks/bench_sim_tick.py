"""CPU per control tick of the bridge's simulator work, in process (no ROS): physics (targets + the tick's
physics substeps), sensing (joint states, IMU, ankle wrenches) and the ground-truth metrics, on
``standing_quiet`` with the standing posture held. ``bench_contract.py`` runs it in the base commit's
worktree and here, to tell the simulator's own cost (the physics changes since: rubber soles, per-substep
contacts, joint speed limits on the servos) from the graph's. Prints one JSON object (ms per tick, per
repeat; thread CPU time).

    python benchmarks/bench_sim_tick.py [--ticks 2500] [--repeats 3] [--repo PATH]
"""
from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ticks", type=int, default=2500)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--repo", default=str(pathlib.Path(__file__).resolve().parents[1]),
                    help="checkout whose humfall_ros to measure (default: this one)")
    a = ap.parse_args()
    sys.path.insert(0, a.repo)
    from humfall_ros import scenario as scenario_mod
    from humfall_ros.sim.ground_truth import GroundTruth
    from humfall_ros.sim.sensors import Sensors
    from humfall_ros.sim.world import SimWorld

    out_repo = str(pathlib.Path(sys.modules["humfall_ros"].__file__).resolve().parents[1])
    sc = scenario_mod.load("standing_quiet")
    s = sc["sim"]
    world = SimWorld(s["physics_rate"], s["control_rate"], friction=s["friction"],
                     contact_breaking_threshold=s["contact_breaking_threshold"])
    sensors, truth = Sensors(world), GroundTruth(world, sc)
    targets = world.targets.copy()
    out: dict = {"benchmark": "sim_tick", "repo": out_repo, "ticks": a.ticks, "physics_ms": [], "sensing_ms": [],
                 "ground_truth_ms": []}
    for _ in range(a.repeats):
        spent = [0.0, 0.0, 0.0]
        for _ in range(a.ticks):
            t0 = time.thread_time()
            world.set_joint_targets(targets)
            world.step_control()
            t1 = time.thread_time()
            sensors.read()
            t2 = time.thread_time()
            truth.track()
            t3 = time.thread_time()
            spent[0] += t1 - t0
            spent[1] += t2 - t1
            spent[2] += t3 - t2
        for key, x in zip(("physics_ms", "sensing_ms", "ground_truth_ms"), spent):
            out[key].append(round(x / a.ticks * 1e3, 4))
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
