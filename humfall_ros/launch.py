"""`humfall up`: start the suite as separate processes, run a scenario, collect the results.

What ``ros2 launch`` would do on a full ROS install, for pip-only machines:
one process per node, each with its log file in the run folder, clean stop
(SIGINT, then SIGTERM, then SIGKILL) on the end of the run, on Ctrl-C or when a
node dies (then the log tail is shown and the exit status is non-zero).
No rclpy here: results come from the bridge's metrics file and the bag.
"""
from __future__ import annotations

import dataclasses
import datetime as dt
import json
import os
import pathlib
import signal
import subprocess
import sys
import time

import yaml

from humfall_ros import params as params_mod
from humfall_ros import scenario as scenario_mod
from humfall_ros.scenario import CONTROLLER_NODES, CONTROLLER_PARAMS
from humfall_ros.control.mux import DEFAULT_PRIORITIES, mux_order

# The mux source each built-in controller node commands (joint_command/<source>), in lockstep.
NODE_SOURCE = {"locomotion": "locomotion", "safe_fall_controller": "safe_fall", "estop_planner": "estop"}
# Bridge parameters that come from the scenario file itself (its sim section and duration).
SCENARIO_OWNED = {"physics_rate", "control_rate", "lockstep", "real_time_factor", "friction", "end_time"}


@dataclasses.dataclass
class NodeSpec:
    """One process of a run: its name, how to start it, its parameters and the mux source it answers."""

    name: str
    module: str                  # python module (run with -m) or a .py file
    params: dict
    source: str | None = None
    priority: int | None = None
    argv: list[str] = dataclasses.field(default_factory=list)  # before --ros-args
    params_file: str | None = None


class RunError(RuntimeError):
    pass


def ros_value(v) -> str:
    """A parameter value as `-p name:=value` wants it (YAML)."""
    if isinstance(v, str):
        return v if v else "''"
    return yaml.safe_dump(v, default_flow_style=True).strip().removesuffix("...").strip()


class Proc:
    def __init__(self, name: str, cmd: list[str], env: dict, log_dir: pathlib.Path):
        self.name = name
        self.log_path = log_dir / f"{name}.log"
        self.log = open(self.log_path, "wb")
        self.p = subprocess.Popen(cmd, env=env, stdout=self.log, stderr=subprocess.STDOUT,
                                  start_new_session=True)  # our Ctrl-C is handled here, not by the node

    def alive(self) -> bool:
        return self.p.poll() is None

    def cpu_seconds(self) -> float | None:
        """CPU time (user + system) the node has used so far (Linux /proc), None if gone."""
        try:
            fields = pathlib.Path(f"/proc/{self.p.pid}/stat").read_text().rsplit(")", 1)[1].split()
            return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
        except (OSError, IndexError, ValueError):
            return None

    def stop(self, timeout: float = 10.0) -> int:
        for sig, wait in ((signal.SIGINT, timeout), (signal.SIGTERM, 3.0), (signal.SIGKILL, 3.0)):
            if not self.alive():
                break
            try:
                self.p.send_signal(sig)
                self.p.wait(wait)
            except subprocess.TimeoutExpired:
                continue
        self.log.close()
        return self.p.returncode

    def tail(self, n: int = 25) -> str:
        try:
            lines = self.log_path.read_text(errors="replace").splitlines()
        except OSError:
            return ""
        return "\n".join(lines[-n:])


def make_run_dir(runs_dir: pathlib.Path, name: str) -> pathlib.Path:
    stamp = dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    d = runs_dir / f"{stamp}-{name}"
    i = 1
    while d.exists():
        i += 1
        d = runs_dir / f"{stamp}-{name}-{i}"
    d.mkdir(parents=True)
    return d


