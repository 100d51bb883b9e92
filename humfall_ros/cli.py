"""The `humfall` command: what ros2 run / launch / service call give a full ROS install.

    humfall up --scenario NAME [--controller NAME] [--set dotted.key=value ...]
    humfall run NODE [--ros-args ...]
    humfall push FX FY FZ [--duration S] [--link L] [--point X Y Z]
    humfall plan-fall --ke 30 [--wall 0.8] [--json]
    humfall bag info FILE | humfall bag plot FILE [--out DIR] | humfall bag recover FILE [--out F]
    humfall campaign SPEC.yaml [...] | humfall campaign report RESULTS   (push campaigns, see campaign --help)
"""
from __future__ import annotations

import argparse
import math
import os
import sys

NODES = ("sim_bridge", "state_estimator", "locomotion", "recorder", "multicontact_planner", "estop_planner",
         "ftb_monitor", "safe_fall_controller")


def _cmd_up(a) -> int:
    from humfall_ros import launch, scenario

    try:
        status, _ = launch.up(a.scenario, a.controller, a.set, runs_dir=a.runs_dir, record=not a.no_record,
                              compose=a.compose,
                              plots=not a.no_plots)
    except (scenario.ScenarioError, launch.RunError) as e:
        print(f"humfall up: {e}", file=sys.stderr)
        return 2
    return status


def _cmd_run(a) -> int:
    import importlib

    if a.node not in NODES:
        print(f"humfall run: unknown node {a.node!r} (nodes: {', '.join(NODES)})", file=sys.stderr)
        return 2
    mod = importlib.import_module(f"humfall_ros.nodes.{a.node}")
    return mod.main([sys.argv[0], *a.ros_args]) or 0


def _cmd_push(a) -> int:
    vals = [a.fx, a.fy, a.fz, a.duration, *a.point]
    if not all(math.isfinite(v) for v in vals):
        print("humfall push: refused: non-finite value", file=sys.stderr)
        return 2
    import rclpy
    from humfall_interfaces.srv import Push

    os.environ.setdefault("ROS_LOG_DIR", os.path.join(os.path.expanduser("~"), ".ros", "log"))
    rclpy.init()
    try:
        node = rclpy.create_node("humfall_push")
        cli = node.create_client(Push, "sim/push")
        if not cli.wait_for_service(timeout_sec=a.timeout):
            print("humfall push: no sim/push service (is sim_bridge running in this ROS_DOMAIN_ID?)",
                  file=sys.stderr)
            return 1
        req = Push.Request(link=a.link, duration=a.duration)
        req.force.x, req.force.y, req.force.z = a.fx, a.fy, a.fz
        req.point.x, req.point.y, req.point.z = a.point
        fut = cli.call_async(req)
        rclpy.spin_until_future_complete(node, fut, timeout_sec=a.timeout)
        if not fut.done():
            print("humfall push: no answer", file=sys.stderr)
            return 1
        resp = fut.result()
        print(("ok: " if resp.success else "refused: ") + resp.message)
        return 0 if resp.success else 1
    finally:
        rclpy.try_shutdown()


def _cmd_plan_fall(a, rest: list[str]) -> int:
    from humfall_ros.nodes import plan_fall_client

    return plan_fall_client.main(rest)


def _cmd_bag(a) -> int:
    if not os.path.exists(a.file):
        print(f"humfall bag: no such file {a.file}", file=sys.stderr)
        return 2
    if a.action == "info":
        from humfall_ros.recording.summary import info_main

        return info_main(a.file)
    if a.action == "recover":
        from humfall_ros.recording import recover

        print(recover(a.file, a.out))
        return 0
    from humfall_ros.recording import plot_main

    return plot_main(a.file, a.out)


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="humfall", description="humfall_ros: humanoid fall handling on ROS 2 Jazzy")
    sub = p.add_subparsers(dest="command", required=True)
    up = sub.add_parser("up", help="start the whole suite, run a scenario, record it")
    up.add_argument("--scenario", default="standing_push", help="scenario name or YAML file")
    up.add_argument("--controller", default=None, help="fall controller (none, stepping, stepping_inertia)")
    up.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="override a scenario key, e.g. push.0.force=[250,0,0] or params.locomotion.ankle_kp=0.5")
    up.add_argument("--runs-dir", default="runs")
    up.add_argument("--no-record", action="store_true")
    up.add_argument("--no-plots", action="store_true")
    up.add_argument("--compose", action="store_true",
                    help="the estimator and all controllers in one process (each still its own node)")
    run = sub.add_parser("run", help="run one node in the foreground")
    run.add_argument("node")
    run.add_argument("ros_args", nargs=argparse.REMAINDER)
    push = sub.add_parser("push", help="push the simulated robot (sim/push)")
    push.add_argument("fx", type=float)
    push.add_argument("fy", type=float)
    push.add_argument("fz", type=float)
    push.add_argument("--duration", type=float, default=0.1)
    push.add_argument("--link", default="chest")
    push.add_argument("--point", type=float, nargs=3, default=[0.0, 0.0, 0.2])
    push.add_argument("--timeout", type=float, default=5.0)
    sub.add_parser("plan-fall", help="call the multi-contact planner (see plan-fall --help)", add_help=False)
    sub.add_parser("campaign", help="push campaigns over scenario keys, local or on Ray (see campaign --help)",
                   add_help=False)
    sub.add_parser("sweep", help="safe-fall sweep over push directions (see sweep --help)", add_help=False)
    sub.add_parser("estop", help="trigger (or --release) the emergency stop (topic estop)", add_help=False)
    bag = sub.add_parser("bag", help="inspect a recorded run")
    bag.add_argument("action", choices=["info", "plot", "recover"])
    bag.add_argument("file")
    bag.add_argument("--out", default=None, help="plot: output folder; recover: output file")
    return p


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] == "plan-fall":
        return _cmd_plan_fall(None, argv[1:])
    # subcommands with their own argument parsers: everything after the name is theirs
    delegated = {"campaign": "humfall_ros.campaign.cli", "sweep": "humfall_ros.sim.fall_sweep",
                 "estop": "humfall_ros.nodes.estop_cli"}
    if argv and argv[0] in delegated:
        import importlib

        try:
            mod = importlib.import_module(delegated[argv[0]])
        except ModuleNotFoundError as e:
            print(f"humfall {argv[0]}: not available in this build ({e})", file=sys.stderr)
            return 2
        return mod.main(argv[1:]) or 0
    a = parser().parse_args(argv)
    return {"up": _cmd_up, "run": _cmd_run, "push": _cmd_push, "bag": _cmd_bag}[a.command](a)


if __name__ == "__main__":
    raise SystemExit(main())
