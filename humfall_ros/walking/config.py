"""The locomotion node's settings as a typed dataclass, built from ``config/locomotion.yaml``."""
from __future__ import annotations

import dataclasses
import math
from typing import Any

from humfall_ros import params


# declared parameters of the node that are not controller settings (``scenario``: the file the node reads)
NODE_ONLY = ("scenario",)
RESUME_STANCES = ("feet", "standard")   # after regaining control: stand where the feet are, or the standard stance


@dataclasses.dataclass(frozen=True)
class LocomotionConfig:
    """Standing and walking settings (units in brackets; meanings in config/locomotion.yaml)."""

    ankle_kp: float = 0.3                 # rad/m, standing balance
    ankle_kd: float = 0.05                # rad s/m
    ankle_max_offset: float = 0.12        # rad
    resume_time: float = 1.0              # s, standing: blend back from the measured posture
    resume_stance: str = "feet"           # "feet": stand where the feet are (IK); "standard": the standing posture
    resume_from_targets: bool = True      # resume from the servos' targets (mux), not the measured joints
    walk_stance_tolerance: float = 0.05   # m, a walk starts only from a stance this close to the standard one
    step_period: float = 0.8              # s
    fast_step_period: float = 0.7         # s, above fast_step_speed_kmh (0: step_period at every speed)
    fast_step_speed_kmh: float = 1.35     # km/h
    double_support: float = 0.1           # s
    com_height: float = 0.70              # m
    swing_apex: float = 0.05              # m
    landing_height: float = 0.0008        # m, the swing ends this high; the foot descends in the double support
    landing_duration: float = 0.02        # s
    liftoff_height: float = 0.0           # m, the rear foot rises this much at the end of a step's double support
    liftoff_duration: float = 0.03        # s, over this last part of it
    step_width_offset: float = 0.0        # m
    crouch_duration: float = 1.0          # s
    start_duration: float = 0.8           # s
    stop_duration: float = 0.8            # s
    settle_duration: float = 1.0          # s
    max_speed_kmh: float = 2.5            # km/h
    max_turn_rate_deg_s: float = 20.0     # deg/s
    preview_horizon: float = 1.6          # s
    preview_q: float = 1.0
    preview_r: float = 1e-7
    multibody_correction: bool = True
    multibody_horizon: float = 0.6        # s
    dcm_gain: float = 0.0                 # m/m
    com_feedback_max: float = 0.03        # m
    zmp_integral_gain: float = 0.0        # 1/s
    zmp_integral_max: float = 0.06        # m
    cop_damping_gain: float = 1.0         # rad/(m s)
    cop_damping_time_constant: float = 0.2  # s
    cop_damping_time_constant_ds: float = 0.2  # s, in double support
    walk_ankle_max_offset: float = 0.05   # rad
    sole_sinkage_gain: float = 1.0        # 1, times the URDF sole contact's sinkage under the planned load
    sole_sinkage_damping: bool = True     # the contact damper's lead in that sinkage
    foot_height_gain: float = 0.05        # 1/s, double-support foot height difference per metre of CoP error rate
    foot_height_time_constant: float = 0.05  # s
    foot_height_max: float = 0.0005       # m
    foot_force_gain: float = 3e-5         # m/(N s), loop 4 on the per-foot forces (0: on the CoP)
    foot_cop_gain: float = 1.0            # rad/(m s), double-support per-foot CoP damping
    foot_cop_min_force: float = 150.0     # N
    foot_force_max_speed_kmh: float = 1.5  # km/h, loops 4 (forces) and 5 only in walks up to this speed
    swing_tilt_compensation: bool = True  # keep the swing foot on its path under the stance ankle offsets
    swing_tilt_ramp: float = 0.03         # s, that correction's ramp-in after the lift-off
    swing_tilt_min_speed_kmh: float = 0.75  # km/h, that correction only in walks faster than this
    swing_tilt_pitch_only: bool = False   # correct for the ankle pitch offsets only
    swing_tilt_ds_hold: bool = False      # in the double support held on the landing foot (False: faded out)
    heading_lateral_gain: float = 0.5     # rad/m, path heading correction per metre of lateral drift
    steer_max_per_step: float = 0.0175    # rad, largest heading correction added to one planned step
    steer_filter_time: float = 0.4        # s, low-pass of the measured heading drift
    steer_enabled: bool = True            # IMU heading / lateral drift steering of the footsteps
    velocity_fraction: float = 0.9
    knee_margin: float = 0.1              # rad
    hip_extension_margin: float = 0.02    # rad

    @classmethod
    def from_params(cls, d: dict[str, Any] | None = None) -> LocomotionConfig:
        """From a locomotion parameter dict (defaults: ``params.defaults("locomotion")``); unknown keys
        are refused, missing ones take the declared default."""
        values = params.defaults("locomotion")
        if d:
            values.update(params.check_overrides("locomotion", d))
        cfg = params.config_from(cls, values, "locomotion", ignore=tuple(NODE_ONLY))
        if cfg.resume_stance not in RESUME_STANCES:
            raise params.ParamError(f"locomotion: resume_stance must be one of {', '.join(RESUME_STANCES)}, "
                                    f"got {cfg.resume_stance!r}")
        if cfg.double_support >= cfg.step_period:
            raise params.ParamError("locomotion: double_support must be shorter than step_period")
        if 0 < cfg.fast_step_period <= cfg.double_support:
            raise params.ParamError("locomotion: double_support must be shorter than fast_step_period")
        return cfg

    def step_period_for(self, speed: float) -> float:
        """The step period [s] of a walk at ``speed`` [m/s]: ``fast_step_period`` above ``fast_step_speed_kmh``
        (when set), else ``step_period``."""
        if self.fast_step_period > 0 and speed * 3.6 > self.fast_step_speed_kmh + 1e-9:
            return self.fast_step_period
        return self.step_period

    def single_support_for(self, speed: float) -> float:
        """T_ss [s] at ``speed`` [m/s]."""
        return self.step_period_for(speed) - self.double_support

    @property
    def single_support(self) -> float:
        """T_ss [s]."""
        return self.step_period - self.double_support

    @property
    def max_speed(self) -> float:
        """[m/s]."""
        return self.max_speed_kmh / 3.6

    @property
    def max_turn_rate(self) -> float:
        """[rad/s]."""
        return math.radians(self.max_turn_rate_deg_s)


__all__ = ["LocomotionConfig"]
