"""The whole suite as real processes: `humfall up`, lockstep determinism, bad input over ROS.

Each test runs in its own ROS_DOMAIN_ID on localhost (conftest.in_ros_domain).
"""
import json
import math
import pathlib
import subprocess
import sys
import time

import pytest

from humfall_ros import launch
from humfall_ros.nodes.common import stamp_key

from conftest import python_node_cmd


def joint_states_from_bag(bag):
    from mcap_ros2.reader import read_ros2_messages

    rows = []
    for m in read_ros2_messages(str(bag), topics=["/joint_states"]):
        rows.append((m.ros_msg.header.stamp.sec, m.ros_msg.header.stamp.nanosec, tuple(m.ros_msg.position)))
    return sorted(set(rows))


@pytest.fixture
def run_up(in_ros_domain, tmp_path):
    def run(scenario, *overrides, controller=None):
        status, result = launch.up(scenario, controller, list(overrides), runs_dir=str(tmp_path / "runs"),
                                   quiet=True)
        return status, result
    return run


def test_up_standing_push_falls_onto_the_target_and_records_everything(run_up):
    status, r = run_up("standing_push", "duration=2.5")
    assert status == 0
    for key in ("scenario", "controller", "fell", "fall_direction_deg", "avoidance_angle_deg",
                "min_target_distance_m", "sim_duration_s", "wall_time_s", "bag"):
        assert key in r
    assert r["fell"] is True
    assert r["min_target_distance_m"] == 0.0
    assert abs(r["fall_direction_deg"]) < 20 and r["avoidance_angle_deg"] < 20
    assert r["sim_duration_s"] == pytest.approx(2.5)
    assert r["metrics"]["uncontrolled_ticks"] == 0  # lockstep: the controller answered every tick
    assert set(r["node_exit_codes"].values()) == {0} and r["bag_finalized"] is True
    assert r["plots"] and all(p.endswith(".png") for p in r["plots"])
    assert any(p.endswith("fall_geometry.png") for p in r["plots"])  # from the recorded sim/result
    # no loss: what the bridge published is what the recorder wrote, per topic
    recorded = {t["topic"]: t["count"] for t in r["recording"]["topics"]}
    published = r["metrics"]["published"]
    assert published["/joint_states"] >= int(2.5 * 500) + 1  # ticks 0..N (+ start-up retransmits)
    # the robot for RViz/Foxglove: URDF once, fixed joints once, moving joints at 50 Hz
    assert recorded["/robot_description"] == 1 and recorded["/tf_static"] == 1
    assert recorded["/tf"] >= int(2.5 * 50)
    # ground truth at its own (lower) rate by default: every 5th tick at 100 Hz
    assert int(2.5 * 100) <= published["/ground_truth/odom"] <= published["/joint_states"] // 4
    for topic, n in published.items():
        assert recorded.get(topic) == n, topic
    # the estimator answered every tick (0 .. N-1) the controller needed
    assert recorded["/centroidal_state"] >= int(2.5 * 500)
    # the bag opens in an independent reader (rosbags) with our custom type
    from rosbags.highlevel import AnyReader

    with AnyReader([pathlib.Path(r["bag"])]) as reader:
        conns = [c for c in reader.connections if c.topic == "/centroidal_state"]
        assert conns and conns[0].msgtype == "humfall_interfaces/msg/CentroidalState"
        n = 0
        for conn, _, raw in reader.messages(connections=conns):
            msg = reader.deserialize(raw, conn.msgtype)
            assert math.isfinite(msg.com.z)
            if msg.left_contact or msg.right_contact:
                # leg odometry is defined while a foot carries load; with both feet off the ground
                # (thrown up by the fall) it extrapolates ballistically (measured z = 1.0 m lying)
                assert 0.0 < msg.com.z < 1.0
            n += 1
        assert n == recorded["/centroidal_state"]
    # and the humfall bag tools read it
    cli = [sys.executable, "-m", "humfall_ros.cli", "bag"]
    info = subprocess.run(cli + ["info", r["bag"]], capture_output=True, text=True, timeout=120)
    assert info.returncode == 0 and "/centroidal_state" in info.stdout and "CentroidalState" in info.stdout
    # no holes in the per-tick topics (stamps every 2 ms from the first tick to the last)
    from humfall_ros.recording import bag_info
    holes = {t["topic"]: (t["missing_stamps"], t["stamp_period_s"]) for t in bag_info(r["bag"])["topics"]}
    for topic in ("/clock", "/joint_states", "/imu", "/mux/state", "/centroidal_state", "/joint_command/locomotion"):
        assert holes[topic][0] == 0 and holes[topic][1] == pytest.approx(0.002), (topic, holes[topic])
    assert "holes:     none on" in info.stdout
    assert r["bag_missing_stamps"] == 0 and r["bag_holes"] == {}   # the run's result says the same
    out = pathlib.Path(r["bag"]).parent / "replot"
    plot = subprocess.run(cli + ["plot", r["bag"], "--out", str(out)], capture_output=True, text=True, timeout=120)
    assert plot.returncode == 0 and sorted(p.name for p in out.glob("*.png"))


