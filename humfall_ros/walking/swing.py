"""Swing-foot trajectories. No rclpy.

Horizontal position and yaw follow a minimum-jerk profile s(tau) = 10 tau^3 - 15 tau^4 + 6 tau^5
over the single-support phase (zero velocity and acceleration at lift-off and touchdown); the
height is ``apex * sin^2(pi tau)`` (zero velocity at both ends, ``apex`` [m] at mid-swing, a quick
first clearance so the toe does not scuff). tau = t / T_ss in [0, 1].
"""
from __future__ import annotations

import math

import numpy as np


def min_jerk(tau: float) -> tuple[float, float]:
    """(s, ds/dtau) of the minimum-jerk profile, tau clipped to [0, 1]."""
    t = min(max(tau, 0.0), 1.0)
    return t ** 3 * (10 - 15 * t + 6 * t * t), 30 * t * t * (1 - t) ** 2


def swing_foot(start: np.ndarray, end: np.ndarray, yaw0: float, yaw1: float, apex: float, tau: float,
               duration: float) -> tuple[np.ndarray, float, np.ndarray, float]:
    """Swing foot sole at phase ``tau``: (position (3,) [m], yaw [rad], velocity (3,) [m/s], yaw rate [rad/s]).

    ``start``/``end``: sole positions (3,) at lift-off and touchdown [m]; ``duration``: T_ss [s].
    """
    s, ds = min_jerk(tau)
    t = min(max(tau, 0.0), 1.0)
    start = np.asarray(start, float)
    end = np.asarray(end, float)
    pos = start + s * (end - start)
    vel = ds / duration * (end - start)
    sp = math.sin(math.pi * t)
    pos[2] = start[2] + s * (end[2] - start[2]) + apex * sp * sp
    vel[2] += apex * 2 * sp * math.cos(math.pi * t) * math.pi / duration
    dyaw = math.remainder(yaw1 - yaw0, 2 * math.pi)
    return pos, yaw0 + s * dyaw, vel, ds / duration * dyaw


__all__ = ["min_jerk", "swing_foot"]
