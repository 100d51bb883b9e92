"""The walking pattern: timeline of support phases, ZMP reference, preview-controlled CoM, swing feet.

Online, one control tick at a time (no rclpy). The timeline is built step by step from the
walking command and always reaches at least the preview horizon ahead, so a new command (speed,
turn, stop) shapes the steps that start after the horizon (a latency of about two steps, the
price of preview control). Per step: single support of ``T - double_support`` on the
stance foot while the other swings (:mod:`.swing`; ``T = config.step_period_for(speed)``: 0.8 s, 0.7 s above
1.35 km/h by default), then a double support in which the ZMP
reference moves linearly from the stance sole to the new one (a fixed, non-zero duration).
Before the first step: an optional crouch (CoM height from standing to ``com_height``, min-jerk,
ZMP at the feet centre) and a start double support (ZMP onto the first stance foot). After the
stop step: a stop double support (ZMP to the middle of the feet) and a settle hold.

The CoM is the cart-table CoM of :class:`PreviewController` (Kajita 2003) at the constant height
``com_height`` [m]; the ZMP reference of a foot is the centre of its sole rectangle.
"""
from __future__ import annotations

import dataclasses
import enum
import math

import numpy as np

from humfall_ros.walking.config import LocomotionConfig
from humfall_ros.walking.footsteps import (
    Footstep,
    WalkCommand,
    first_swing_side,
    footstep_at,
    other,
    path_advance,
)
from humfall_ros.walking.preview import PreviewController
from humfall_ros.walking.swing import min_jerk, swing_foot


class SupportPhase(enum.Enum):
    DOUBLE = "double"
    SINGLE_LEFT = "single_left"    # the left foot supports, the right swings
    SINGLE_RIGHT = "single_right"


@dataclasses.dataclass
class Phase:
    """One span of the timeline, in control ticks [start, start + ticks)."""

    kind: str                      # "hold", "ds" or "ss"
    start: int
    ticks: int
    zmp0: np.ndarray               # ZMP reference at the start [m] (2,)
    zmp1: np.ndarray               # and at the end
    feet: dict                     # side -> Footstep at the phase start
    step_index: int
    swing_to: Footstep | None = None  # ss: where the swing foot lands
    landing: str | None = None     # ds after a swing: the foot that just landed (it finishes its descent)
    liftoff: float = 0.0           # ds before a swing: the rear foot rises this much at its end [m]; ss: the swing
                                   # foot starts this high

    @property
    def end(self) -> int:
        return self.start + self.ticks

    @property
    def stance(self) -> str | None:
        return other(self.swing_to.side) if self.swing_to is not None else None


@dataclasses.dataclass
class FootState:
    """A sole's reference: position [m] (3,), yaw [rad], velocity [m/s] (3,), yaw rate [rad/s]."""

    position: np.ndarray
    yaw: float
    velocity: np.ndarray
    yaw_rate: float


@dataclasses.dataclass
class PatternSample:
    """The pattern at one tick (world frame of the pattern, ground z = 0)."""

    tick: int
    time: float                    # since the pattern started [s]
    support: SupportPhase
    phase_fraction: float          # in [0, 1) of the current support phase
    step_index: int                # 0 before the first swing, j during/after step j
    com: np.ndarray                # reference CoM [m] (3,)
    com_velocity: np.ndarray       # [m/s] (3,)
    com_acceleration: np.ndarray   # [m/s^2] (3,)
    zmp: np.ndarray                # reference ZMP [m] (3,), z = 0
    capture_point: np.ndarray      # reference capture point c + dc/dt / omega [m] (3,)
    feet: dict                     # side -> FootState
    next_footsteps: list           # upcoming Footsteps, the one in flight first
    kind: str                      # the phase kind ("hold", "ds", "ss")
    finished: bool                 # the stop and settle are over


def sole_zmp(step: Footstep, offset_x: float) -> np.ndarray:
    """The ZMP reference point of a sole [m] (2,): its centre, ``offset_x`` ahead of the sole frame."""
    return np.array([step.x + offset_x * math.cos(step.yaw), step.y + offset_x * math.sin(step.yaw)])


