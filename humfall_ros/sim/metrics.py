"""Ground-truth run metrics: did the robot fall, where, and how close to the target.

Avoidance angle (paper 1, Fig. 5): the angle at the initial CoP P between the
fall direction (P to the CoM's ground projection when the trunk lands) and
P to the target T: 0 deg falls onto the target, 180 deg straight away.
"""
from __future__ import annotations

import math

import numpy as np

FALL_TRUNK_TILT = math.radians(45.0)   # trunk tilt beyond which the robot has fallen
FALL_WAIST_HEIGHT = 0.35               # m; waist below this: fallen


def angle_between_deg(a, b) -> float:
    a = np.asarray(a, float)[:2]
    b = np.asarray(b, float)[:2]
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    if na < 1e-9 or nb < 1e-9:
        return float("nan")
    return math.degrees(math.acos(float(np.clip(a @ b / (na * nb), -1.0, 1.0))))


def avoidance_angle_deg(cop, landing_com, target) -> float:
    """Angle at P between P->G_landing and P->T (paper 1, Fig. 5)."""
    p = np.asarray(cop, float)[:2]
    return angle_between_deg(np.asarray(landing_com, float)[:2] - p, np.asarray(target, float)[:2] - p)


class FallMetrics:
    """Accumulates ground-truth facts tick by tick."""

    def __init__(self, target_xy=None):
        self.target_xy = None if target_xy is None else np.asarray(target_xy, float)[:2]
        self.initial_cop = None
        self.fell = False
        self.fall_time = None
        self.landing_com = None
        self.landing_time = None
        self.min_target_distance = math.inf
        self.max_trunk_tilt = 0.0
        self.last_com = None

    def set_reference_cop(self, cop) -> None:
        """The P of Fig. 5: the CoP when the disturbance begins."""
        if self.initial_cop is None and cop is not None:
            self.initial_cop = np.asarray(cop, float)[:2].copy()

    def update(self, t: float, com, trunk_tilt: float, waist_height: float, target_distance: float | None,
               non_foot_contact: bool) -> None:
        com = np.asarray(com, float)
        self.last_com = com
        self.max_trunk_tilt = max(self.max_trunk_tilt, trunk_tilt)
        if target_distance is not None:
            self.min_target_distance = min(self.min_target_distance, target_distance)
        if not self.fell and (trunk_tilt > FALL_TRUNK_TILT or waist_height < FALL_WAIST_HEIGHT):
            self.fell = True
            self.fall_time = t
        # the trunk "meets the ground" (or an object): first non-foot contact once falling
        if self.landing_com is None and non_foot_contact and (self.fell or trunk_tilt > math.radians(20)):
            self.landing_com = com.copy()
            self.landing_time = t

    def result(self) -> dict:
        land = self.landing_com if self.landing_com is not None else self.last_com
        out = {
            "fell": bool(self.fell),
            "fall_time_s": self.fall_time,
            "landing_time_s": self.landing_time,
            "max_trunk_tilt_deg": math.degrees(self.max_trunk_tilt),
            "fall_direction_deg": None,
            "avoidance_angle_deg": None,
            "min_target_distance_m": None if not math.isfinite(self.min_target_distance)
            else round(float(self.min_target_distance), 4),
            "initial_cop": None if self.initial_cop is None else [float(x) for x in self.initial_cop],
            "landing_com": None if land is None else [float(x) for x in land],
        }
        if self.fell and self.initial_cop is not None and land is not None:
            d = land[:2] - self.initial_cop
            out["fall_direction_deg"] = math.degrees(math.atan2(d[1], d[0]))
            if self.target_xy is not None:
                out["avoidance_angle_deg"] = avoidance_angle_deg(self.initial_cop, land, self.target_xy)
        return out
