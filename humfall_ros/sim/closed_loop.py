"""The suite in one process: world -> sensors -> estimator -> monitors -> controllers -> mux -> world.

The ROS graph runs the same pieces in separate processes, tick for tick in the
same order (the bridge publishes the sensors and the mux state of tick k, the
estimator answers, the monitors and controllers answer, the bridge arbitrates
with the same ``CommandMux`` and steps), from the same parameter declarations
(``config/<node>.yaml`` plus the scenario's ``params``). So a lockstep run gives
the same joint states in process and over ROS (tested). This loop is for unit
tests, benchmarks and campaigns, where DDS would only add time.

A *monitor* (e.g. the FTB) is a per-tick stage that is not a command source:
``name``, ``reset()``, ``step(observation) -> value``; its value goes into the
controllers' ``observation.inputs[name]`` of the same tick, as its per-tick topic
would. A monitor may also keep a dict ``latched`` (e.g. ``{"fall_event": ...}``):
its entries are in every later observation's inputs, as a transient-local topic's
last message would be; an entry whose value is None removes that input from this tick on
(the topic's "cleared" message, e.g. the FTB's recovery clearing ``fall_event``).

Every observation's inputs also hold ``"imu"``: ``(orientation xyzw, gyro in the IMU
frame)`` as numpy arrays (what a node gets from the per-tick ``imu`` topic), and
``"obstacles"`` (the scenario's boxes as ``contract.Obstacle``).
"""
from __future__ import annotations

import dataclasses
from typing import Any, Callable, Protocol

import numpy as np

from humfall_ros.control.contract import (Controller, JointTargets, Observation, Obstacle, centroidal_from_estimate,
                                          stamp_ns_of)
from humfall_ros.control.mux import CommandMux, JointCommand, mux_order
from humfall_ros.model.estimation import CentroidalEstimator, estimate_error
from humfall_ros.sim.ground_truth import GroundTruth
from humfall_ros.sim.sensors import SensorNoise, Sensors
from humfall_ros.sim.world import SimWorld
from humfall_ros.suite import node_params, suite

class Monitor(Protocol):
    name: str

    def reset(self) -> None: ...

    def step(self, observation: Observation) -> Any: ...


@dataclasses.dataclass
class LoopResult:
    metrics: dict
    joint_positions: np.ndarray          # ticks x joints, measured (what joint_states carries)
    max_errors: dict                     # estimator vs ground truth, until trunk_tilt_limit
    max_trunk_tilt_deg: float
    active_sources: list[str] = dataclasses.field(default_factory=list)  # per tick, as MuxState.active
    outputs: dict[str, list] = dataclasses.field(default_factory=dict)   # per-tick monitor values by name


def to_command(stamp: float, targets: JointTargets | None, joint_names: list[str]) -> JointCommand:
    """What the controller node publishes (a JointState), as the bridge receives it."""
    if targets is None:
        return JointCommand(stamp, [], [])
    q = [float(x) for x in np.asarray(targets.positions, float)]
    v = [] if targets.velocities is None else [float(x) for x in np.asarray(targets.velocities, float)]
    return JointCommand(stamp, list(joint_names), q, v)


def sensor_noise(sc: dict) -> SensorNoise:
    """The bridge's sensor noise of this scenario (``params.sim_bridge.noise_*``)."""
    b = node_params(sc, "sim_bridge")
    return SensorNoise(**{f.name: b[f"noise_{f.name}"] for f in dataclasses.fields(SensorNoise) if f.name != "seed"},
                       seed=b["noise_seed"])