def node_command(node: str | NodeSpec, params: dict | None = None) -> list[str]:
    spec = node if isinstance(node, NodeSpec) else NodeSpec(node, f"humfall_ros.nodes.{node}", params or {})
    mod = spec.module
    cmd = [sys.executable, mod] if mod.endswith(".py") else [sys.executable, "-m", mod]
    cmd += list(spec.argv)
    cmd.append("--ros-args")
    if spec.params_file:
        cmd += ["--params-file", spec.params_file]
    for k, v in spec.params.items():
        cmd += ["-p", f"{k}:={ros_value(v)}"]
    return cmd


def plan_nodes(sc: dict, run_dir: pathlib.Path, record: bool) -> list[NodeSpec]:
    """The run's processes in start order; the bridge last so the others are listening.

    The command sources are registered from the controller nodes started (the built-in
    ones and the scenario's ``controllers``), ordered by priority for the bridge's mux;
    every one of them answers in lockstep.
    """
    controller = sc["controller"]
    if controller not in CONTROLLER_NODES:
        raise RunError(f"controller {controller!r} is not available yet (available: {', '.join(CONTROLLER_NODES)})")
    extra = sc["params"]
    nodes: list[NodeSpec] = []
    if record:
        nodes.append(NodeSpec("recorder", "humfall_ros.nodes.recorder",
                              {"output_dir": str(run_dir), "scenario": sc["name"]}))
    nodes.append(NodeSpec("state_estimator", "humfall_ros.nodes.state_estimator", {}))
    builtin = getattr(scenario_mod, "BUILTIN_PRIORITIES", DEFAULT_PRIORITIES)
    for n in ["locomotion", *CONTROLLER_NODES[controller]]:
        src = NODE_SOURCE.get(n)
        own = dict(CONTROLLER_PARAMS.get(controller, {}).get(n, {}))
        if "scenario" in params_mod.declarations(n):  # it reads its part of the scenario (e.g. the walk)
            own["scenario"] = str(run_dir / "scenario.yaml")
        nodes.append(NodeSpec(n, f"humfall_ros.nodes.{n}", own, src, builtin.get(src) if src else None))
    from humfall_ros.estop.config import trigger_params

    trigger = trigger_params(sc["estop"])
    if scenario_mod.runs_estop(sc):
        # the e-stop listens on `estop` whenever the robot walks (humfall estop), and a scenario
        # trigger acts on exactly its tick (scenario.runs_estop: the same rule in process)
        nodes.append(NodeSpec("estop_planner", "humfall_ros.nodes.estop_planner", dict(trigger), "estop",
                              builtin.get("estop")))
    for ci, c in enumerate(sc.get("controllers") or []):
        node = c["node"]
        mod = node if (node.endswith(".py") or "." in node) else f"humfall_ros.nodes.{node}"
        stem = pathlib.Path(node).stem if node.endswith(".py") else node.rsplit(".", 1)[-1]
        name = f"{stem}_{c['source']}"  # one node module may serve several sources
        own = dict(c.get("params") or {})
        if mod.startswith("humfall_ros.nodes.") and params_mod.declarations(stem):
            # a package node declares its parameters: a typo would be ignored by rclpy, refuse it here
            try:
                own = params_mod.check_overrides(stem, own, prefix=f"controllers.{ci}.params.")
            except params_mod.ParamError as e:
                raise RunError(str(e)) from None
        nodes.append(NodeSpec(name, mod, own, c["source"], int(c["priority"])))
    sources = [n for n in nodes if n.source]
    try:
        order = mux_order([n.source for n in sources], {n.source: n.priority for n in sources})
    except ValueError as e:
        raise RunError(f"controllers: {e}") from None
    names = [n.name for n in nodes]
    if len(set(names)) != len(names):
        raise RunError(f"two processes would have the same name: {names}")
    bridge = NodeSpec("sim_bridge", "humfall_ros.nodes.sim_bridge", {
        "scenario": str(run_dir / "scenario.yaml"),
        "metrics_file": str(run_dir / "metrics.json"),
        "command_sources": order or [""],
        "lockstep_sources": order or [""],
        "wait_for_nodes": ["recorder"] if record else [""],
    })
    nodes.append(bridge)
    est = {**params_mod.defaults("state_estimator"), **extra.get("state_estimator", {})}
    if est.get("use_ground_truth") is True:
        # the estimator then waits for ground_truth/odom every tick
        bridge.params["ground_truth_rate"] = float(sc["sim"]["control_rate"])
    declared = {n.name for n in nodes if not n.module.endswith(".py") and n.module.startswith("humfall_ros.nodes.")}
    unknown = set(extra) - declared
    if unknown:
        raise RunError(f"params for nodes that are not in this run: {sorted(unknown)}")
    for n in nodes:
        if n.name in declared:
            owned = set(n.params) | (SCENARIO_OWNED if n.name == "sim_bridge" else set())
            # what the scenario's content implies first: its params.<node> may still override it
            n.params = {**scenario_mod.node_defaults(sc, n.name), **n.params,
                        **check_node_params(n.name, extra.get(n.name, {}), owned=owned)}
    return nodes


