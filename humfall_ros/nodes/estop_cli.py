"""``humfall estop [--release]``: trigger (or release) the e-stop of a running suite.

Publishes one ``std_msgs/msg/Empty`` on ``/estop`` (``--release``: on ``/estop/release``), reliable and
transient-local, as ``ros2 topic pub --once --qos-durability transient_local /estop std_msgs/msg/Empty`` would:
it waits up to ``--timeout`` seconds for the ``estop_planner`` node to subscribe (not just any subscriber: the
recorder subscribes to every topic), publishes, waits until every subscriber has acknowledged the message, and
says what happened. Exit status 0: delivered;
1: no subscriber within the timeout (nothing published) or not acknowledged; 2: bad arguments.

Run it in the suite's ROS domain (``humfall up`` prints its ``ROS_DOMAIN_ID``). The node's answer is on
``/estop/status`` (``state``, ``feasible``, ``reason``); a release is granted only once the robot holds
still at its final posture (otherwise refused and logged by the node; send it again).
"""
from __future__ import annotations

import argparse
import os
import sys
import time

TRIGGER_TOPIC = "/estop"
RELEASE_TOPIC = "/estop/release"


def parse(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="humfall estop", description="trigger or release the e-stop of a running suite")
    ap.add_argument("--release", action="store_true", help="clear a latched stop once the robot is home")
    ap.add_argument("--timeout", type=float, default=5.0, help="seconds to wait for the node (default 5)")
    ap.add_argument("--node", default="estop_planner", help="the subscriber to wait for (default estop_planner)")
    a = ap.parse_args(argv)
    if not a.timeout > 0:
        ap.error("--timeout must be > 0")
    return a


def main(argv: list[str] | None = None) -> int:
    try:
        args = parse(sys.argv[1:] if argv is None else argv)
    except SystemExit as e:
        return int(e.code or 0)
    # the same middleware and discovery range as the suite's nodes (humfall_ros.launch.child_env)
    os.environ.setdefault("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    import rclpy
    from rclpy.duration import Duration
    from std_msgs.msg import Empty

    from humfall_ros.nodes.common import QOS_LATCHED

    topic = RELEASE_TOPIC if args.release else TRIGGER_TOPIC
    what = "release" if args.release else "e-stop trigger"
    rclpy.init(args=[])
    node = rclpy.create_node(f"humfall_estop_cli_{os.getpid()}")
    try:
        pub = node.create_publisher(Empty, topic, QOS_LATCHED)
        deadline = time.monotonic() + args.timeout

        def planner_listens() -> bool:  # the recorder subscribes to every topic: wait for the e-stop node itself
            return any(i.node_name == args.node for i in node.get_subscriptions_info_by_topic(topic))

        while not planner_listens() and time.monotonic() < deadline:
            time.sleep(0.02)
        if not planner_listens():
            print(f"no subscriber on {topic} from {args.node} within {args.timeout:g} s (is the suite running with "
                  f"an {args.node}, ROS_DOMAIN_ID={os.environ.get('ROS_DOMAIN_ID', '0')}?): nothing published",
                  file=sys.stderr)
            return 1
        n = pub.get_subscription_count()
        pub.publish(Empty())
        left = max(deadline - time.monotonic(), 1.0)
        acked = pub.wait_for_all_acked(Duration(seconds=left))
        if not acked:
            print(f"{what} published on {topic} but not acknowledged by its {n} subscriber(s) within {left:.1f} s",
                  file=sys.stderr)
            return 1
        print(f"{what} delivered on {topic} to {n} subscriber(s)")
        return 0
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    raise SystemExit(main())
