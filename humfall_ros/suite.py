"""What a scenario runs, in process: the controllers and monitors ``humfall up`` would start for it.

One place for the suite's composition, used by the in-process loop (``sim.closed_loop.ClosedLoop``),
the fall experiments (``sim.fall_runs``), benchmarks and tests: every node's parameters from its
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
from humfall_ros.scenario import CONTROLLER_PARAMS, CONTROLLERS


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
    """A controller or monitor whose observation also gets inputs that other in-process controllers computed.

    ``SameTickInputs(estop, {"walking/state": lambda: walking.state})`` gives the e-stop the walking state of
    the same tick (walking comes first in the loop's list), as the e-stop node's tick gate waits for
    ``walking/state`` of the tick's stamp. A monitor (the FTB fed ``walking/state`` and ``estop/status``) runs
    before the controllers, so it reads what they computed on the previous tick (2 ms old; on the graph the
    FTB waits for the same tick's messages). A provider that returns None adds nothing. Everything else
    (``source``, ``name``, ``status``, ``decision``, ``latched``, ...) is the wrapped object's.
    """

    def __init__(self, inner, providers: dict[str, Callable[[], Any]]):
        self.inner = inner
        self.providers = dict(providers)

    def __getattr__(self, name):
        if name in ("inner", "providers"):  # not set yet (copy, unpickling): no recursion
            raise AttributeError(name)
        return getattr(self.inner, name)

    def reset(self) -> None:
        self.inner.reset()

    def step(self, observation: Observation):
        extra = {k: v for k, v in ((k, f()) for k, f in self.providers.items()) if v is not None}
        if not extra:
            return self.inner.step(observation)
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
            if isinstance(m, SameTickInputs) and m.config.use_estop_status:
                # the FTB's stop reference while it plays (the node waits for estop/status)
                m.providers["estop/status"] = lambda: estop.status
    return controllers, monitors


def standing_controller(sc: dict, model) -> StandingController:
    """The standing balance alone as the "locomotion" source (the walking controller stands with it too)."""
    p = node_params(sc, "locomotion")
    return StandingController(model, model.standing_posture, p["ankle_kp"], p["ankle_kd"], p["ankle_max_offset"],
                              p["resume_time"])


def controllers_for(sc: dict, kind: str, model=None):
    """(controllers, monitors) of the run, as the launcher would start them for ``kind``."""
    from humfall_ros.model.humanoid import load_model
    if kind not in CONTROLLERS:
        raise ValueError(f"controller must be one of {CONTROLLERS}, got {kind!r}")
    model = model or load_model()
    ftb = FtbMonitor(FtbConfig.from_params(node_params(sc, "ftb_monitor")))
    ctrls = [locomotion_controller(sc, model)]  # the locomotion node's own controller
    if ftb.config.use_walking_state or ftb.config.use_estop_status:  # the e-stop's status is added by suite()
        loco0 = ctrls[0]
        ftb = SameTickInputs(ftb, {"walking/state": lambda: getattr(loco0, "state", None)}
                             if ftb.config.use_walking_state else {})
    if kind != "none":
        p = node_params(sc, "safe_fall_controller")
        p.update(CONTROLLER_PARAMS.get(kind, {}).get("safe_fall_controller", {}))
        safe = SafeFallController(model, SafeFallConfig.from_params(p))
        loco = ctrls[0]
        # walking/state of the same tick (the node reads the latest message): the planned footstep
        ctrls.append(SameTickInputs(safe, {"walking/state": lambda: loco.state}))
    return ctrls, [ftb]


__all__ = ["CONTROLLERS", "SameTickInputs", "controllers_for", "locomotion_controller",
           "node_params", "standing_controller", "suite"]
