"""Whole-suite speed: real-time factor in lockstep and free-run, and per-hop latency.

Starts `humfall up` (every node its own process, recorder included) on
standing_quiet in a private ROS domain on localhost: free-running as fast as it
can (``--repeats`` times, since the figure moves with the machine's load), once
at a 1.0 target and once in lockstep. Reads the sim/wall times and each node's
CPU from result.json; a 1 s run gives the start-up CPU to subtract, so the
per-node figure is CPU per simulated second. During the lockstep run a probe
node in this process timestamps, per control tick, the arrival of joint_states
(bridge out), centroidal_state (estimator out), joint_command/locomotion
(controller out) and the next tick's joint_states (bridge stepped): the three
hops of sim -> estimator -> controller -> sim. The probe's own delivery delay
is in every timestamp alike, so differences are the hops. Prints one JSON object.

    python benchmarks/bench_suite.py [--seconds 10] [--control-rate 500] [--repeats 3] [--scenario walking]
"""
from __future__ import annotations

import argparse
import json
import os
import pathlib
import subprocess
import sys
import tempfile
import time

import numpy as np

REPO = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def standin_overrides(n: int) -> list[str]:
    """``--set`` for n idle per-tick controller nodes (test/takeover_controller.py, never taking over)."""
    if n <= 0:
        return []
    node = REPO / "test" / "takeover_controller.py"
    items = ", ".join(f"{{node: {node}, source: standin{i}, priority: {40 + i}, "
                      f"params: {{source: standin{i}, take_over_time: -1.0}}}}" for i in range(1, n + 1))
    return ["--set", f"controllers=[{items}]"]


COMPOSE = False  # --compose: the estimator and the controllers in one process
SCENARIO = "standing_quiet"  # --scenario: e.g. walking (the walking suite, issue 10)


def up(seconds: float, rate: float, lockstep: bool, rtf: float, runs: pathlib.Path, env: dict,
       probe: bool = False, standins: int = 0) -> dict:
    cmd = [sys.executable, "-m", "humfall_ros.cli", "up", "--scenario", SCENARIO, "--runs-dir", str(runs),
           "--no-plots", "--set", f"duration={seconds}", "--set", f"sim.control_rate={rate}",
           "--set", f"sim.lockstep={str(lockstep).lower()}", "--set", f"sim.real_time_factor={rtf}",
           *standin_overrides(standins), *(["--compose"] if COMPOSE else [])]
    before = set(runs.glob("*")) if runs.exists() else set()
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    hops = run_probe(proc) if probe else None
    proc.wait()
    (run_dir,) = set(runs.glob("*")) - before
    r = json.loads((run_dir / "result.json").read_text())
    bridge_wall = r["metrics"].get("bridge_wall_time_s")
    out = {"sim_s": r["sim_duration_s"], "bridge_wall_s": bridge_wall,
           "real_time_factor": round(r["sim_duration_s"] / bridge_wall, 3) if bridge_wall else None,
           "total_wall_s_incl_startup": r["wall_time_s"]}
    out["node_cpu_s"] = r.get("node_cpu_s")
    # free-run: ticks where the controller's command was late (the robot held its last targets)
    out["uncontrolled_ticks"] = r["metrics"].get("uncontrolled_ticks")
    out["ticks"] = r["metrics"].get("ticks")
    if "recording" in r:
        out["recorded_messages"] = r["recording"].get("message_count")
    if hops is not None:
        out["hops_ms"] = hops
    return out


