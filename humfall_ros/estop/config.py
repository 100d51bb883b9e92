"""The e-stop's configuration, built from ``config/estop_planner.yaml`` (one source per parameter)."""
from __future__ import annotations

import dataclasses

from humfall_ros import params

BETA_POLICIES = ("clamp", "supremum", "omega_c")
# the scenario's single-support phase names (humfall_ros.scenario.Phase) -> elapsed fraction (issue 12's trials)
SS_PHASES = {"ss_start": 0.1, "ss_mid": 0.5, "ss_end": 0.95}
FALLBACKS = ("min_n3_crouch", "none")
BLEND_PROFILES = ("linear", "quintic")
# parameters of config/estop_planner.yaml that only the node reads (not EstopConfig's)
NODE_KEYS = frozenset({"walking_state_input"})


@dataclasses.dataclass(frozen=True)
class TriggerPhase:
    """A gait phase for a scheduled trigger (scenario ``estop.at.phase``).

    Attributes:
        kind: ``ds_start`` (first tick of a double support), ``ds_mid`` (its middle) or ``ss``.
        fraction: for ``ss``, the fraction of the single support elapsed, in [0, 1].
    """

    kind: str
    fraction: float = 0.0

    @staticmethod
    def parse(text: str) -> TriggerPhase:
        text = text.strip()
        if text in ("ds_start", "ds_mid"):
            return TriggerPhase(text)
        if text in SS_PHASES:
            return TriggerPhase("ss", SS_PHASES[text])
        if text.startswith("ss:"):
            try:
                f = float(text[3:])
            except ValueError:
                f = float("nan")
            if not 0.0 <= f <= 1.0:
                raise ValueError(f"trigger_phase {text!r}: the single-support fraction must be in [0, 1]")
            return TriggerPhase("ss", f)
        raise ValueError(f"trigger_phase {text!r} is not ds_start, ds_mid, ss_start, ss_mid, ss_end "
                         "or ss:<fraction>")


@dataclasses.dataclass(frozen=True)
class EstopConfig:
    """Every parameter of the estop_planner node (units and meaning in config/estop_planner.yaml)."""

    omega_f: float = 25.0
    cog_height_min: float = 0.5
    cog_height_max: float = 1.0
    max_cog_speed: float = 1.5
    minor_lqr_weights: tuple[float, float, float] = (1.0, 10.0, 1.0)
    minor_lqr_input_weight: float = 0.1
    lqr_cog_height: float = 0.74
    major_beta: float = -100.0
    beta_policy: str = "omega_c"
    major_beta_ratio: float = 2.0
    beta_margin: float = 0.05
    zmp_margin: float = 0.015
    samples: int = 96
    settle_speed: float = 0.01
    terminal_tolerance: float = 1e-5
    joint_margin: float = 0.02
    ik_max_iterations: int = 60
    ik_dt: float = 0.05
    ik_tolerance: float = 1e-3
    crouch_min_cog_height: float = 0.55
    crouch_clearance: float = 0.02
    crouch_duration: float = 0.8
    fallback: str = "min_n3_crouch"
    ankle_kp: float = 0.3
    ankle_kd: float = 0.05
    ankle_max_offset: float = 0.12
    com_integral_gain: float = 0.0
    com_integral_max: float = 0.03
    foot_cop_gain: float = 0.0
    foot_cop_min_force: float = 150.0
    foot_cop_time_constant: float = 0.2
    sole_sinkage_gain: float = 1.0
    flatten_held_feet: bool = True
    blend_profile: str = "quintic"
    foot_force_gain: float = 3e-5
    foot_height_time_constant: float = 0.05
    foot_height_max: float = 0.0005
    sole_flat_gain: float = 20.0
    sole_flat_max: float = 0.02
    sole_flat_time_constant: float = 0.3
    sole_flat_min_force: float = 150.0
    joint_stop_time: float = 0.3
    home_duration: float = 1.5
    align_feet: bool = True
    align_shift_time: float = 0.8
    align_swing_time: float = 0.8
    align_apex: float = 0.04
    align_width_offset: float = 0.0
    align_min_offset: float = 0.01
    align_max_speed: float = 0.05
    trigger_time: float = -1.0
    trigger_step: int = -1
    trigger_phase: str = "ds_start"

    def __post_init__(self):
        if self.beta_policy not in BETA_POLICIES:
            raise ValueError(f"beta_policy {self.beta_policy!r} is not one of {', '.join(BETA_POLICIES)}")
        if self.blend_profile not in BLEND_PROFILES:
            raise ValueError(f"blend_profile {self.blend_profile!r} is not one of {', '.join(BLEND_PROFILES)}")
        if self.fallback not in FALLBACKS:
            raise ValueError(f"fallback {self.fallback!r} is not one of {', '.join(FALLBACKS)}")
        if len(self.minor_lqr_weights) != 3 or min(self.minor_lqr_weights) < 0:
            raise ValueError(f"minor_lqr_weights must be 3 numbers >= 0, got {self.minor_lqr_weights}")
        if not self.cog_height_min < self.cog_height_max:
            raise ValueError("cog_height_min must be below cog_height_max")
        object.__setattr__(self, "minor_lqr_weights", tuple(float(w) for w in self.minor_lqr_weights))
        TriggerPhase.parse(self.trigger_phase)

    @property
    def phase(self) -> TriggerPhase:
        return TriggerPhase.parse(self.trigger_phase)

    @staticmethod
    def from_params(d: dict) -> EstopConfig:
        """From a dict of parameter names (e.g. ``params.defaults("estop_planner")``); unknown keys are refused
        (the node's own keys, :data:`NODE_KEYS`, are ignored)."""
        return params.config_from(EstopConfig, d, "estop_planner", ignore=tuple(NODE_KEYS))

    @staticmethod
    def defaults(**overrides) -> EstopConfig:
        """The declared defaults (config/estop_planner.yaml), with ``overrides``."""
        return EstopConfig.from_params({**params.defaults("estop_planner"), **overrides})


def trigger_params(estop: dict) -> dict:
    """The node parameters of a scenario's ``estop`` section (humfall_ros.scenario.Estop).

    ``time`` >= 0 -> ``trigger_time``; ``at: {step, phase}`` -> ``trigger_step``, ``trigger_phase`` (the
    e-stop's phase names: ds_start, ds_mid, ss_start / ss_mid / ss_end = 0.1 / 0.5 / 0.95 of the single
    support); a ``random_window`` [lo, hi] with hi > 0 and neither of those -> ``trigger_time`` drawn
    uniformly in it with ``seed`` (numpy's default_rng); nothing -> {} (no scheduled trigger).
    """
    if estop.get("at") is not None:
        TriggerPhase.parse(estop["at"]["phase"])
        return {"trigger_step": int(estop["at"]["step"]), "trigger_phase": str(estop["at"]["phase"])}
    if float(estop.get("time", -1.0)) >= 0:
        return {"trigger_time": float(estop["time"])}
    lo, hi = (float(v) for v in estop.get("random_window", (0.0, 0.0)))
    if hi > 0:
        import numpy as np

        return {"trigger_time": float(lo + (hi - lo) * np.random.default_rng(int(estop.get("seed", 0))).random())}
    return {}


__all__ = ["BETA_POLICIES", "BLEND_PROFILES", "FALLBACKS", "NODE_KEYS", "SS_PHASES", "EstopConfig", "TriggerPhase",
           "trigger_params"]
