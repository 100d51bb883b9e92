"""Joint command arbitration, like twist_mux, for lockstep controllers that take over.

Sources are ordered by priority (highest first: safe_fall > estop > locomotion).
A source **engages** with its first non-empty command and stays engaged until it
sends an empty one (no joint names: a **release**). The highest-priority engaged
source drives the robot:

* its command is used while it is live (stamped for a tick that has happened, at
  most ``timeout`` sim seconds ago);
* if it goes silent while engaged (free-run: a slow or dead controller), the mux
  **holds** the last targets and says so: it never hands a robot that a fall
  controller or the e-stop took over back to a lower source on a timeout. In
  lockstep every source answers every tick, so that only happens after the
  bridge's stall timeout.

Commands may name a subset of the joints; the others keep their previous targets.
Refused (with a reason, never applied): a command stamped for a tick that has not
happened, and a second, different answer to a tick a source already answered (the
first one stands; an identical resend is a harmless duplicate).
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

STAMP_EPS = 1e-9  # s: stamps are integer nanoseconds
# Mux priorities of the built-in sources (higher wins): safe_fall > estop > locomotion.
DEFAULT_PRIORITIES = {"locomotion": 10, "estop": 20, "safe_fall": 30}


@dataclasses.dataclass
class JointCommand:
    stamp: float                  # sim time [s] the command was computed for
    names: list[str]
    positions: list[float]
    velocities: list[float] = dataclasses.field(default_factory=list)

    @property
    def is_release(self) -> bool:
        return not self.names

    def same_content(self, other: "JointCommand") -> bool:
        return (self.names == other.names and list(self.positions) == list(other.positions)
                and list(self.velocities) == list(other.velocities))


@dataclasses.dataclass(frozen=True)
class MuxDecision:
    """Who drives the robot for the coming tick.

    Attributes:
        source: the engaged source with the highest priority, or None (nobody engaged).
        holding: that source is silent (no live command): the robot holds its last targets.
    """

    source: str | None
    holding: bool = False


class CommandMux:
    """Priority arbitration of joint commands (see the module docstring).

    Args:
        sources: source names, highest priority first.
        joint_names: the model's joint order.
        timeout: sim seconds a command stays live.
    """

    def __init__(self, sources: list[str], joint_names: list[str], timeout: float):
        if len(set(sources)) != len(sources):
            raise ValueError(f"command sources must be unique: {sources}")
        self.sources = list(sources)
        self.index = {n: i for i, n in enumerate(joint_names)}
        self.timeout = timeout
        self.clear()

    def clear(self) -> None:
        """Forget every command (the world was reset: they were for the old timeline)."""
        self.latest: dict[str, JointCommand | None] = {s: None for s in self.sources}
        self.engaged: dict[str, bool] = {s: False for s in self.sources}

    def update(self, source: str, cmd: JointCommand, now: float) -> str | None:
        """Take a command of ``source`` at sim time ``now``; None if accepted, else why it is refused.

        A duplicate of the tick's accepted answer returns None and changes nothing.
        """
        if source not in self.latest:
            return f"unknown source {source!r}"
        if cmd.stamp > now + STAMP_EPS:
            return f"stamped {cmd.stamp:.6f} s, a tick that has not happened (now {now:.6f} s)"
        prev = self.latest[source]
        if prev is not None and abs(prev.stamp - cmd.stamp) <= STAMP_EPS:
            if prev.same_content(cmd):
                return None
            return f"a second, different answer to tick {cmd.stamp:.6f} s (the first one stands)"
        if prev is not None and cmd.stamp < prev.stamp - STAMP_EPS:
            return f"stamped {cmd.stamp:.6f} s, older than its last command ({prev.stamp:.6f} s)"
        self.latest[source] = cmd
        self.engaged[source] = not cmd.is_release
        return None

    def live(self, source: str, t: float) -> bool:
        cmd = self.latest[source]
        return cmd is not None and not cmd.is_release and -STAMP_EPS <= t - cmd.stamp <= self.timeout + STAMP_EPS

    def decide(self, t: float) -> MuxDecision:
        for s in self.sources:
            if self.engaged[s]:
                return MuxDecision(s, holding=not self.live(s, t))
        return MuxDecision(None)

    def active(self, t: float) -> str | None:
        """The source whose command drives the robot at ``t`` (None when holding or nobody is engaged)."""
        d = self.decide(t)
        return None if d.holding else d.source

    def targets(self, t: float, positions: np.ndarray, velocities: np.ndarray):
        """(decision, position targets, velocity targets) at sim time t.

        Holding, or nobody engaged: the given targets unchanged.
        """
        d = self.decide(t)
        if d.source is None or d.holding:
            return d, positions, velocities
        cmd = self.latest[d.source]
        q = np.array(positions, dtype=float)
        v = np.array(velocities, dtype=float) if cmd.velocities else np.zeros_like(q)
        for i, n in enumerate(cmd.names):
            j = self.index[n]
            q[j] = cmd.positions[i]
            if cmd.velocities:
                v[j] = cmd.velocities[i]
        return d, q, v


def mux_order(sources, priorities: dict[str, int] | None = None) -> list[str]:
    """Source names, highest priority first; ValueError on a tie or a source without a priority."""
    pr = {**DEFAULT_PRIORITIES, **(priorities or {})}
    sources = list(sources)
    missing = [s for s in sources if s not in pr]
    if missing:
        raise ValueError(f"no mux priority for sources {missing}")
    by_priority: dict[int, str] = {}
    for s in sources:
        if pr[s] in by_priority and by_priority[pr[s]] != s:
            raise ValueError(f"sources {by_priority[pr[s]]!r} and {s!r} both claim priority {pr[s]}")
        by_priority[pr[s]] = s
    if len(set(sources)) != len(sources):
        raise ValueError(f"command sources must be unique: {sources}")
    return sorted(sources, key=lambda s: -pr[s])


def validate_command(names, positions, velocities, known) -> str | None:
    """None if a joint command is usable, else why it is refused."""
    if len(positions) != len(names):
        return f"{len(names)} names but {len(positions)} positions"
    if len(velocities) not in (0, len(names)):
        return f"{len(names)} names but {len(velocities)} velocities"
    unknown = [n for n in names if n not in known]
    if unknown:
        return f"unknown joints {unknown[:3]}"
    if len(set(names)) != len(names):
        return "duplicate joint names"
    if not all(math.isfinite(x) for x in list(positions) + list(velocities)):
        return "non-finite value"
    return None


__all__ = ["DEFAULT_PRIORITIES", "CommandMux", "JointCommand", "MuxDecision", "mux_order", "validate_command"]
