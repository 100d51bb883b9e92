"""Is the push still acting? The capture point's residual against the LIPM (ours; paper 1 is silent).

On the linear inverted pendulum the capture point xi = c + c_dot / omega obeys xi_dot = omega (xi - p) with p the
CoP; a horizontal external force F adds F / (m omega):

    r = xi_dot - omega (xi - p) = (c_ddot - omega^2 (c - p)) / omega = F / (m omega)

so r [m/s] reads the push that is still on the robot from the estimator's own outputs (capture point, CoP, CoM
height), without knowing the push. Measured (docs/safe_fall.md, session 9): 2.1-2.3 m/s during a 1.3x standing
push with exact sensors, 0.1-0.15 m/s after it; with ``TYPICAL_NOISE`` a one-tick difference swings by +-3 m/s,
hence the window: xi_dot is the difference over ``window_s``, omega (xi - p) its mean over the same ticks.

The safe-fall controller defers its decision while |r| is large (``defer_push_residual_mps``), so the step is
chosen from the state the push leaves, not from the middle of the push (the FTB fires 12-22 ms before a 1.5x
push ends).
"""
from __future__ import annotations

import collections
import math

import numpy as np

from humfall_ros.dynamics.pendulum import GRAVITY


class PushResidual:
    """A sliding-window estimate of r (module docstring), fed one state per tick."""

    def __init__(self, window_s: float = 0.02):
        if not (window_s > 0.0 and math.isfinite(window_s)):
            raise ValueError(f"window_s must be positive and finite, got {window_s}")
        self.window_s = float(window_s)
        self._buf: collections.deque = collections.deque()

    def reset(self) -> None:
        self._buf.clear()

    def update(self, time_s: float, com, capture_point, cop) -> None:
        """One tick's estimate (world frame, ground z = 0); non-finite states are skipped (never raise)."""
        c = np.asarray(com, float).reshape(-1)
        xi = np.asarray(capture_point, float).reshape(-1)[:2]
        p = np.asarray(cop, float).reshape(-1)[:2]
        if c.size < 3 or not (np.all(np.isfinite(c)) and np.all(np.isfinite(xi)) and np.all(np.isfinite(p))
                              and math.isfinite(time_s)) or c[2] <= 0.0:
            return
        if self._buf and time_s <= self._buf[-1][0]:
            self._buf.clear()   # time went back (a new run): start again
        omega = math.sqrt(GRAVITY / c[2])
        self._buf.append((float(time_s), xi.copy(), omega * (xi - p)))
        while len(self._buf) > 2 and self._buf[1][0] <= time_s - self.window_s + 1e-9:
            self._buf.popleft()

    @property
    def ready(self) -> bool:
        """A full window is held."""
        return len(self._buf) >= 2 and self._buf[-1][0] - self._buf[0][0] >= self.window_s - 1e-9

    def value(self) -> np.ndarray:
        """r [m/s], (2,); NaN until two ticks are held."""
        if len(self._buf) < 2:
            return np.full(2, np.nan)
        t0, xi0, _ = self._buf[0]
        t1, xi1, _ = self._buf[-1]
        # xi_dot over the window against omega (xi - p) by the trapezoid over the same span
        buf = list(self._buf)
        drift = np.sum([0.5 * (a[2] + b[2]) * (b[0] - a[0]) for a, b in zip(buf, buf[1:])], axis=0)
        return ((xi1 - xi0) - drift) / (t1 - t0)

    def magnitude(self) -> float:
        """|r| [m/s] (NaN until two ticks are held)."""
        return float(np.linalg.norm(self.value()))
