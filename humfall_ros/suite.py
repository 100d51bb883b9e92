"""What a scenario runs, in process: the controllers and monitors ``humfall up`` would start for it.

One place for the suite's composition, used by the in-process loop (``sim.closed_loop.ClosedLoop``),
the fall experiments (``fall.runs``), benchmarks and tests: every node's parameters from its
declaration (``config/<node>.yaml``) plus what the scenario implies and its ``params.<node>``
(``node_params``); locomotion; with a fall controller the FTB monitor and the safe-fall controller;
the e-stop when the scenario walks or schedules a trigger. The wrappers give a controller or a
monitor the per-tick outputs of another (``walking/state``, ``estop/status``), as the nodes' tick
gates wait for those messages. No simulator and no rclpy here.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Callable

from humfall_ros import params as params_mod
from humfall_ros.control.contract import Controller, Observation
from humfall_ros.control.standing import StandingController
from humfall_ros.fall.controller import SafeFallConfig, SafeFallController
from humfall_ros.fall.ftb import FtbConfig, FtbMonitor

CONTROLLERS = ("none", "stepping", "stepping_inertia")


def node_params(sc: dict, node: str) -> dict:
    """A node's parameters for this scenario: its declaration's defaults, what the scenario's
    content implies (``scenario.node_defaults``), then ``params.<node>``."""
    from humfall_ros.scenario import node_defaults

    p = params_mod.defaults(node)
    p.update(node_defaults(sc, node))
    p.update(params_mod.check_overrides(node, sc["params"].get(node, {}), prefix=f"params.{node}."))
    return p


def locomotion_controller(sc: dict, model):
    """The locomotion node's controller for this scenario (what the node builds from the same file)."""
    from humfall_ros.walking.controller import from_scenario

    return from_scenario(sc, model, node_params(sc, "locomotion"))


class SameTickInputs:
    """A controller whose observation also gets inputs computed this tick by controllers before it.

    ``SameTickInputs(estop, {"walking/state": lambda: walking.state})`` gives the e-stop the walking
    state of the same tick (walking comes first in the loop's list), as the e-stop node's tick gate
    waits for ``walking/state`` of the tick's stamp.
    """

    def __init__(self, controller: Controller, providers: dict[str, Callable[[], Any]]):
        self.inner = controller
        self.source = controller.source
        self.providers = dict(providers)

    def __getattr__(self, name):  # status, decision, ... of the wrapped controller
        return getattr(self.inner, name)

    def reset(self) -> None:
        self.inner.reset()

    def step(self, observation: Observation):
        extra = {k: f() for k, f in self.providers.items()}
        return self.inner.step(dataclasses.replace(observation, inputs={**observation.inputs, **extra}))


def suite(sc: dict, model) -> tuple[list[Controller], list]:
    """The controllers and monitors ``humfall up`` starts for ``sc``, as in-process objects.

    locomotion (``locomotion_controller``); with ``controller`` stepping / stepping_inertia the FTB
    monitor and the safe-fall controller (``controllers_for``); the e-stop when the scenario walks
    or schedules a trigger (fed the walking state of the same tick).
    """
    monitors: list = []
    if sc["controller"] != "none":
        # its locomotion controller is the one the gait-fed FTB and the safe-fall controller read
        controllers, monitors = controllers_for(sc, sc["controller"], model)
        loco = controllers[0]
        assert loco.source == "locomotion"
    else:
        loco = locomotion_controller(sc, model)
        controllers = [loco]
    from humfall_ros.scenario import runs_estop

    if runs_estop(sc):
        from humfall_ros.estop.config import EstopConfig, trigger_params
        from humfall_ros.estop.controller import EstopController

        p = node_params(sc, "estop_planner")
        p.update(trigger_params(sc["estop"]))
        estop = EstopController(model, EstopConfig.from_params(p), 1.0 / sc["sim"]["control_rate"])
        controllers.append(SameTickInputs(estop, {"walking/state": lambda: loco.state}))
        for m in monitors:
            if getattr(m, "config", None) is not None and m.config.use_estop_status and hasattr(m, "estop"):
                m.estop = estop  # the FTB's stop reference while it plays (the node waits for estop/status)
    return controllers, monitors


def standing_controller(sc: dict, model) -> StandingController:
    """The standing balance alone as the "locomotion" source (the walking controller stands with it too)."""
    p = node_params(sc, "locomotion")
    return StandingController(model, model.standing_posture, p["ankle_kp"], p["ankle_kd"], p["ankle_max_offset"],
                              p["resume_time"])


class GaitFedFtb:
    """The FTB monitor fed ``walking/state`` from the walking controller (``use_walking_state``) and, once
    ``estop`` is set (``use_estop_status``), ``estop/status`` from the e-stop controller.

    The loop runs monitors before controllers, so the states read are the ones the controllers
    computed on the previous tick (2 ms old; on the graph the FTB waits for the same tick's
    messages). The monitor's ``name``, ``latched``, ``event`` and ``state`` are the FTB's.
    """

    def __init__(self, ftb: FtbMonitor, walking=None, estop=None):
        self.inner = ftb
        self.walking = walking
        self.estop = estop
        self.name = ftb.name

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def reset(self) -> None:
        self.inner.reset()

    def step(self, observation):
        extra = {}
        state = getattr(self.walking, "state", None)
        if state is not None:
            extra["walking/state"] = state
        status = getattr(self.estop, "status", None)
        if status is not None:
            extra["estop/status"] = status
        if not extra:
            return self.inner.step(observation)
        return self.inner.step(dataclasses.replace(observation, inputs={**observation.inputs, **extra}))


def controllers_for(sc: dict, kind: str, model=None):
    """(controllers, monitors) of the run, as the launcher would start them for ``kind``."""
    from humfall_ros.launch import CONTROLLER_PARAMS
    from humfall_ros.model.humanoid import load_model
    if kind not in CONTROLLERS:
        raise ValueError(f"controller must be one of {CONTROLLERS}, got {kind!r}")
    model = model or load_model()
    ftb = FtbMonitor(FtbConfig.from_params(node_params(sc, "ftb_monitor")))
    ctrls = [locomotion_controller(sc, model)]  # the locomotion node's own controller
    if ftb.config.use_walking_state or ftb.config.use_estop_status:  # the e-stop is set by suite()
        ftb = GaitFedFtb(ftb, ctrls[0] if ftb.config.use_walking_state else None)
    if kind != "none":
        p = node_params(sc, "safe_fall_controller")
        p.update(CONTROLLER_PARAMS.get(kind, {}).get("safe_fall_controller", {}))
        safe = SafeFallController(model, SafeFallConfig.from_params(p))
        loco = ctrls[0]
        # walking/state of the same tick (the node reads the latest message): the planned footstep
        ctrls.append(SameTickInputs(safe, {"walking/state": lambda: loco.state}))
    return ctrls, [ftb]


__all__ = ["CONTROLLERS", "GaitFedFtb", "SameTickInputs", "controllers_for", "locomotion_controller",
           "node_params", "standing_controller", "suite"]
