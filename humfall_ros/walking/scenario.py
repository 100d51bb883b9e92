"""A scenario's walk: the walking commands it gives and the sim time of its gait phases. No rclpy, no simulator.

The scenario's ``walk:`` section (humfall_ros/scenario.py: ``start_time``, ``speed_kmh``,
``direction_deg``, ``steps``, ``step_period``, ``double_support``, ``turn_rate_deg_s``) becomes

* :func:`walk_schedule`: the timed :class:`WalkCommand` list the :class:`LocomotionController`
  acts on (in process and in the ``locomotion`` node, which gets the scenario file as its
  ``scenario`` parameter),
* :func:`walking_config`: the controller's settings for that scenario (``params.locomotion`` over
  the declared defaults, then ``walk.step_period`` / ``walk.double_support``),
* :func:`phase_time`: the sim time of a gait event ``{step: K, phase: ...}``, from the walking
  pattern's own timeline (:class:`WalkingPattern`), so pushes and e-stops can be timed by phase.

Gait events. Step ``K`` (0 = the first step) is the ``K``-th swing; its double support is the one
*before* that swing (for ``K = 0`` the start double support, in which the ZMP moves onto the first
stance foot; for ``K >= 1`` the double support after swing ``K - 1``), then its single support.
``steps = N`` gives swings ``K = 0 .. N - 1`` and the stop step ``K = N`` (the last swing foot lands
beside the other). ``ds_start``/``ss_start``: the first tick of the phase; ``ds_mid``/``ss_mid``:
the first tick at half of it; ``ss_end``: the first tick after the single support (touchdown, the
same instant as the next step's ``ds_start``). The time is the stamp of the control tick whose
``walking/state`` first shows that phase (support and ``phase_fraction``): the walk starts at the
first control tick at or after ``walk.start_time``, and the pattern sample published at that tick
is the pattern's tick 1.
"""
from __future__ import annotations

import math

from humfall_ros import params as params_mod
from humfall_ros.model.humanoid import HumanoidModel, load_model
from humfall_ros.walking.config import LocomotionConfig
from humfall_ros.walking.footsteps import Footstep, WalkCommand, step_width
from humfall_ros.walking.pattern import WalkingPattern

PHASES = ("ds_start", "ds_mid", "ss_start", "ss_mid", "ss_end")


class WalkScenarioError(ValueError):
    """A scenario's walk the walking controller cannot follow (the message says why)."""


def walking_params(sc: dict, params: dict | None = None) -> dict:
    """The locomotion parameters of scenario ``sc``: ``params`` (e.g. a node's declared values) or
    the declared defaults with ``params.locomotion`` over them, then the walk's ``step_period`` and
    ``double_support`` (the scenario's statement of the gait; a conflicting ``params.locomotion``
    value is refused)."""
    if params is None:
        p = params_mod.defaults("locomotion")
        given = sc.get("params", {}).get("locomotion", {})
        p.update(params_mod.check_overrides("locomotion", given, prefix="params.locomotion."))
    else:
        p = dict(params)
        given = {}
    w = sc["walk"]
    for key in ("step_period", "double_support"):
        if key in given and abs(float(given[key]) - float(w[key])) > 1e-12:
            raise WalkScenarioError(f"params.locomotion.{key} = {given[key]} contradicts walk.{key} = {w[key]}: "
                                    f"give it once, in walk")
        p[key] = float(w[key])
    return p


def walking_config(sc: dict, params: dict | None = None) -> LocomotionConfig:
    """The controller settings of scenario ``sc`` (:func:`walking_params`, then ``from_params``)."""
    return LocomotionConfig.from_params(walking_params(sc, params))


def control_period(sc: dict) -> float:
    """The control period of the scenario [s]."""
    return 1.0 / float(sc["sim"]["control_rate"])