class WalkingPattern:
    """Online walking pattern (see the module docstring).

    Args:
        config: walking settings.
        dt: control period [s].
        width: lateral distance between the feet [m].
        zmp_offset_x: sole centre ahead of the sole frame [m].
        feet: side -> Footstep of the soles now (flat on the ground).
        com: CoM now [m] (3,).
        command: the walking command.
        n_steps: walk this many steps then stop (None: until a zero command).
    """

    def __init__(self, config: LocomotionConfig, dt: float, width: float, zmp_offset_x: float, feet: dict,
                 com, command: WalkCommand, n_steps: int | None = None):
        self.cfg = config
        self.dt = float(dt)
        self.width = float(width)
        self.zmp_offset_x = float(zmp_offset_x)
        self.command = command
        self.steps_left = n_steps
        self.stopping = False
        self.ended = False                 # the timeline is complete (stop planned)
        com = np.asarray(com, float)
        self.preview = PreviewController(dt, config.com_height, config.preview_horizon, config.preview_q, 0.0,
                                         config.preview_r)
        self.preview.reset(com[:2])
        self.z0 = float(com[2])
        self.zc = float(config.com_height)
        self.tick = 0
        self.phases: list[Phase] = []
        self._zmp_chunks: list[np.ndarray] = []
        self._zmp = np.zeros((0, 2))
        self._phase_i = 0
        self._feet_end = dict(feet)        # placements at the end of the planned timeline
        mid = 0.5 * (feet["l"].position + feet["r"].position)
        heading = math.atan2(math.sin(feet["l"].yaw) + math.sin(feet["r"].yaw),
                             math.cos(feet["l"].yaw) + math.cos(feet["r"].yaw))
        self.path_pose = (float(mid[0]), float(mid[1]), heading)
        self.next_swing = first_swing_side(command)
        self.step_count = 0
        # steering (set by the controller from the measured drift): the path of the steps not yet planned
        # turns by up to `steer_max_per_step` per step until its total correction reaches `steer_target`
        self.steer_target = 0.0            # [rad]
        self.steer_total = 0.0             # [rad] applied so far
        self.crouch_ticks = self._ticks(config.crouch_duration) if abs(self.z0 - self.zc) > 0.002 else 0
        center = 0.5 * (sole_zmp(feet["l"], zmp_offset_x) + sole_zmp(feet["r"], zmp_offset_x))
        com_xy = com[:2].copy()
        if self.crouch_ticks:
            self._append(Phase("hold", 0, self.crouch_ticks, com_xy, center, dict(feet), 0))
        first_stance = sole_zmp(feet[other(self.next_swing)], zmp_offset_x)
        self._append(Phase("ds", self._end(), self._ticks(config.start_duration),
                           center if self.crouch_ticks else com_xy, first_stance, dict(feet), 0))
        self._extend()

    # ------------------------------------------------------------------ timeline
    def _ticks(self, seconds: float) -> int:
        return max(1, round(seconds / self.dt))

    def _end(self) -> int:
        return self.phases[-1].end if self.phases else 0

    def _append(self, ph: Phase) -> None:
        self.phases.append(ph)
        a = np.arange(ph.ticks)[:, None] / ph.ticks
        self._zmp_chunks.append(ph.zmp0 + a * (ph.zmp1 - ph.zmp0))

    def _zmp_array(self) -> np.ndarray:
        if self._zmp_chunks:
            self._zmp = np.concatenate([self._zmp, *self._zmp_chunks])
            self._zmp_chunks = []
        return self._zmp

    def set_command(self, command: WalkCommand) -> None:
        """A new command for the steps not yet planned; a zero command plans the stop."""
        if command.is_zero:
            self.stopping = True
        else:
            self.command = command

    def _extend(self) -> None:
        need = self.tick + self.preview.n_preview + 2
        while not self.ended and self._end() < need:
            self._plan_step()
        if self.ended and self._end() < need:  # hold the last ZMP beyond the timeline
            last = self.phases[-1]
            self._append(Phase("hold", last.end, need - last.end + self._ticks(1.0), last.zmp1, last.zmp1,
                               dict(self._feet_end), last.step_index))

    def _plan_step(self) -> None:
        cfg = self.cfg
        feet = dict(self._feet_end)
        side = self.next_swing
        stance_zmp = sole_zmp(feet[other(side)], self.zmp_offset_x)
        stop = self.stopping or (self.steps_left is not None and self.steps_left <= 0)
        self.step_count += 1
        T = cfg.step_period_for(self.command.speed)
        if stop:
            target = footstep_at(self.path_pose, side, self.width, self.step_count, stop=True)
        else:
            d = float(np.clip(self.steer_target - self.steer_total, -cfg.steer_max_per_step, cfg.steer_max_per_step))
            self.steer_total += d
            self.path_pose = path_advance(self.path_pose, self.command.speed * T, self.command.yaw_rate * T + d)
            target = footstep_at(self.path_pose, side, self.width, self.step_count)
            if self.steps_left is not None:
                self.steps_left -= 1
        prev = self.phases[-1] if self.phases else None
        self._append(Phase("ss", self._end(), self._ticks(T - cfg.double_support), stance_zmp, stance_zmp, dict(feet),
                           self.step_count, target, liftoff=prev.liftoff if prev is not None else 0.0))
        feet[side] = target
        self._feet_end = feet
        new_zmp = sole_zmp(target, self.zmp_offset_x)
        if stop:
            center = 0.5 * (new_zmp + stance_zmp)
            self._append(Phase("ds", self._end(), self._ticks(cfg.stop_duration), stance_zmp, center, dict(feet),
                               self.step_count, landing=side))
            self._append(Phase("hold", self._end(), self._ticks(cfg.settle_duration), center, center, dict(feet),
                               self.step_count))
            self.ended = True
            self.finish_tick = self._end()
        else:
            self._append(Phase("ds", self._end(), self._ticks(cfg.double_support), stance_zmp, new_zmp, dict(feet),
                               self.step_count, landing=side, liftoff=cfg.liftoff_height))
            self.next_swing = other(side)

    # ------------------------------------------------------------------ per tick
    def zmp_reference(self, tick: int) -> np.ndarray:
        z = self._zmp_array()
        return z[min(tick, len(z) - 1)]

    def step(self) -> PatternSample:
        """Advance one control tick and return the references at the new tick."""
        self._extend()
        z = self._zmp_array()
        k = self.tick
        n = self.preview.n_preview
        st = self.preview.step(z[k], z[k + 1:k + 1 + n])
        self.tick = k + 1
        return self.sample(st)

    def current_phase(self) -> Phase:
        while self._phase_i + 1 < len(self.phases) and self.phases[self._phase_i].end <= self.tick:
            self._phase_i += 1
        return self.phases[self._phase_i]

    def sample(self, st: np.ndarray | None = None) -> PatternSample:
        """The references at the current tick (``st``: preview state, default the controller's)."""
        st = self.preview.state if st is None else st
        k = self.tick
        ph = self.current_phase()
        frac = min(max((k - ph.start) / ph.ticks, 0.0), 1.0)
        # CoM height: the crouch, then constant
        if self.crouch_ticks and k < self.crouch_ticks:
            s, ds = min_jerk(k / self.crouch_ticks)
            T = self.crouch_ticks * self.dt
            z, vz = self.z0 + s * (self.zc - self.z0), ds / T * (self.zc - self.z0)
        else:
            z, vz = self.zc, 0.0
        com = np.array([st[0, 0], st[0, 1], z])
        vel = np.array([st[1, 0], st[1, 1], vz])
        acc = np.array([st[2, 0], st[2, 1], 0.0])
        omega = self.preview.omega
        cp = np.array([com[0] + vel[0] / omega, com[1] + vel[1] / omega, 0.0])
        feet = {}
        for s_, fs in ph.feet.items():
            feet[s_] = FootState(np.array([fs.x, fs.y, 0.0]), fs.yaw, np.zeros(3), 0.0)
        h = self.cfg.landing_height
        if ph.kind == "ss":
            sw = ph.swing_to
            a = ph.feet[sw.side]
            pos, yaw, v, wz = swing_foot(np.array([a.x, a.y, ph.liftoff]), np.array([sw.x, sw.y, h]), a.yaw, sw.yaw,
                                         self.cfg.swing_apex, frac, ph.ticks * self.dt)
            feet[sw.side] = FootState(pos, yaw, v, wz)
            support = SupportPhase.SINGLE_LEFT if ph.stance == "l" else SupportPhase.SINGLE_RIGHT
        else:
            support = SupportPhase.DOUBLE
            if ph.landing is not None and h > 0:  # the landed foot descends the last landing_height
                T = self.cfg.landing_duration
                s_, ds_ = min_jerk((k - ph.start) * self.dt / T)
                f = feet[ph.landing]
                f.position[2] = h * (1.0 - s_)
                f.velocity[2] = -h * ds_ / T
            if ph.liftoff > 0 and ph.landing is not None:  # the rear foot starts its lift-off at the end
                T = self.cfg.liftoff_duration
                s_, ds_ = min_jerk(((k - ph.start) - (ph.ticks - T / self.dt)) * self.dt / T)
                f = feet[other(ph.landing)]
                f.position[2] = ph.liftoff * s_
                f.velocity[2] = ph.liftoff * ds_ / T
        zr = self.zmp_reference(k)
        upcoming = [p.swing_to for p in self.phases[self._phase_i:] if p.swing_to is not None][:4]
        finished = self.ended and k >= self.finish_tick
        return PatternSample(k, k * self.dt, support, frac if frac < 1.0 else 0.0, ph.step_index, com, vel, acc,
                             np.array([zr[0], zr[1], 0.0]), cp, feet, upcoming, ph.kind, finished)

    # ------------------------------------------------------------------ offline
    def single_support_phase(self, step_count: int) -> Phase:
        """The single support of swing ``step_count`` (1 = the first), planning ahead as needed
        (the timeline does not depend on when it is planned). KeyError if the walk has no such step."""
        while True:
            for ph in self.phases:
                if ph.kind == "ss" and ph.step_index == step_count:
                    return ph
            if self.ended:
                raise KeyError(f"the walk has no step {step_count}")
            self._plan_step()

    def phase_before(self, phase: Phase) -> Phase:
        """The timeline phase that ends where ``phase`` starts (a single support's double support)."""
        for ph in self.phases:
            if ph.end == phase.start:
                return ph
        raise KeyError(f"no phase before tick {phase.start}")

    def planned_footsteps(self) -> list[Footstep]:
        return [p.swing_to for p in self.phases if p.swing_to is not None]


__all__ = ["FootState", "PatternSample", "Phase", "SupportPhase", "WalkingPattern", "sole_zmp"]