def compose_nodes(nodes: list[NodeSpec], run_dir: pathlib.Path) -> list[NodeSpec]:
    """The per-tick nodes (estimator and controllers) folded into one ``composed`` process.

    The recorder and the bridge keep their own processes (the bridge owns time; the
    recorder must outlive everyone). Parameters go through a params file with a
    section per node, as ``ros2 launch`` would give a component container.
    """
    folded = [n for n in nodes if n.name not in ("recorder", "sim_bridge")]
    if len(folded) < 2:
        return nodes
    params = {n.name: {"ros__parameters": dict(n.params)} for n in folded}
    path = run_dir / "composed_params.yaml"
    path.write_text(yaml.safe_dump(params, sort_keys=False))
    composed = NodeSpec("composed", "humfall_ros.nodes.composed", {})
    composed.argv = [f"{n.name}={n.module}" for n in folded]
    composed.params_file = str(path)
    out = [n for n in nodes if n.name == "recorder"] + [composed] + [n for n in nodes if n.name == "sim_bridge"]
    return out


def check_node_params(node: str, params: dict, owned: set[str]) -> dict:
    """Refuse parameters a node does not have, of the wrong type or range, or that the launcher sets.

    Returns them typed like the node declares them (``50`` for a double becomes 50.0:
    ROS refuses an INTEGER for a DOUBLE parameter and the node would die on it).
    rclpy silently ignores overrides of undeclared parameters and kills the node on a
    wrong type after the whole suite has started: the one declaration
    (``config/<node>.yaml``, humfall_ros.params) catches both first.
    """
    for key in params:
        if key in owned:
            raise RunError(f"params.{node}.{key} is set by the launcher from the scenario "
                           "(use the scenario's own keys)")
    try:
        return params_mod.check_overrides(node, params, prefix=f"params.{node}.")
    except params_mod.ParamError as e:
        raise RunError(str(e)) from None


def child_env(run_dir: pathlib.Path, extra: dict | None = None) -> dict:
    env = {**os.environ, **(extra or {})}
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    env["RMW_IMPLEMENTATION"] = "rmw_fastrtps_cpp"
    env["ROS_LOG_DIR"] = str(run_dir / "logs" / "ros")
    env.setdefault("HOME", str(run_dir))
    env["PYTHONUNBUFFERED"] = "1"
    env["MPLBACKEND"] = "Agg"
    # children import the same humfall_ros as this process
    pkg_root = str(pathlib.Path(__file__).resolve().parents[1])
    env["PYTHONPATH"] = os.pathsep.join(x for x in (pkg_root, env.get("PYTHONPATH", "")) if x)
    return env


