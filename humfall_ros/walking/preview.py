"""Preview control of the ZMP on the cart-table model (Kajita et al., ICRA 2003). No rclpy.

Model (per horizontal axis, sampling time ``dt`` [s], CoM height ``z_c`` [m])::

    x_{k+1} = A x_k + B u_k,   x = [c, dc/dt, d2c/dt2],  u = d3c/dt3 (jerk)
    p_k     = C x_k,           C = [1, 0, -z_c / g]      (the cart-table ZMP)

    A = [[1, dt, dt^2/2], [0, 1, dt], [0, 0, 1]],  B = [dt^3/6, dt^2/2, dt]

Cost (the servo form with integral action, Katayama et al. 1985 as used by Kajita 2003)::

    J = sum_k  Q_e (p_k - p_ref_k)^2 + Q_x ||x_{k+1} - x_k||^2 + R (u_k - u_{k-1})^2

on the augmented incremental state ``[e_k, Δx_k]`` (4 states). ``scipy.linalg.solve_discrete_are``
gives P; the control is::

    u_k = -G_i sum_{i<=k} (p_i - p_ref_i) - G_x x_k - sum_{j=1..N} G_p(j) p_ref_{k+j}

with the preview gains G_p(j) from the closed-loop recursion (Katayama's result). The horizon is
``N = round(horizon / dt)`` samples. The gains depend on ``z_c``: :meth:`set_com_height`
recomputes them when it changes.
"""
from __future__ import annotations

import dataclasses
import functools
import math

import numpy as np
import scipy.linalg

from humfall_ros.dynamics.pendulum import GRAVITY


@dataclasses.dataclass(frozen=True)
class PreviewGains:
    """Gains of one (dt, z_c, horizon, weights).

    Attributes:
        gi: integral gain G_i [1/(m s^3)], scalar.
        gx: state gain G_x (3,).
        gp: preview gains G_p(1..N) (N,) [1/(m s^3)].
        com_height: z_c [m]; dt [s].
    """

    gi: float
    gx: np.ndarray
    gp: np.ndarray
    com_height: float
    dt: float


