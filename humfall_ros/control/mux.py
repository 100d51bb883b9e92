"""Joint command arbitration, like twist_mux: the highest-priority live source wins.

A source is live while its latest command is non-empty, no older than
``timeout`` (sim seconds) and not from the future (a command stamped after the
current time belongs to a timeline that a reset ended). An empty command (no joint names) is a release: the
source yields without waiting for the timeout. Commands may name a subset of
the joints; the others keep their previous targets.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np


@dataclasses.dataclass
class JointCommand:
    stamp: float                  # sim time the command was computed for
    names: list[str]
    positions: list[float]
    velocities: list[float] = dataclasses.field(default_factory=list)


class CommandMux:
    def __init__(self, sources: list[str], joint_names: list[str], timeout: float):
        if len(set(sources)) != len(sources):
            raise ValueError("command sources must be unique")
        self.sources = list(sources)            # highest priority first
        self.index = {n: i for i, n in enumerate(joint_names)}
        self.timeout = timeout
        self.latest: dict[str, JointCommand | None] = {s: None for s in sources}

    def update(self, source: str, cmd: JointCommand) -> None:
        self.latest[source] = cmd

    def clear(self) -> None:
        """Forget every command (the world was reset: they were for the old timeline)."""
        self.latest = {s: None for s in self.sources}

    def active(self, t: float) -> str | None:
        for s in self.sources:
            cmd = self.latest[s]
            # live: computed for a tick that has happened, at most `timeout` ago
            if cmd is not None and cmd.names and -1e-9 <= t - cmd.stamp <= self.timeout + 1e-9:
                return s
        return None

    def targets(self, t: float, positions: np.ndarray, velocities: np.ndarray):
        """(active source or None, position targets, velocity targets) at sim time t."""
        s = self.active(t)
        if s is None:
            return None, positions, velocities
        cmd = self.latest[s]
        q = np.array(positions, dtype=float)
        v = np.array(velocities, dtype=float) if cmd.velocities else np.zeros_like(q)
        for i, n in enumerate(cmd.names):
            j = self.index[n]
            q[j] = cmd.positions[i]
            if cmd.velocities:
                v[j] = cmd.velocities[i]
        return s, q, v


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
