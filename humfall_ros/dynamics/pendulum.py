"""Inverted-pendulum quantities used across the suite.

Paper 1 (safe fall) approximates the toppling robot by a point mass on a
massless leg from the CoP P to the CoM G; its reference point Q is the capture
point (eq. 1-2).
"""
from __future__ import annotations

import math

import numpy as np

GRAVITY = 9.81


def capture_point(com, com_velocity, ground_height: float = 0.0, g: float = GRAVITY) -> np.ndarray:
    """Capture point Q = G_xy + sqrt(z_G / g) * dG_xy/dt  (paper 1, eq. 1-2).

    ``z_G`` is the CoM height above the ground the robot stands on. Returns a
    3-vector on the ground plane.
    """
    com = np.asarray(com, dtype=float)
    vel = np.asarray(com_velocity, dtype=float)
    z = max(com[2] - ground_height, 1e-6)
    omega_inv = math.sqrt(z / g)
    return np.array([com[0] + omega_inv * vel[0], com[1] + omega_inv * vel[1], ground_height])


def lean_angle(com, cop) -> tuple[float, float]:
    """Angle between the P->G line and the vertical, and the heading of P->G on the ground.

    This is the theta of paper 1, Fig. 4. Returns (angle, heading) in radians.
    """
    d = np.asarray(com, dtype=float) - np.asarray(cop, dtype=float)
    horiz = math.hypot(d[0], d[1])
    return math.atan2(horiz, d[2]), math.atan2(d[1], d[0])
