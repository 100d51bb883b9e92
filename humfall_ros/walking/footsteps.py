"""Footstep plans from a walking command (forward speed, yaw rate). No rclpy.

A plan walks a path frame ``(x, y, heading)`` forward: every step advances it by
``stride = speed * step_period`` [m] along the mean heading of the step and turns it by
``yaw_rate * step_period`` [rad]. Footstep ``j`` sits at path pose ``P_j`` offset by half the
step width to its side. Starting with the feet side by side at ``P_0``, the first swing (the
*start step*) moves a foot ``stride`` ahead; later swings move ``2 * stride`` (from behind
the stance foot to ahead of it); the *stop step* brings the last swing foot beside the other
(it moves ``stride``). The double-support distance between the feet is therefore ``stride``.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from humfall_ros.model.humanoid import HumanoidModel


@dataclasses.dataclass(frozen=True)
class WalkCommand:
    """A walking command: forward speed [m/s] and yaw rate [rad/s] (REP 103: +z, to the left);
    ``n_steps``: walk that many steps, then stop (None: until a zero command)."""

    speed: float = 0.0
    yaw_rate: float = 0.0
    n_steps: int | None = None

    @property
    def is_zero(self) -> bool:
        return abs(self.speed) < 1e-6 and abs(self.yaw_rate) < 1e-6


@dataclasses.dataclass(frozen=True)
class Footstep:
    """Where a sole lands: ``side`` "l"/"r", sole-frame position (x, y) [m] and yaw [rad] (world)."""

    side: str
    x: float
    y: float
    yaw: float
    index: int = 0
    stop: bool = False

    @property
    def position(self) -> np.ndarray:
        return np.array([self.x, self.y])


def other(side: str) -> str:
    return "r" if side == "l" else "l"


def step_width(model: HumanoidModel) -> float:
    """Lateral distance between the feet [m]: the hip spacing of the model (feet under the hips)."""
    y = [model.model.jointPlacements[model.model.getJointId(f"{s}_hip_yaw")].translation[1] for s in ("l", "r")]
    return float(abs(y[0] - y[1]))


def path_advance(pose: tuple[float, float, float], stride: float, turn: float) -> tuple[float, float, float]:
    """Next path pose: advance ``stride`` [m] along the mid heading, turn ``turn`` [rad]."""
    x, y, h = pose
    mid = h + turn / 2
    return x + stride * math.cos(mid), y + stride * math.sin(mid), h + turn


def footstep_at(pose, side: str, width: float, index: int, stop: bool = False) -> Footstep:
    x, y, h = pose
    s = 1.0 if side == "l" else -1.0
    return Footstep(side, x - s * width / 2 * math.sin(h), y + s * width / 2 * math.cos(h), h, index, stop)


def first_swing_side(command: WalkCommand) -> str:
    """The foot that leaves first: the one on the side of the turn (it opens the turn), else the right."""
    return "l" if command.yaw_rate > 1e-6 else "r"


def plan_footsteps(start_pose: tuple[float, float, float], command: WalkCommand, n_steps: int, step_period: float,
                   width: float, first_side: str | None = None) -> list[Footstep]:
    """``n_steps`` footsteps (the first is the start step) then the stop step, from the feet side by
    side about ``start_pose`` = (x, y, heading) [m, m, rad].

    Returns ``n_steps + 1`` footsteps: distance walked ``n_steps * speed * step_period`` [m]."""
    if n_steps < 1:
        raise ValueError("a walk needs at least one step")
    side = first_side or first_swing_side(command)
    stride = command.speed * step_period
    turn = command.yaw_rate * step_period
    pose = start_pose
    steps = []
    for j in range(1, n_steps + 1):
        pose = path_advance(pose, stride, turn)
        steps.append(footstep_at(pose, side, width, j))
        side = other(side)
    steps.append(footstep_at(pose, side, width, n_steps + 1, stop=True))
    return steps


__all__ = ["Footstep", "WalkCommand", "first_swing_side", "footstep_at", "other", "path_advance", "plan_footsteps",
           "step_width"]