def test_cli_refuses_what_it_cannot_do(in_ros_domain, tmp_path):
    cli = [sys.executable, "-m", "humfall_ros.cli"]
    p = subprocess.run(cli + ["run", "warp_core"], env=in_ros_domain, capture_output=True, text=True, timeout=60)
    assert p.returncode == 2 and "unknown node" in p.stderr
    p = subprocess.run(cli + ["push", "nan", "0", "0"], env=in_ros_domain, capture_output=True, text=True, timeout=60)
    assert p.returncode == 2 and "non-finite" in p.stderr
    p = subprocess.run(cli + ["push", "10", "0", "0", "--timeout", "1"], env=in_ros_domain, capture_output=True,
                       text=True, timeout=60)
    assert p.returncode == 1 and "no sim/push service" in p.stderr
    p = subprocess.run(cli + ["bag", "info", str(tmp_path / "none.mcap")], env=in_ros_domain, capture_output=True,
                       text=True, timeout=60)
    assert p.returncode == 2 and "no such file" in p.stderr


def test_two_lockstep_runs_give_identical_joint_states(run_up):
    s1, r1 = run_up("standing_push", "duration=1.0")
    s2, r2 = run_up("standing_push", "duration=1.0")
    assert s1 == s2 == 0
    a, b = joint_states_from_bag(r1["bag"]), joint_states_from_bag(r2["bag"])
    assert len(a) == 501  # distinct (stamp, positions) rows: ticks 0..500
    assert a == b


def test_scenario_errors_are_refused_before_anything_starts(in_ros_domain, tmp_path):
    env = dict(in_ros_domain)
    bad = tmp_path / "bad.yaml"
    bad.write_text("duration: 1\nobstacles:\n  - name: a\n    sise: [1, 1, 1]\n")
    cmd = [sys.executable, "-m", "humfall_ros.cli", "up", "--runs-dir", str(tmp_path / "runs")]
    p = subprocess.run(cmd + ["--scenario", str(bad)], env=env, capture_output=True, text=True, timeout=60)
    assert p.returncode == 2 and "unknown key obstacles.0.sise" in p.stderr
    p = subprocess.run(cmd + ["--scenario", "small_push", "--set", "push.0.strength=3"], env=env,
                       capture_output=True, text=True, timeout=60)
    assert p.returncode == 2 and "no such key push.0.strength" in p.stderr
    for override, why in (("params.nobody.x=1", "not in this run"),
                          ("params.locomotion.ankle_kpp=0.5", "locomotion has no parameter 'ankle_kpp'"),
                          ("params.locomotion.ankle_kp=abc", "expected double (a number) like 0.3"),
                          ("params.sim_bridge.end_time=0", "set by the launcher")):
        p = subprocess.run(cmd + ["--scenario", "small_push", "--set", override], env=env,
                           capture_output=True, text=True, timeout=60)
        assert p.returncode == 2 and why in p.stderr, (override, p.stderr)
    assert not (tmp_path / "runs").exists()  # refused before any run folder or process