def run_probe(proc) -> dict:
    import rclpy
    from humfall_interfaces.msg import CentroidalState
    from sensor_msgs.msg import JointState

    from humfall_ros.nodes.common import QOS_RELIABLE

    rclpy.init()
    node = rclpy.create_node("latency_probe")
    seen: dict[str, dict[int, float]] = {"js": {}, "cs": {}, "cmd": {}}

    def rec(kind):
        def cb(msg):
            k = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
            seen[kind].setdefault(k, time.perf_counter())
        return cb

    node.create_subscription(JointState, "joint_states", rec("js"), QOS_RELIABLE)
    node.create_subscription(CentroidalState, "centroidal_state", rec("cs"), QOS_RELIABLE)
    node.create_subscription(JointState, "joint_command/locomotion", rec("cmd"), QOS_RELIABLE)
    try:
        while proc.poll() is None:
            rclpy.spin_once(node, timeout_sec=0.05)
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    keys = sorted(set(seen["js"]) & set(seen["cs"]) & set(seen["cmd"]))
    est, ctl, sim = [], [], []
    for a, b in zip(keys, keys[1:]):
        if b not in seen["js"]:
            continue
        est.append(seen["cs"][a] - seen["js"][a])
        ctl.append(seen["cmd"][a] - seen["cs"][a])
        sim.append(seen["js"][b] - seen["cmd"][a])
    def stats(x):
        x = np.array(x) * 1e3
        return {"median": round(float(np.median(x)), 3), "p95": round(float(np.percentile(x, 95)), 3)} if len(x) \
            else None
    return {"ticks": len(est), "sim_to_estimator_out": stats(est), "estimator_to_controller_out": stats(ctl),
            "controller_to_next_sensors": stats(sim),
            "tick_total": stats(np.array(est) + np.array(ctl) + np.array(sim))}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--control-rate", type=float, default=500.0)
    ap.add_argument("--repeats", type=int, default=3, help="free-run repeats (the RTF varies with the machine's load)")
    ap.add_argument("--standins", type=int, default=0,
                    help="extra idle per-tick controller nodes (lockstep sources answering every tick with a release)")
    ap.add_argument("--compose", action="store_true", help="humfall up --compose")
    ap.add_argument("--scenario", default="standing_quiet", help="the scenario (walking: the walking suite)")
    a = ap.parse_args()
    global COMPOSE, SCENARIO
    COMPOSE, SCENARIO = a.compose, a.scenario
    env = dict(os.environ)
    env["ROS_DOMAIN_ID"] = str(60 + os.getpid() % 30)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    os.environ.update({k: env[k] for k in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE")})
    os.environ.setdefault("ROS_LOG_DIR", tempfile.mkdtemp())
    with tempfile.TemporaryDirectory() as tmp:
        runs = pathlib.Path(tmp) / "runs"
        load_before = os.getloadavg()[0]
        k = a.standins
        free = [up(a.seconds, a.control_rate, False, 0.0, runs, env, standins=k) for _ in range(a.repeats)]
        # a 1 s run measures each node's start-up CPU (imports, model, discovery), so the
        # per-node figure below is the CPU of running the sim, per simulated second
        short = up(1.0, a.control_rate, False, 0.0, runs, env, standins=k)
        rtfs = sorted(r["real_time_factor"] for r in free)
        per_sim_s = {n: round(float(np.median([(r["node_cpu_s"][n] - short["node_cpu_s"][n]) / (a.seconds - 1.0)
                                               for r in free])), 3) for n in short["node_cpu_s"]}
        res = {
            "benchmark": "suite",
            "scenario": a.scenario,
            "cpu_count": os.cpu_count(),
            "load_average_1min_before": round(load_before, 2),
            "control_rate_hz": a.control_rate,
            "free_run_max": {"real_time_factor_median": rtfs[len(rtfs) // 2], "real_time_factor_min": rtfs[0],
                             "real_time_factor_max": rtfs[-1],
                             "uncontrolled_ticks": [r["uncontrolled_ticks"] for r in free],
                             "ticks": free[0]["ticks"], "runs": free},
            "cpu_cores_per_sim_second": {**per_sim_s, "total": round(sum(per_sim_s.values()), 3)},
            "standin_controllers": k,
            "composed": a.compose,
            "free_run_target_1": up(a.seconds, a.control_rate, False, 1.0, runs, env, standins=k),
            "lockstep": up(a.seconds, a.control_rate, True, 1.0, runs, env, probe=True, standins=k),
        }
    print(json.dumps(res, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