class ClosedLoop:
    """One scenario, in process. ``step()`` runs one control tick; ``run()`` to the end.

    Args:
        sc: a validated scenario (humfall_ros.scenario).
        controllers: contract controllers (default: what ``humfall up`` starts for the scenario, ``suite``).
        monitors: per-tick stages whose values feed the controllers' inputs.
        priorities: mux priorities of the controllers' sources (higher wins; defaults for the built-ins).
        noise: sensor noise (default: the scenario's ``params.sim_bridge.noise_*``).
        inputs: a callable (loop, observation) -> None that may add latched inputs (e.g. a
            walking command) to the observation before the controllers see it.
    """

    def __init__(self, sc: dict, controllers: list[Controller] | None = None, monitors: list[Monitor] | None = None,
                 priorities: dict[str, int] | None = None, noise: SensorNoise | None = None,
                 inputs: Callable[["ClosedLoop", Observation], None] | None = None, track_errors: bool = False,
                 trunk_tilt_limit_deg: float = 30.0):
        s = sc["sim"]
        self.sc = sc
        posture = None
        if sc["robot"]["initial_posture"]:
            from humfall_ros.model.humanoid import STANDING_POSTURE

            posture = {**STANDING_POSTURE, **sc["robot"]["initial_posture"]}
        bridge = node_params(sc, "sim_bridge")
        self.world = SimWorld(s["physics_rate"], s["control_rate"], friction=s["friction"], initial_posture=posture,
                              contact_breaking_threshold=s["contact_breaking_threshold"],
                              servo_time_constant=s["servo_time_constant"])
        self.model = self.world.model
        self.ground_truth = GroundTruth(self.world, sc)
        self.sensors = Sensors(self.world, sensor_noise(sc) if noise is None else noise)
        est = node_params(sc, "state_estimator")
        self.estimator = CentroidalEstimator(self.model, contact_force=est["contact_force"],
                                             com_velocity_time_constant=est["com_velocity_time_constant"],
                                             com_velocity_band=est["com_velocity_band"])
        if controllers is None:
            controllers, default_monitors = suite(sc, self.model)
            monitors = default_monitors if monitors is None else monitors
        self.controllers = list(controllers)
        self.monitors = list(monitors or [])
        order = mux_order([c.source for c in self.controllers], priorities)
        self.mux = CommandMux(order, self.model.joint_names, bridge["command_timeout"])
        self.inputs = inputs
        self.active = "none"
        self.track_errors = track_errors
        # the reference for the estimator's errors: exact sensors, leg odometry only (its fused fields = odometry's)
        self._truth = CentroidalEstimator(self.model, contact_force=est["contact_force"],
                                          com_velocity_time_constant=0.0) if track_errors else None
        self.tilt_limit = np.radians(trunk_tilt_limit_deg)
        self.errors: dict[str, float] = {}
        self._past_tilt_limit = False
        self.joint_positions: list[np.ndarray] = []
        self.active_sources: list[str] = []
        self.outputs: dict[str, list] = {m.name: [] for m in self.monitors}
        self.latched: dict[str, Any] = {}
        self.obstacles = [Obstacle(o["name"], tuple(o["position"]), tuple(o["size"]), o["yaw"], o["is_target"])
                          for o in sc["obstacles"]]
        for c in self.controllers:
            c.reset()
        for m in self.monitors:
            m.reset()

    def step(self) -> Observation:
        w = self.world
        r = self.sensors.read()
        stamp = stamp_ns_of(w.time)
        e = self.estimator.update(stamp * 1e-9, r.joint_position, r.joint_velocity, r.imu_orientation, r.gyro,
                                  r.wrenches)
        self.joint_positions.append(r.joint_position)
        self.active_sources.append(self.active)
        if self.track_errors and not self._past_tilt_limit and w.trunk_tilt() >= self.tilt_limit:
            self._past_tilt_limit = True  # compared until the trunk first passes the limit, not after a rebound
        if self.track_errors and not self._past_tilt_limit and w.time > 0.05:  # skip the first settling
            qj, vj, _ = w.joint_states()
            g = self._truth.update(w.time, qj, vj, r.imu_orientation, r.gyro, r.wrenches,
                                   base_truth=w.base_state())
            for k, v in estimate_error(e, g).items():
                self.errors[k] = max(self.errors.get(k, 0.0), v)
        obs = Observation(stamp, np.asarray(r.joint_position, float), np.asarray(r.joint_velocity, float),
                          centroidal_from_estimate(e), self.active, {"obstacles": self.obstacles},
                          joint_targets=np.array(w.targets, dtype=float))
        obs.inputs["imu"] = (np.asarray(r.imu_orientation, float), np.asarray(r.gyro, float))
        obs.inputs.update(self.latched)
        for m in self.monitors:
            value = m.step(obs)
            obs.inputs[m.name] = value
            self.outputs[m.name].append(value)
            latched = getattr(m, "latched", None)
            if latched:
                for key, v in latched.items():  # None: cleared (the input is gone from this tick on)
                    if v is None:
                        self.latched.pop(key, None)
                        obs.inputs.pop(key, None)
                    else:
                        self.latched[key] = obs.inputs[key] = v
        if self.inputs is not None:
            self.inputs(self, obs)
        t = stamp * 1e-9
        for c in self.controllers:
            self.mux.update(c.source, to_command(t, c.step(obs), self.model.joint_names), now=t)
        decision, q, v = self.mux.targets(t, w.targets, w.target_velocities)
        if decision.source is not None and not decision.holding:
            w.set_joint_targets(q, v)
        self.active = decision.source or "none"
        w.step_control()
        self.ground_truth.track()
        self._note_events()
        return obs

    def _note_events(self) -> None:
        """What the bridge learns from ``fall_event`` and ``safe_fall/decision``, for the run metrics."""
        m = self.ground_truth.metrics
        for mon in self.monitors:
            event = getattr(mon, "event", None)
            if event is not None:
                m.note_fall_event(getattr(event, "time", None))
        for c in self.controllers:
            decision = getattr(c, "decision", None)
            if decision is not None:
                m.note_decision(decision)

    def run(self, duration: float | None = None, stop: Callable[["ClosedLoop"], bool] | None = None) -> LoopResult:
        """Run to the scenario's end (or ``duration`` [s]), or until ``stop(loop)`` is true after a tick."""
        ticks = int(round((duration or self.sc["duration"]) * self.sc["sim"]["control_rate"]))
        for _ in range(ticks):
            self.step()
            if stop is not None and stop(self):
                break
        r = self.metrics()
        return LoopResult(r, np.array(self.joint_positions), dict(self.errors), r["max_trunk_tilt_deg"],
                          list(self.active_sources), self.outputs)

    def metrics(self) -> dict:
        """The ground truth's run metrics, plus what each controller reports of its run (``run_metrics()``,
        e.g. the e-stop's ``estop_*``), as one flat dict."""
        r = self.ground_truth.metrics.result()
        for c in self.controllers:
            run_metrics = getattr(c, "run_metrics", None)
            if callable(run_metrics):
                r.update(run_metrics())
        return r

    def close(self) -> None:
        self.world.close()


def run_scenario(sc: dict, duration: float | None = None, trunk_tilt_limit_deg: float = 30.0,
                 noise: SensorNoise | None = None, controllers: list[Controller] | None = None,
                 monitors: list[Monitor] | None = None, priorities: dict[str, int] | None = None,
                 inputs=None) -> LoopResult:
    """Run a validated scenario without ROS (see ClosedLoop); estimator errors are tracked."""
    loop = ClosedLoop(sc, controllers, monitors, priorities, noise, inputs, track_errors=True,
                      trunk_tilt_limit_deg=trunk_tilt_limit_deg)
    try:
        return loop.run(duration)
    finally:
        loop.close()