def test_bridge_refuses_bad_pushes_and_commands_and_keeps_running(in_ros_domain, tmp_path):
    import rclpy
    from humfall_interfaces.srv import Push
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import JointState

    bridge = subprocess.Popen(python_node_cmd("humfall_ros.nodes.sim_bridge", "--ros-args", "-p", "lockstep:=false",
                                              "-p", "scenario:=standing_quiet"),
                              env=in_ros_domain, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    rclpy.init()
    node = rclpy.create_node("bad_input_probe")
    try:
        cli = node.create_client(Push, "sim/push")
        assert cli.wait_for_service(timeout_sec=30.0)

        def push(fx, fy=0.0, fz=0.0, duration=0.1, link=""):
            req = Push.Request(duration=duration, link=link)
            req.force.x, req.force.y, req.force.z = fx, fy, fz
            fut = cli.call_async(req)
            rclpy.spin_until_future_complete(node, fut, timeout_sec=10.0)
            assert fut.done()
            return fut.result()

        for args, why in (((float("nan"),), "non-finite"), ((0.0, float("inf")), "non-finite"),
                          ((6000.0,), "exceeds"), ((10.0, 0.0, 0.0, -1.0), "duration"),
                          ((10.0, 0.0, 0.0, 0.1, "tail"), "unknown link")):
            resp = push(*args)
            assert not resp.success and why in resp.message
        pub = node.create_publisher(JointState, "joint_command/locomotion",
                                    QoSProfile(depth=20, reliability=ReliabilityPolicy.RELIABLE))
        deadline = time.monotonic() + 10
        while pub.get_subscription_count() == 0 and time.monotonic() < deadline:
            rclpy.spin_once(node, timeout_sec=0.05)
        for bad in (JointState(name=["l_knee", "warp_drive"], position=[0.1, 0.2]),
                    JointState(name=["l_knee"], position=[0.1, 0.2]),
                    JointState(name=["l_knee"], position=[float("nan")])):
            pub.publish(bad)
            end = time.monotonic() + 1.1  # the bridge throttles its warning to one a second
            while time.monotonic() < end:
                rclpy.spin_once(node, timeout_sec=0.05)
        assert bridge.poll() is None, "the bridge died on bad input"
        assert push(50.0).success  # still serving
        from std_srvs.srv import Trigger

        reset = node.create_client(Trigger, "sim/reset")
        assert reset.wait_for_service(timeout_sec=10.0)
        from rosgraph_msgs.msg import Clock

        clock = []
        node.create_subscription(Clock, "/clock", lambda m: clock.append(m.clock.sec + m.clock.nanosec * 1e-9), 10)
        end = time.monotonic() + 1.0
        while time.monotonic() < end:
            rclpy.spin_once(node, timeout_sec=0.05)
        before = clock[-1]
        fut = reset.call_async(Trigger.Request())
        rclpy.spin_until_future_complete(node, fut, timeout_sec=10.0)
        assert fut.done() and fut.result().success
        clock.clear()
        end = time.monotonic() + 10.0
        while not clock and time.monotonic() < end:
            rclpy.spin_once(node, timeout_sec=0.05)
        assert clock, "no /clock after the reset"
        assert before > 1.0 and clock[0] < before  # time restarted from zero
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
        bridge.terminate()
        out, _ = bridge.communicate(timeout=20)
    assert "unknown joints" in out and "1 names but 2 positions" in out and "non-finite" in out


def test_estimator_can_run_on_ground_truth_for_comparison(run_up):
    # viz_rate=25 is an integer for a double parameter: the launcher must type it, not kill the node
    status, r = run_up("standing_quiet", "duration=1.0", "params.state_estimator.use_ground_truth=true",
                       "params.state_estimator.viz_rate=25")
    assert status == 0 and r["fell"] is False
    from mcap_ros2.reader import read_ros2_messages

    coms = [m.ros_msg.com for m in read_ros2_messages(r["bag"], topics=["/centroidal_state"])]
    assert len(coms) >= 500  # it answered every tick, with ground_truth/odom in its sync set
    odom = [m.ros_msg.pose.pose.position for m in read_ros2_messages(r["bag"], topics=["/ground_truth/odom"])]
    assert abs(odom[-1].z - 0.73) < 0.02 and all(0.7 < c.z < 0.8 for c in coms)
    assert len(odom) >= 500  # the launcher raised ground_truth_rate to the control rate for it


def test_bridge_mux_switches_by_priority_and_reports_it(in_ros_domain):
    import rclpy
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from rosgraph_msgs.msg import Clock
    from sensor_msgs.msg import JointState
    from humfall_interfaces.msg import MuxState
    from std_msgs.msg import String

    from humfall_ros.model.humanoid import load_model

    bridge = subprocess.Popen(python_node_cmd("humfall_ros.nodes.sim_bridge", "--ros-args", "-p", "lockstep:=false",
                                              "-p", "scenario:=standing_quiet", "-p", "command_timeout:=0.5"),
                              env=in_ros_domain, stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT)
    rclpy.init()
    node = rclpy.create_node("mux_probe")
    try:
        now = {"t": None}
        active = []
        node.create_subscription(Clock, "/clock", lambda m: now.update(t=m.clock), 10)
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        node.create_subscription(String, "active_controller", lambda m: active.append(m.data), latched)
        holding = []
        node.create_subscription(MuxState, "mux/state", lambda m: holding.append(m.holding), 50)
        reliable = QoSProfile(depth=20, reliability=ReliabilityPolicy.RELIABLE)
        pubs = {s: node.create_publisher(JointState, f"joint_command/{s}", reliable) for s in ("estop", "locomotion")}
        joints = load_model().joint_names

        def run_until(done, sources, release=(), at_least=0.3, at_most=15.0):
            """Command as given until done() holds (after at_least s); False if at_most s pass first."""
            start = time.monotonic()
            while time.monotonic() - start < at_most:
                rclpy.spin_once(node, timeout_sec=0.005)
                if now["t"] is None:
                    continue
                for s in sources:
                    cmd = JointState(name=joints, position=[0.0] * len(joints))
                    cmd.header.stamp = now["t"]
                    pubs[s].publish(cmd)
                for s in release:
                    cmd = JointState()
                    cmd.header.stamp = now["t"]
                    pubs[s].publish(cmd)
                if time.monotonic() - start > at_least and done():
                    return True
            return False

        deadline = time.monotonic() + 30
        while now["t"] is None and time.monotonic() < deadline:
            rclpy.spin_once(node, timeout_sec=0.05)
        assert run_until(lambda: active and active[-1] == "locomotion", ["locomotion"])
        assert run_until(lambda: active[-1] == "estop", ["locomotion", "estop"])
        assert run_until(lambda: active[-1] == "locomotion", ["locomotion"], release=["estop"])
        # locomotion goes silent: it is engaged, so the bridge holds its last targets (never "none")
        assert run_until(lambda: holding and holding[-1], [], at_least=1.0)
        assert active[-1] == "locomotion"
        # only an explicit release disengages
        assert run_until(lambda: active[-1] == "none", [], release=["locomotion"])
        assert bridge.poll() is None
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
        bridge.terminate()
        bridge.wait(timeout=20)


def test_free_run_closes_the_loop_from_the_first_tick(run_up):
    status, r = run_up("standing_quiet", "duration=1.0", "sim.lockstep=false", "sim.real_time_factor=1.0")
    assert status == 0 and r["fell"] is False and r["metrics"]["ticks"] == 500
    from mcap_ros2.reader import read_ros2_messages

    stamps = [stamp_key(m.ros_msg.header.stamp) for m in read_ros2_messages(r["bag"],
                                                                           topics=["/joint_command/locomotion"])]
    assert stamps and min(stamps) == 0  # time started only once the controller had answered tick 0


def test_free_run_bridge_alone_starts_without_its_controllers(ros_env, tmp_path):
    metrics = tmp_path / "metrics.json"
    bridge = subprocess.run(python_node_cmd("humfall_ros.nodes.sim_bridge", "--ros-args", "-p", "lockstep:=false",
                                            "-p", "start_timeout:=0.5", "-p", "end_time:=0.2",
                                            "-p", f"metrics_file:={metrics}"),
                            env=ros_env, capture_output=True, text=True, timeout=120)
    assert bridge.returncode == 0, bridge.stderr[-2000:]
    assert "starting without it" in bridge.stderr
    r = json.loads(metrics.read_text())
    assert r["sim_duration_s"] == pytest.approx(0.2) and r["uncontrolled_ticks"] == r["ticks"] == 100


def test_sensor_noise_reaches_the_graph_and_the_robot_still_stands(run_up):
    status, r = run_up("standing_quiet", "duration=0.5", "params.sim_bridge.noise_joint_position=0.002",
                       "params.sim_bridge.noise_seed=3")
    assert status == 0 and r["fell"] is False
    import numpy as np
    from mcap_ros2.reader import read_ros2_messages

    q = np.array([m.ros_msg.position for m in read_ros2_messages(r["bag"], topics=["/joint_states"])])
    # tick-to-tick jitter of a standing robot: ~1e-5 rad exact, ~sqrt(2) * 2e-3 with the noise
    assert 0.002 < np.std(np.diff(q, axis=0)) < 0.005
