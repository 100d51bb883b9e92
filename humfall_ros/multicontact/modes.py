"""Contact modes and environment surfaces (paper 2, Sec. III-A and Fig. 2).

A contact mode sigma is the set of extremities in contact, written like the
paper's figures: ``"LF/RF/LH"``. The planar environment has the ground (z = 0)
and optionally a vertical wall x = wall_x facing the robot. Feet always touch
the ground; hands touch the wall when there is one (the pushed robot meets it
first) and the ground otherwise.
"""
from __future__ import annotations

import dataclasses
import math

from humfall_ros.multicontact.model import EXTREMITIES, FEET

Mode = tuple  # canonical: extremities in EXTREMITIES order


def make_mode(extremities) -> Mode:
    s = set(extremities)
    return tuple(e for e in EXTREMITIES if e in s)


def one_foot_alone(mode: Mode) -> bool:
    """Only one foot in contact: a support the planar model balances in the sagittal plane alone, while a
    3-D robot there also needs a lateral weight shift the plan does not have (docs/multicontact.md,
    "Session 27"; the planner's ``single_foot_modes``)."""
    return len(mode) == 1 and mode[0] in FEET


def is_foot_landing(change: str, extremity: str) -> bool:
    """A transition that puts a foot down: the landing half of a protective step (its own T_min,
    ``OptConfig.step_t_min``; the capture cost of ``step_capture_weight``; the executor's touchdown switch)."""
    return change == "add" and extremity in FEET


def mode_label(mode: Mode) -> str:
    return "/".join(mode) if mode else "-"


def parse_mode(text: str) -> Mode:
    """``"LF/RF"`` -> ("LF", "RF"); raises ValueError naming an unknown extremity."""
    parts = [p.strip() for p in str(text).replace(",", "/").split("/") if p.strip()]
    unknown = [p for p in parts if p not in EXTREMITIES]
    if unknown:
        raise ValueError(f"unknown extremity {unknown[0]!r} (known: {', '.join(EXTREMITIES)})")
    if len(set(parts)) != len(parts):
        raise ValueError(f"extremity repeated in mode {text!r}")
    if not parts:
        raise ValueError("empty contact mode: at least one extremity must be in contact")
    return make_mode(parts)


def adjacent_modes(mode: Mode) -> list[tuple[Mode, str, str]]:
    """Modes differing from ``mode`` by exactly one extremity (Fig. 2).

    Returns (mode, 'add'|'remove', extremity). Additions come first (they can
    take energy out through the impact), then removals. The empty mode (the
    robot in flight) is not a neighbour.
    """
    out = []
    for e in EXTREMITIES:
        if e not in mode:
            out.append((make_mode(mode + (e,)), "add", e))
    for e in mode:
        rest = tuple(x for x in mode if x != e)
        if rest:
            out.append((rest, "remove", e))
    return out


@dataclasses.dataclass(frozen=True)
class Environment:
    """Ground z = 0 plus an optional wall, the plane x = wall_x (None: no wall)."""

    wall_x: float | None = None

    @property
    def has_wall(self) -> bool:
        return self.wall_x is not None and math.isfinite(self.wall_x)

    def surface_of(self, extremity: str) -> str:
        if extremity in FEET or not self.has_wall:
            return "ground"
        return "wall"

    @staticmethod
    def from_distance(wall_distance: float) -> Environment:
        """Request convention: wall_distance <= 0 means no wall."""
        return Environment(float(wall_distance) if wall_distance and wall_distance > 0 else None)


def strategy_of(sequence) -> str:
    """The paper's name (Sec. IV-B) for a plan's contact sequence (labels like ``"LF/RF"``, first the start).

    "inertial shaping": no contact change; "protective step": a foot lands that was not in the mode before it
    (from two feet that is a release and a landing; from one foot, as the paper's trees start, one landing);
    "hand contact": a hand lands; both: "protective step + hand contact". A sequence that only lifts a foot and
    stops on the other adds no contact: "foot lifted" (the issue's "no new contact", not one of the paper's names).
    """
    modes = [set(str(m).split("/")) for m in sequence]
    if not modes:
        return "none"
    added = set().union(*(b - a for a, b in zip(modes, modes[1:]))) if len(modes) > 1 else set()
    steps = bool(added & set(FEET))
    hands = bool(added - set(FEET))
    if steps and hands:
        return "protective step + hand contact"
    if hands:
        return "hand contact"
    if steps:
        return "protective step"
    return "inertial shaping" if len(modes) == 1 else "foot lifted"