def up(scenario: str, controller: str | None = None, overrides: list[str] | None = None,
       runs_dir: str = "runs", record: bool = True, plots: bool = True, quiet: bool = False,
       timeout: float | None = None, compose: bool = False, env: dict | None = None) -> tuple[int, dict]:
    """Run a scenario end to end; returns (exit status, result dict).

    ``compose``: the estimator and every controller node in one process and executor
    (humfall_ros.nodes.composed), each still its own node on its own topics. ``env``: variables
    for the nodes' environment (e.g. a ROS_DOMAIN_ID per trial), over this process's.
    """
    def say(*a):
        if not quiet:
            print(*a, flush=True)

    sc = scenario_mod.load(scenario, overrides)
    if controller:
        sc = scenario_mod.apply_override(sc, f"controller={controller}")
    plan_nodes(sc, pathlib.Path(runs_dir), record)  # refuse bad node parameters before any folder exists
    run_dir = make_run_dir(pathlib.Path(runs_dir), sc["name"])
    (run_dir / "scenario.yaml").write_text(scenario_mod.dump(sc))
    log_dir = run_dir / "logs"
    log_dir.mkdir()
    nodes = plan_nodes(sc, run_dir, record)
    if compose:
        nodes = compose_nodes(nodes, run_dir)
    env = child_env(run_dir, env)
    say(f"run folder {run_dir}  (ROS_DOMAIN_ID={env.get('ROS_DOMAIN_ID', '0')})")
    procs: list[Proc] = []
    status, failure = 0, None
    interrupted = False
    t0 = time.monotonic()

    def on_sigint(*_):
        nonlocal interrupted
        interrupted = True

    old = signal.signal(signal.SIGINT, on_sigint)
    try:
        for spec in nodes:
            if spec.name == "sim_bridge":
                time.sleep(1.0)  # let the others finish start-up before time starts
            procs.append(Proc(spec.name, node_command(spec), env, log_dir))
            say(f"  started {spec.name} (pid {procs[-1].p.pid})")
        bridge = procs[-1]
        limit = timeout if timeout is not None else max(120.0, 60.0 * float(sc["duration"]))
        while not interrupted:
            if not bridge.alive():
                if bridge.p.returncode != 0:
                    failure = bridge
                break
            dead = [p for p in procs[:-1] if not p.alive()]
            if dead:
                failure = dead[0]
                break
            if time.monotonic() - t0 > limit:
                failure = bridge
                say(f"run exceeded its {limit:.0f} s wall-time limit")
                break
            time.sleep(0.1)
    finally:
        cpu = {p.name: p.cpu_seconds() for p in procs}
        # stop in reverse start order: the recorder last, so it records everything
        exits = {p.name: p.stop() for p in reversed(procs)}
        signal.signal(signal.SIGINT, old)
    wall = time.monotonic() - t0
    if failure is not None:
        status = 1
        say(f"\nnode {failure.name} died (exit {failure.p.returncode}); last lines of {failure.log_path}:")
        say(failure.tail())
    unclean = {n: c for n, c in exits.items() if c != 0 and (failure is None or n != failure.name)}
    if unclean and failure is None:
        status = 1
        say(f"\nnodes did not shut down cleanly: {unclean} (negative: killed by that signal); logs in {log_dir}")
    if interrupted:
        status = status or 130
        say("interrupted: stopped every node cleanly")
    result = collect_result(sc, run_dir, wall, record, plots and status == 0)
    if cpu.get("sim_bridge") is None and "bridge_cpu_s" in result["metrics"]:
        cpu["sim_bridge"] = result["metrics"]["bridge_cpu_s"]  # it exits on its own at the end
    result["node_cpu_s"] = cpu
    result["node_exit_codes"] = exits
    if record:
        result["bag_finalized"] = bool(result.get("recording", {}).get("finalized"))
        if not result["bag_finalized"]:
            status = status or 1
            say(f"the bag was not closed cleanly; `humfall bag recover {result['bag']}` makes a finalized copy")
    (run_dir / "result.json").write_text(json.dumps(result, indent=2))
    say(summary(result))
    return status, result


