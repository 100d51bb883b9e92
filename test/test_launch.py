"""`humfall up` as users drive it: Ctrl-C stops cleanly, a dying node fails the run loudly."""
import json
import os
import pathlib
import signal
import subprocess
import sys
import time


def children(pid: int) -> dict[int, str]:
    """Direct children of a process: pid -> command line (from /proc)."""
    out = {}
    for d in pathlib.Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            ppid = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
            if ppid == pid:
                out[int(d.name)] = (d / "cmdline").read_bytes().replace(b"\0", b" ").decode()
        except (OSError, IndexError, ValueError):
            continue
    return out


def start_up(env, runs, *extra):
    cmd = [sys.executable, "-m", "humfall_ros.cli", "up", "--scenario", "standing_quiet", "--runs-dir", str(runs),
           "--no-plots", *extra]
    return subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def wait_for_clock(runs: pathlib.Path, timeout: float = 60.0) -> None:
    """Until the recorder's stats show sim time moving (the run is under way)."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        for stats in runs.glob("*/recording_stats.json"):
            try:
                topics = json.loads(stats.read_text())["topics"]
            except (ValueError, KeyError):
                continue
            if any(t["topic"] == "/clock" and t["count"] > 50 for t in topics):
                return
        time.sleep(0.2)
    raise AssertionError("the run never started")


def test_ctrl_c_stops_every_node_and_keeps_the_bag(in_ros_domain, tmp_path):
    runs = tmp_path / "runs"
    up = start_up(in_ros_domain, runs)
    wait_for_clock(runs)
    kids = children(up.pid)
    assert len(kids) == 4  # recorder, estimator, locomotion, bridge
    up.send_signal(signal.SIGINT)
    out, _ = up.communicate(timeout=60)
    assert up.returncode == 130, out
    assert "interrupted" in out
    for pid in kids:
        assert not pathlib.Path(f"/proc/{pid}").exists() or \
            pathlib.Path(f"/proc/{pid}/stat").read_text().split()[2] == "Z"
    (run,) = runs.iterdir()
    result = json.loads((run / "result.json").read_text())
    stats = json.loads((run / "recording_stats.json").read_text())
    assert stats["finalized"] is True and result["bag"]
    from mcap_ros2.reader import read_ros2_messages

    n = sum(1 for _ in read_ros2_messages(result["bag"], topics=["/joint_states"]))
    assert n > 50


def test_a_node_that_dies_fails_the_run_with_its_log(in_ros_domain, tmp_path):
    runs = tmp_path / "runs"
    up = start_up(in_ros_domain, runs, "--set", "duration=60")
    wait_for_clock(runs)
    (loco,) = [pid for pid, cmd in children(up.pid).items() if "humfall_ros.nodes.locomotion" in cmd]
    os.kill(loco, signal.SIGKILL)
    out, _ = up.communicate(timeout=60)
    assert up.returncode == 1
    assert "node locomotion died" in out and "locomotion.log" in out


def test_sim_reset_mid_run_restarts_the_whole_lockstep_suite(in_ros_domain, tmp_path):
    import rclpy
    from rosgraph_msgs.msg import Clock
    from std_srvs.srv import Trigger

    runs = tmp_path / "runs"
    up = start_up(in_ros_domain, runs, "--set", "duration=2.0")
    rclpy.init()
    node = rclpy.create_node("reset_probe")
    try:
        now = {"t": 0.0}
        node.create_subscription(Clock, "/clock", lambda m: now.update(t=m.clock.sec + m.clock.nanosec * 1e-9), 10)
        reset = node.create_client(Trigger, "sim/reset")
        deadline = time.monotonic() + 60
        while now["t"] < 1.0 and time.monotonic() < deadline:
            rclpy.spin_once(node, timeout_sec=0.05)
        assert now["t"] >= 1.0, "the run never got to t=1 s"
        assert reset.wait_for_service(timeout_sec=10)
        fut = reset.call_async(Trigger.Request())
        rclpy.spin_until_future_complete(node, fut, timeout_sec=10)
        assert fut.done() and fut.result().success
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    out, _ = up.communicate(timeout=120)
    assert up.returncode == 0, out
    (run,) = runs.iterdir()
    r = json.loads((run / "result.json").read_text())
    # the estimator and the controller followed the restarted clock: no tick waited for them
    assert r["metrics"]["stalled_ticks"] == 0
    assert r["sim_duration_s"] == 2.0 and r["fell"] is False
    ticks = r["metrics"]["published"]["/joint_states"]
    assert ticks >= 1000 + 500  # ~1 s before the reset and the whole 2 s after it


def test_the_run_summary_names_a_bag_with_holes():
    """`humfall up` prints when its bag misses stamps of a periodic topic, and stays quiet when it does not."""
    from humfall_ros.launch import summary

    r = {"scenario": "standing_quiet", "controller": "none", "fell": False, "fall_direction_deg": None,
         "avoidance_angle_deg": None, "min_target_distance_m": None, "sim_duration_s": 2.0, "wall_time_s": 3.0,
         "bag": "runs/x/bag.mcap", "metrics": {}, "plots": [], "bag_missing_stamps": 0, "bag_holes": {}}
    assert "misses" not in summary(r)
    r.update(bag_missing_stamps=29, bag_holes={"/joint_states": 29})
    assert "the bag misses 29 stamps of periodic topics: {'/joint_states': 29}" in summary(r)