def cart_table(dt: float, com_height: float, g: float = GRAVITY) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(A (3x3), B (3,), C (3,)) of the discrete cart-table model (module docstring)."""
    A = np.array([[1.0, dt, dt * dt / 2], [0.0, 1.0, dt], [0.0, 0.0, 1.0]])
    B = np.array([dt ** 3 / 6, dt * dt / 2, dt])
    C = np.array([1.0, 0.0, -com_height / g])
    return A, B, C


@functools.lru_cache(maxsize=16)
def preview_gains(dt: float, com_height: float, horizon: float, q_e: float = 1.0, q_x: float = 0.0,
                  r: float = 1e-6) -> PreviewGains:
    """Preview-control gains (Kajita 2003 / Katayama 1985) from the discrete Riccati equation.

    Cached by argument (a replan at the same CoM height reuses them; a new height computes new ones)."""
    A, B, C = cart_table(dt, com_height)
    At = np.zeros((4, 4))
    At[0, 0] = 1.0
    At[0, 1:] = C @ A
    At[1:, 1:] = A
    Bt = np.concatenate([[C @ B], B]).reshape(4, 1)
    Q = np.diag([q_e, q_x, q_x, q_x])
    R = np.array([[r]])
    P = scipy.linalg.solve_discrete_are(At, Bt, Q, R)
    S = float(R[0, 0] + (Bt.T @ P @ Bt)[0, 0])
    K = (Bt.T @ P @ At).ravel() / S
    gi, gx = float(K[0]), K[1:].copy()
    Ac = At - Bt @ K.reshape(1, 4)
    It = np.array([1.0, 0.0, 0.0, 0.0])
    n = round(horizon / dt)
    gp = np.empty(n)
    X = -Ac.T @ P @ It
    gp[0] = -gi
    BtT = Bt.ravel() / S
    for j in range(1, n):
        gp[j] = BtT @ X
        X = Ac.T @ X
    return PreviewGains(gi, gx, gp, float(com_height), float(dt))


class PreviewController:
    """Online preview control of the ZMP, both horizontal axes (x, y) at once.

    Args:
        dt: control period [s]; com_height: z_c [m]; horizon: preview time [s] (>= 1.6 s by default
            config); q_e, q_x, r: cost weights (module docstring).

    ``state`` is (3, 2): rows c, dc/dt, d2c/dt2 [m, m/s, m/s^2], columns x and y.
    """

    def __init__(self, dt: float, com_height: float, horizon: float, q_e: float = 1.0, q_x: float = 0.0,
                 r: float = 1e-6):
        self.dt, self.horizon = float(dt), float(horizon)
        self.q_e, self.q_x, self.r = q_e, q_x, r
        self.gains = preview_gains(dt, com_height, horizon, q_e, q_x, r)
        self.A, self.B, self.C = cart_table(dt, com_height)
        self.state = np.zeros((3, 2))
        self.error_sum = np.zeros(2)

    @property
    def com_height(self) -> float:
        return self.gains.com_height

    @property
    def n_preview(self) -> int:
        return len(self.gains.gp)

    @property
    def omega(self) -> float:
        """sqrt(g / z_c) [1/s]."""
        return math.sqrt(GRAVITY / self.com_height)

    def set_com_height(self, com_height: float, tolerance: float = 1e-6) -> bool:
        """Recompute the gains for a new z_c [m]; True if they were recomputed."""
        if abs(com_height - self.com_height) <= tolerance:
            return False
        self.gains = preview_gains(self.dt, com_height, self.horizon, self.q_e, self.q_x, self.r)
        self.A, self.B, self.C = cart_table(self.dt, com_height)
        return True

    def reset(self, com_xy, com_velocity_xy=(0.0, 0.0), com_acceleration_xy=(0.0, 0.0)) -> None:
        """Start from a CoM state; the integral of the ZMP error restarts at 0."""
        self.state = np.array([com_xy, com_velocity_xy, com_acceleration_xy], float).reshape(3, 2)
        self.error_sum = np.zeros(2)

    def zmp(self) -> np.ndarray:
        """Cart-table ZMP of the current state [m] (2,)."""
        return self.C @ self.state

    def step(self, zmp_ref_now, zmp_ref_future) -> np.ndarray:
        """Advance one period. ``zmp_ref_now`` (2,) is p_ref_k, ``zmp_ref_future`` (N, 2) holds
        p_ref_{k+1..k+N}; returns the new state (3, 2)."""
        g = self.gains
        self.error_sum += self.C @ self.state - np.asarray(zmp_ref_now, float)
        u = -g.gi * self.error_sum - g.gx @ self.state - g.gp @ zmp_ref_future
        self.state = self.A @ self.state + np.outer(self.B, u)
        return self.state

    def rollout(self, zmp_ref: np.ndarray) -> np.ndarray:
        """Run the controller over a whole reference (K + N, 2) from the current state (which is
        kept); returns the states (K, 3, 2) for k = 1..K. For offline checks and the benchmark."""
        zmp_ref = np.asarray(zmp_ref, float)
        n = self.n_preview
        k_total = len(zmp_ref) - n
        if k_total <= 0:
            raise ValueError(f"the reference must be longer than the preview ({n} samples)")
        saved = self.state.copy(), self.error_sum.copy()
        # the feed-forward sum over the preview, for every k at once (a correlation)
        windows = np.lib.stride_tricks.sliding_window_view(zmp_ref[1:], n, axis=0)[:k_total]  # (K, 2, N)
        ff = windows @ self.gains.gp  # (K, 2)
        out = np.empty((k_total, 3, 2))
        g = self.gains
        x, es = self.state, self.error_sum
        for k in range(k_total):
            es = es + self.C @ x - zmp_ref[k]
            u = -g.gi * es - g.gx @ x - ff[k]
            x = self.A @ x + np.outer(self.B, u)
            out[k] = x
        self.state, self.error_sum = saved
        return out


__all__ = ["PreviewController", "PreviewGains", "cart_table", "preview_gains"]