def walk_schedule(sc: dict) -> list[tuple[float, WalkCommand]]:
    """The walking commands of scenario ``sc``: [(sim time [s], command)], empty when it does not walk.

    One command at ``walk.start_time``: ``speed_kmh`` [km/h] -> m/s, ``turn_rate_deg_s`` -> rad/s,
    ``steps`` swings then the stop step. ``direction_deg`` other than 0 (sideways or backward walking)
    is refused: the pattern walks forward along the feet's heading only."""
    w = sc["walk"]
    if int(w["steps"]) <= 0 or (float(w["speed_kmh"]) == 0.0 and float(w["turn_rate_deg_s"]) == 0.0):
        return []
    if abs(float(w["direction_deg"])) > 1e-9:
        raise WalkScenarioError(f"walk.direction_deg = {w['direction_deg']}: only forward walking (0 deg) is "
                                f"supported (turn with walk.turn_rate_deg_s)")
    cmd = WalkCommand(float(w["speed_kmh"]) / 3.6, math.radians(float(w["turn_rate_deg_s"])), int(w["steps"]))
    return [(float(w["start_time"]), cmd)]


def start_tick_time(start_time: float, dt: float) -> float:
    """Sim time [s] of the first control tick at or after ``start_time`` (ticks at k * dt)."""
    return math.ceil(start_time / dt - 1e-6) * dt


def phase_time(sc: dict, at: dict, model: HumanoidModel | None = None) -> float:
    """Absolute sim time [s] of the gait event ``at = {"step": K, "phase": ...}`` of ``sc``'s walk
    (module docstring). Raises WalkScenarioError when the scenario does not walk or has no step K."""
    schedule = walk_schedule(sc)
    if not schedule:
        raise WalkScenarioError("the scenario does not walk (walk.steps = 0 or no speed): no gait phases")
    phase = at["phase"]
    if phase not in PHASES:
        raise WalkScenarioError(f"phase {phase!r} is not one of {', '.join(PHASES)}")
    k = int(at["step"])
    t_start, cmd = schedule[0]
    if not 0 <= k <= cmd.n_steps:
        raise WalkScenarioError(f"step {k} is outside the walk (steps 0 .. {cmd.n_steps}, the last is the stop)")
    cfg = walking_config(sc)
    dt = control_period(sc)
    model = model or load_model()
    pattern = rehearsal_pattern(cfg, dt, model, cmd)
    ss = pattern.single_support_phase(k + 1)
    ds = pattern.phase_before(ss)
    if phase.startswith("ds"):
        tick = ds.start + (math.ceil(ds.ticks / 2 - 1e-9) if phase == "ds_mid" else 0)
    elif phase == "ss_start":
        tick = ss.start
    elif phase == "ss_mid":
        tick = ss.start + math.ceil(ss.ticks / 2 - 1e-9)
    else:
        tick = ss.end
    t0 = start_tick_time(t_start, dt)
    return t0 + max(tick - 1, 0) * dt


def rehearsal_pattern(cfg: LocomotionConfig, dt: float, model: HumanoidModel, cmd: WalkCommand) -> WalkingPattern:
    """The pattern of ``cmd`` from the standing posture (the timeline the controller will follow)."""
    q = model.configuration([0, 0, 0], [0, 0, 0, 1], model.joint_vector(model.standing_posture))
    model.forward(q)
    z0 = float(model.com(q)[2] - model.frame_position(model.sole_frame["l"])[2])  # above the soles
    w = step_width(model) + cfg.step_width_offset
    feet = {"l": Footstep("l", 0.0, w / 2, 0.0), "r": Footstep("r", 0.0, -w / 2, 0.0)}
    return WalkingPattern(cfg, dt, w, 0.0, feet, [0.0, 0.0, z0], cmd, cmd.n_steps)


__all__ = ["PHASES", "WalkScenarioError", "control_period", "phase_time", "rehearsal_pattern", "start_tick_time",
           "walk_schedule", "walking_config", "walking_params"]
