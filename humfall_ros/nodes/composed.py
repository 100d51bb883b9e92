"""Several per-tick nodes in one process and executor (``humfall up --compose``).

    python -m humfall_ros.nodes.composed NAME=MODULE [NAME=MODULE ...] --ros-args --params-file FILE

Each MODULE (``humfall_ros.nodes.<x>`` or a ``.py`` file) has ``make_node(name)``, or
defines one rclpy Node subclass constructed without arguments (its own name); each
node keeps its own name, parameters (the params file's ``<name>:
ros__parameters`` section) and topics. What they share is the process: one wait
set over their per-tick subscriptions, each per-tick topic taken once and handed
to every node that reads it (humfall_ros.nodes.common.Composition). Stops on
SIGINT/SIGTERM like every node.
"""
from __future__ import annotations

import importlib
import importlib.util
import os
import pathlib
import sys

import rclpy
import rclpy.executors
from rclpy.parameter import Parameter

from humfall_ros.nodes.common import Composition, _exit_past_worker_threads, close_node, shutting_down


def load_module(module: str):
    if module.endswith(".py"):
        path = pathlib.Path(module).resolve()
        spec = importlib.util.spec_from_file_location(path.stem, path)
        mod = importlib.util.module_from_spec(spec)
        sys.modules[path.stem] = mod
        spec.loader.exec_module(mod)
        return mod
    return importlib.import_module(module)


def make_node(mod, name: str):
    if hasattr(mod, "make_node"):
        return mod.make_node(name)
    from rclpy.node import Node

    classes = [c for c in vars(mod).values()
               if isinstance(c, type) and issubclass(c, Node) and c.__module__ == mod.__name__]
    if len(classes) != 1:
        raise RuntimeError(f"{mod.__name__}: no make_node() and {len(classes)} node classes")
    node = classes[0]()
    if node.get_name() != name:
        raise RuntimeError(f"{mod.__name__} makes node {node.get_name()!r}, not {name!r}")
    return node


def main(args=None) -> int:
    argv = list(sys.argv if args is None else args)
    try:
        cut = argv.index("--ros-args")
    except ValueError:
        cut = len(argv)
    specs = [a.split("=", 1) for a in argv[1:cut]]
    if not specs or any(len(s) != 2 for s in specs):
        print("usage: composed NAME=MODULE [NAME=MODULE ...] --ros-args --params-file FILE", file=sys.stderr)
        return 2
    os.environ.setdefault("ROS_LOG_DIR", os.path.join(os.path.expanduser("~"), ".ros", "log"))
    rclpy.init(args=[argv[0], *argv[cut:]])
    nodes = []
    comp = Composition.current = Composition()
    try:
        for name, module in specs:
            node = make_node(load_module(module), name)
            if not node.has_parameter("use_sim_time"):
                node.declare_parameter("use_sim_time", True)
            node.set_parameters([Parameter("use_sim_time", Parameter.Type.BOOL, True)])
            nodes.append(node)
        executor = rclpy.executors.SingleThreadedExecutor()
        for node in nodes:
            executor.add_node(node)
        nodes[0].get_logger().info(f"composed {', '.join(n.get_name() for n in nodes)}: "
                                   f"{len(comp.subs)} shared per-tick subscriptions")
        comp.spin(executor)
    except (KeyboardInterrupt, rclpy.executors.ExternalShutdownException):
        pass
    except Exception:  # noqa: BLE001
        if not shutting_down():
            raise
    finally:
        for node in nodes:
            close_node(node)
        Composition.current = None
        rclpy.try_shutdown()
    return _exit_past_worker_threads(0)


if __name__ == "__main__":
    raise SystemExit(main())
