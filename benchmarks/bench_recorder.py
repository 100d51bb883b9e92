"""Recorder throughput: joint_states-size messages at fixed rates, published vs recorded.

Starts the recorder as its own process (as `humfall up` does) in a private ROS
domain on localhost, publishes sensor_msgs/JointState (30 joints, all arrays
filled, ~1 KiB of CDR) from this process at each target rate for a few seconds,
each rate on its own topic, stops the recorder with SIGINT and counts what the
bag holds per topic. The publisher QoS is the suite's QOS_RELIABLE (reliable,
keep-last 20) by default: with a shallow writer history the middleware drops the
oldest unacknowledged samples when the recorder falls behind, so loss here is
real loss. Prints one JSON object.

    python benchmarks/bench_recorder.py [--rates 500,1000,2000,4000] [--seconds 3] [--depth 20]
"""
from __future__ import annotations

import argparse
import json
import os
import pathlib
import signal
import subprocess
import sys
import tempfile
import time

REPO = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def cpu_seconds(pid: int) -> float:
    """utime + stime of a process (Linux /proc), for CPU cost per message."""
    fields = pathlib.Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rates", default="500,1000,2000,4000")
    ap.add_argument("--seconds", type=float, default=3.0)
    ap.add_argument("--depth", type=int, default=20, help="publisher history depth")
    ap.add_argument("--joints", type=int, default=30)
    args = ap.parse_args()
    rates = [int(r) for r in args.rates.split(",")]

    domain = str(60 + os.getpid() % 30)
    env = dict(os.environ, ROS_DOMAIN_ID=domain, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               RMW_IMPLEMENTATION="rmw_fastrtps_cpp",
               PYTHONPATH=f"{REPO}{os.pathsep}{os.environ.get('PYTHONPATH', '')}")
    env.setdefault("ROS_LOG_DIR", tempfile.mkdtemp(prefix="bench_roslog_"))
    os.environ.update({k: env[k] for k in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE",
                                           "RMW_IMPLEMENTATION", "ROS_LOG_DIR")})

    import rclpy
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import JointState

    from humfall_ros.recording import bag_info

    out = pathlib.Path(tempfile.mkdtemp(prefix="bench_recorder_")) / "run"
    log = open(out.parent / "recorder.log", "wb")  # noqa: SIM115
    rec = subprocess.Popen([sys.executable, "-m", "humfall_ros.nodes.recorder", "--ros-args",
                            "-p", f"output_dir:={out}", "-p", "clock:=wall"],
                           env=env, stdout=log, stderr=subprocess.STDOUT)
    rclpy.init()
    node = rclpy.create_node("bench_recorder_pub")
    qos = QoSProfile(depth=args.depth, history=HistoryPolicy.KEEP_LAST,
                     reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)
    names = [f"joint_{i}" for i in range(args.joints)]
    results = []
    try:
        for rate in rates:
            topic = f"/bench/joint_states_{rate}hz"
            pub = node.create_publisher(JointState, topic, qos)
            end = time.monotonic() + 30
            while pub.get_subscription_count() < 1:   # wait until the recorder has subscribed
                if time.monotonic() > end or rec.poll() is not None:
                    raise RuntimeError("recorder did not subscribe")
                time.sleep(0.02)
            msg = JointState(name=names, position=[0.1] * args.joints, velocity=[0.2] * args.joints,
                             effort=[0.3] * args.joints)
            size = len(serialize_message(msg))
            n = int(rate * args.seconds)
            cpu0 = cpu_seconds(rec.pid)
            t0 = time.monotonic()
            for i in range(n):
                target = t0 + i / rate
                delay = target - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                msg.header.stamp.sec, msg.header.stamp.nanosec = i // 1000, (i % 1000) * 1000
                pub.publish(msg)
            wall = time.monotonic() - t0
            time.sleep(1.0)   # drain
            results.append({"topic": topic, "target_hz": rate, "published": n,
                            "achieved_publish_hz": round(n / wall, 1), "msg_bytes": size,
                            "recorder_cpu_s_per_1k_msgs": round(1000 * (cpu_seconds(rec.pid) - cpu0) / n, 4)})
    finally:
        node.destroy_node()
        rclpy.shutdown()
        if rec.poll() is None:
            rec.send_signal(signal.SIGINT)
            try:
                rec.wait(timeout=30)
            except subprocess.TimeoutExpired:
                rec.kill()
                raise
    info = bag_info(out)
    counts = {t["topic"]: t["count"] for t in info["topics"]}
    for r in results:
        r["recorded"] = counts.get(r["topic"], 0)
        r["lost"] = r["published"] - r["recorded"]
    lossless = [r["achieved_publish_hz"] for r in results if r["lost"] == 0]
    print(json.dumps({
        "benchmark": "recorder_throughput",
        "publisher_depth": args.depth,
        "seconds_per_rate": args.seconds,
        "cpus": os.cpu_count(),
        "max_lossless_hz": max(lossless) if lossless else 0,
        "bag_bytes": info["size_bytes"],
        "bag_finalized": info["finalized"],
        "results": results,
    }, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