def collect_result(sc: dict, run_dir: pathlib.Path, wall: float, record: bool, plots: bool) -> dict:
    metrics_path = run_dir / "metrics.json"
    metrics = json.loads(metrics_path.read_text()) if metrics_path.is_file() else {}
    bag = next(iter(sorted(run_dir.glob("*.mcap"))), None)
    result = {
        "scenario": sc["name"],
        "controller": sc["controller"],
        "fell": metrics.get("fell"),
        "fall_direction_deg": metrics.get("fall_direction_deg"),
        "avoidance_angle_deg": metrics.get("avoidance_angle_deg"),
        "min_target_distance_m": metrics.get("min_target_distance_m"),
        **{k: metrics.get(k) for k in ("avoidance_angle_p2_deg", "predicted_avoidance_deg", "captured",
                                       "predicted_captured", "fall_event_time_s", "lead_time_s", "prediction")
           if k in metrics},
        **({"estop": metrics["estop"]} if "estop" in metrics else {}),
        "sim_duration_s": metrics.get("sim_duration_s"),
        "wall_time_s": round(wall, 3),
        "bag": str(bag) if bag else None,
        "metrics": metrics,
        "plots": [],
    }
    stats = run_dir / "recording_stats.json"
    if stats.is_file():
        result["recording"] = json.loads(stats.read_text())
    if bag is not None:
        try:  # holes in the per-tick topics (messages the recorder never got): say so with the result
            from humfall_ros.recording import bag_info

            holes = {t["topic"]: t["missing_stamps"] for t in bag_info(bag)["topics"] if t["missing_stamps"]}
            result["bag_missing_stamps"] = sum(holes.values())
            result["bag_holes"] = holes
        except Exception as e:  # noqa: BLE001 - an unreadable bag must not lose the result
            result["bag_holes_error"] = str(e)
    if bag is not None and "estop" not in result and sc["estop"] and scenario_mod.runs_estop(sc):
        try:  # the e-stop section (paper 3 figures) from the bag's estop/status and centroidal_state
            from humfall_ros.estop.metrics import estop_result_from_bag

            result["estop"] = estop_result_from_bag(str(bag), bool(metrics.get("fell")))
        except Exception as e:  # noqa: BLE001 - a figure failure must not lose the result
            result["estop_error"] = str(e)
    if plots and bag is not None:
        try:
            from humfall_ros.recording import plot_run

            result["plots"] = [str(p) for p in plot_run(bag, run_dir)]
        except Exception as e:  # noqa: BLE001 - a plot failure must not lose the result
            result["plot_error"] = str(e)
    return result


def summary(r: dict) -> str:
    def f(x, unit=""):
        return "n/a" if x is None else (f"{x:.1f}{unit}" if isinstance(x, float) else f"{x}{unit}")

    lines = [f"\n{r['scenario']} / controller {r['controller']}",
             f"  fell: {r['fell']}   fall direction: {f(r['fall_direction_deg'], ' deg')}   "
             f"avoidance angle: {f(r['avoidance_angle_deg'], ' deg')}",
             f"  min distance to target: {f(r['min_target_distance_m'], ' m')}",
             f"  sim {f(r['sim_duration_s'], ' s')} in {f(r['wall_time_s'], ' s')} wall",
             f"  bag: {r['bag']}"]
    m = r.get("metrics") or {}
    if m.get("bridge_wall_time_s") and r.get("sim_duration_s"):
        rtf = r["sim_duration_s"] / m["bridge_wall_time_s"]
        late = m.get("uncontrolled_ticks")
        lines.insert(-1, f"  real-time factor {rtf:.2f}" + (f"; {late} of {m.get('ticks')} ticks without a live "
                                                             "controller command" if late else ""))
    if r.get("bag_missing_stamps"):
        lines.append(f"  the bag misses {r['bag_missing_stamps']} stamps of periodic topics: {r['bag_holes']} "
                     "(`humfall bag info`)")
    if r.get("plots"):
        lines.append(f"  plots: {', '.join(pathlib.Path(p).name for p in r['plots'])}")
    return "\n".join(lines)
