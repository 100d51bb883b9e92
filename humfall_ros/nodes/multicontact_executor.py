"""multicontact_executor: a stored multi-contact fall plan (paper 2) executed as a lockstep command source.

A ``ControllerNode`` (humfall_ros/nodes/controller_node.py) running
``humfall_ros.multicontact.executor.MulticontactExecutor`` as source ``multicontact`` (parameter
``source``; the scenario's ``controllers`` entry names the same source and its mux priority, above
the built-ins). It releases until ``start_time`` (default: the plan file's ``take_over_time``), then
tracks the plan's sagittal joints and holds the rest; it never releases after that.

**Where the plan comes from:** a plan file (``plan_file``, ``StoredPlan`` JSON), written by
``benchmarks/bench_multicontact_exec.py --save-plans DIR`` from the in-process run of the same scenario:
the push's end state measured in PyBullet, mapped to the planar state and planned there. The
simulation is deterministic and the lockstep graph gives the in-process joint states (tested), so the
state at ``start_time`` over ROS is the one the plan was made from. Or, with ``plan_live`` (session 43), planned
inside the take-over tick at ``start_time`` from that tick's sensors and the estimator (``multicontact.live``; the
planner's ``planner_profile``, "execution" by default: its library answers 10-50 J forward pushes); in lockstep
the bridge waits for the answer (``params.sim_bridge.stall_timeout`` above ``plan_time_budget``). The scenario
``multicontact_push_live`` does that.

Parameters: ``config/multicontact_executor.yaml``. Relative plan files are looked up from the working
directory, then in ``config/multicontact_plans/``.
"""
from __future__ import annotations

import dataclasses
import pathlib
import sys

from humfall_ros import paths
from humfall_ros.multicontact.executor import ExecutorConfig, MulticontactExecutor, StoredPlan
from humfall_ros.nodes.common import run_node
from humfall_ros.nodes.controller_node import IMU, ControllerNode

CONFIG = "multicontact_executor"


def plan_path(name: str) -> pathlib.Path:
    """The plan file ``name``: as given if it exists, else ``config/multicontact_plans/<name>[.json]``."""
    p = pathlib.Path(name)
    if p.is_file():
        return p
    shared = paths.config_path("multicontact_plans") / name
    for c in (shared, shared.with_suffix(".json")):
        if c.is_file():
            return c
    raise FileNotFoundError(f"no plan file {name!r} (nor in {shared.parent})")


class _NeverTakesOver:
    """A source that always releases (no plan file given)."""

    def __init__(self, source: str):
        self.source = source

    def reset(self) -> None:
        pass

    def step(self, observation):
        return None


def make_controller(p: dict, model):
    """The executor of ``p["plan_file"]``, or with ``p["plan_live"]`` of a plan made at the take-over from the
    sensors (``multicontact.live.SensedPlanSource``) (the node's declared parameters)."""
    if p["plan_live"] and p["plan_file"]:
        raise ValueError("give plan_file or plan_live, not both")
    if p["plan_live"] and p["start_time"] < 0:
        raise ValueError("plan_live needs start_time (the sim time to plan and take over at, e.g. the push's end)")
    if not p["plan_file"] and not p["plan_live"]:
        return _NeverTakesOver(p["source"])
    from humfall_ros.multicontact.model import load_model as load_planar

    segments, source = [], None
    if p["plan_live"]:
        from humfall_ros.multicontact.live import SensedPlanSource
        from humfall_ros.multicontact.planner import FallPlanner

        source = SensedPlanSource(FallPlanner.from_params(), model, profile=p["planner_profile"],
                                  time_budget=p["plan_time_budget"])
        start = p["start_time"]
    else:
        plan = StoredPlan.load(plan_path(p["plan_file"]))
        segments = plan.segments
        start = plan.take_over_time if p["start_time"] < 0 else p["start_time"]
    # every declared parameter named like an ExecutorConfig field is that field (a test checks the declaration
    # has them all); start_time < 0 means the plan file's
    fields = {f.name for f in dataclasses.fields(ExecutorConfig)}
    cfg = ExecutorConfig.from_params({**{k: v for k, v in p.items() if k in fields}, "start_time": start})
    ex = MulticontactExecutor(segments, load_planar().joint_names, model.joint_names, cfg, plan_source=source,
                              model=model)
    ex.source = p["source"]
    return ex


def source_from_argv(argv: list[str]) -> str:
    """The ``source:=`` of the command line (the node's name follows it), default from the declaration."""
    from humfall_ros import params

    return next((a.split(":=", 1)[1] for a in argv if a.startswith("source:=")),
                params.defaults(CONFIG)["source"])


def make_node(name: str | None = None):
    """The node, named ``name`` (default ``multicontact_executor_<source>``, as the launcher names the process of
    a scenario's controllers entry: ``<module stem>_<source>``; the composed runner passes that name, so a
    composed run's params-file section reaches it)."""
    # the IMU each tick: the base pitch feedback (ExecutorConfig.base_pitch_gain) estimates the base's pitch from it
    node = ControllerNode(name or f"{CONFIG}_{source_from_argv(sys.argv)}", make_controller, inputs=[IMU],
                          config_name=CONFIG)
    ex = node.controller
    if isinstance(ex, MulticontactExecutor) and ex.plan_source is not None:
        live = ex.plan_source

        def logged(observation):   # the plan made at the take-over, said in the log
            segs = live(observation)
            i = live.info
            node.get_logger().info(
                f"plan from the sensors at {observation.time:.3f} s: success={i.get('success')} "
                f"source={i.get('source', '')} {' -> '.join(i.get('contact_sequence') or [])} "
                f"planar KE {i.get('ke_planar_projected', float('nan')):.2f} J, {i.get('compute_s', 0.0):.2f} s: "
                f"{i.get('reason', '')}")
            return segs

        ex.plan_source = logged
        node.get_logger().info(f"plan: made at the take-over ({ex.cfg.start_time:.3f} s) from the sensors, "
                               f"planner_profile {live.profile!r}")
    elif isinstance(ex, MulticontactExecutor):
        node.get_logger().info(f"plan: {len(ex.segments)} segments "
                               f"({' -> '.join(s.target_mode and '/'.join(s.target_mode) for s in ex.segments)}), "
                               f"take-over at {ex.cfg.start_time:.3f} s")
    else:
        node.get_logger().warning("no plan_file: this source never takes over")
    return node


def main(args=None) -> int:
    argv = sys.argv if args is None else args
    return run_node(lambda: make_node(f"{CONFIG}_{source_from_argv(argv)}"), args)


if __name__ == "__main__":
    raise SystemExit(main())
