"""Sanity limits of a push (no pybullet): shared by the scenario schema, the PyBullet world and the bridge's
``sim/push`` service, so a push refused in one place is refused in all of them.
"""
from __future__ import annotations

import math
from collections.abc import Sequence

MAX_PUSH_FORCE = 5000.0        # [N]; anything above is a typo, not a push
MAX_PUSH_DURATION = 10.0       # [s]
MAX_PUSH_POINT_OFFSET = 2.0    # [m] from the link origin


def validate_push(force: Sequence[float], point: Sequence[float], duration: float) -> str | None:
    """None if the push is sane, else the reason it is refused.

    Args:
        force: force in the world frame [N], 3 numbers.
        point: application point in the link frame [m], 3 numbers.
        duration: how long the force acts [s].
    """
    vals = [float(v) for v in (*force, *point, duration)]
    if not all(math.isfinite(v) for v in vals):
        return "push has a non-finite value (NaN or inf)"
    mag = math.hypot(*(float(f) for f in force))
    if mag > MAX_PUSH_FORCE:
        return f"push force {mag:.0f} N exceeds the {MAX_PUSH_FORCE:.0f} N limit"
    if duration <= 0 or duration > MAX_PUSH_DURATION:
        return f"push duration {duration} s must be in (0, {MAX_PUSH_DURATION:g}]"
    if math.hypot(*(float(p) for p in point)) > MAX_PUSH_POINT_OFFSET:
        return f"push application point is more than {MAX_PUSH_POINT_OFFSET:g} m from the link origin"
    return None
