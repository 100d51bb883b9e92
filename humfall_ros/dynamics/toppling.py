"""Toppling pendulums of paper 1 (§III-A): control duration, the state at its end, the spherical case.

A robot whose CoP sits on an edge of its support polygon rotates about that edge:
a 2-D inverted pendulum from the edge to the CoM G, lean angle theta from the
vertical, positive when G is beyond the edge (outside the polygon), theta < 0
while G is still behind it. With mass m, pivot distance L and inertia I about the
pivot (a point mass: I = m L^2),

    I theta'' = m g L sin(theta),        E = 1/2 I theta'^2 + m g L cos(theta)   (energy, constant)

and the crest energy is E_c = m g L (G straight above the edge, at rest). We write
e = E / E_c and omega0^2 = m g L / I.

**Time to a lean angle (the control duration).** With the substitution
psi = pi/2 - theta/2 the time from theta0 to theta1 (theta increasing) is an
incomplete elliptic integral of the first kind F(phi | m) = ``scipy.special.ellipkinc``
(the derivation is checked with sympy in ``test/test_toppling.py``):

* over the crest (e >= 1), m = 2 / (e + 1) <= 1:
  ``t = sqrt(m) / omega0 * (F(pi/2 - theta0/2 | m) - F(pi/2 - theta1/2 | m))``
* below the crest (e < 1) the same integral has m > 1; the reciprocal-modulus
  transformation (DLMF 19.7.4) gives, with m' = (e + 1) / 2 and
  sin(beta) = cos(theta/2) / sqrt(m'), ``t = (F(beta0 | m') - F(beta1 | m')) / omega0``;
  beta = pi/2 at the turning point theta_t = arccos(e).

Whether the pendulum reaches the threshold at all (``FallOutcome``): G behind the
edge and moving towards it falls only over the crest (e > 1), else it swings back
("never falls", never a NaN); G beyond the edge and moving back falls (after a
turning point) only below the crest (e < 1); G exactly on the crest at rest, or any
state exactly on the separatrix e = 1 that approaches the crest, takes an infinite
time (``CREST``).

**theta_threshold** is the lean at which the fall controller's work must be done
(paper 1 §III-A1: the controller is active until the lean crosses it). It is an
argument here; the controller's default is in ``config/safe_fall_controller.yaml``.

**Velocity at the end of the duration**: eq. 3, theta'(dT) = sqrt(2E/I - 2 m g L cos(theta(dT)) / I).

**Spherical pendulum** (CoP at a corner): a point mass on a rigid massless rod
about the corner, integrated in Cartesian coordinates (no singularity at the
vertical, where the toppling starts) with ``scipy.integrate.solve_ivp``; the
batched fixed-step version :func:`spherical_rk4` is what the per-tick decision
uses (measured speed; tested against solve_ivp).
"""
from __future__ import annotations

import dataclasses
import enum
import math

import numpy as np
from scipy.integrate import solve_ivp
from scipy.special import ellipk, ellipkinc

from humfall_ros.dynamics.pendulum import GRAVITY

CREST_TOLERANCE = 1e-12   # |e - 1| below this is the separatrix itself


class FallOutcome(enum.Enum):
    """Does the toppling pendulum reach the threshold lean?"""

    FALLS = "falls"                # reaches it in a finite time
    NEVER_FALLS = "never_falls"    # swings back onto the support side first
    CREST = "crest"                # on the separatrix towards the crest: infinite time


@dataclasses.dataclass(frozen=True)
class ToppleTime:
    """Result of :func:`time_to_lean`.

    Attributes:
        outcome: whether the threshold is reached.
        time: time to reach ``theta_end`` [s] (``math.inf`` unless FALLS; 0 if already beyond).
        theta_end: the threshold lean [rad].
        theta_dot_end: lean rate when reaching it, eq. 3 [rad/s] (NaN unless FALLS).
        energy_ratio: e = E / (m g L) [-].
    """

    outcome: FallOutcome
    time: float
    theta_end: float
    theta_dot_end: float
    energy_ratio: float


def energy_ratio(theta, theta_dot, length, inertia_ratio=1.0, g: float = GRAVITY):
    """e = E / E_crest of the 2-D pendulum (vectorised).

    Args:
        theta: lean from the vertical, + beyond the edge [rad].
        theta_dot: lean rate [rad/s].
        length: pivot-to-CoM distance L [m].
        inertia_ratio: I / (m L^2) [-] (1 for a point mass).
    """
    theta = np.asarray(theta, float)
    return inertia_ratio * length * np.asarray(theta_dot, float) ** 2 / (2.0 * g) + np.cos(theta)


def separatrix_margin(theta, theta_dot, e):
    """Signed energy distance to the separatrix e = 1, positive inside the forward-falling region.

    The forward-falling region of the inverted pendulum is {e > 1, theta' > 0} U {e < 1, theta > 0}
    (towards theta -> +, i.e. over the edge); the margin |e - 1| with that sign is continuous
    in (theta, theta') and zero exactly on the separatrix (vectorised).
    """
    theta = np.asarray(theta, float)
    theta_dot = np.asarray(theta_dot, float)
    e = np.asarray(e, float)
    falls = ((e > 1.0) & (theta_dot > 0.0)) | ((e < 1.0) & (theta > 0.0)) | ((theta > 0.0) & (theta_dot >= 0.0))
    return np.where(falls, 1.0, -1.0) * np.abs(e - 1.0)


def lean_rate(theta, energy, mass, length, inertia, g: float = GRAVITY):
    """Eq. 3: theta' = sqrt(2E/I - 2 m g L cos(theta) / I) [rad/s] (the forward root; 0 at a turning point)."""
    arg = 2.0 * energy / inertia - 2.0 * mass * g * length * np.cos(theta) / inertia
    return np.sqrt(np.maximum(arg, 0.0))


def time_to_lean(theta0: float, theta_dot0: float, theta_end: float, length: float,
                 inertia_ratio: float = 1.0, g: float = GRAVITY) -> ToppleTime:
    """Control duration: time for the 2-D pendulum to lean from theta0 to theta_end (elliptic form).

    Args:
        theta0: initial lean about the edge [rad] (< 0: CoM still behind the edge).
        theta_dot0: initial lean rate [rad/s] (> 0: towards the edge and beyond).
        theta_end: threshold lean theta_threshold [rad], in (0, pi).
        length: pivot-to-CoM distance L [m].
        inertia_ratio: I / (m L^2) [-].

    Returns:
        ToppleTime (never NaN in ``time``; ``math.inf`` when the threshold is not reached).
    """
    if not 0.0 < theta_end < math.pi:
        raise ValueError(f"theta_end must be in (0, pi), got {theta_end}")
    omega0 = math.sqrt(g / (length * inertia_ratio))
    e = float(energy_ratio(theta0, theta_dot0, length, inertia_ratio, g))
    mass_free_energy = e * g * length  # E / m
    inertia = inertia_ratio * length * length  # I / m

    def rate_end() -> float:
        return float(lean_rate(theta_end, mass_free_energy, 1.0, length, inertia, g))

    if theta0 >= theta_end and theta_dot0 >= 0.0:
        return ToppleTime(FallOutcome.FALLS, 0.0, theta_end, float(theta_dot0), e)
    on_crest = abs(e - 1.0) < CREST_TOLERANCE
    if theta_dot0 >= 0.0:
        if theta0 < 0.0 or (theta0 == 0.0 and theta_dot0 == 0.0):
            if on_crest or (theta0 == 0.0 and theta_dot0 == 0.0):
                return ToppleTime(FallOutcome.CREST, math.inf, theta_end, math.nan, e)
            if e < 1.0:
                return ToppleTime(FallOutcome.NEVER_FALLS, math.inf, theta_end, math.nan, e)
        backward_first = False
    else:
        if theta0 <= 0.0:
            return ToppleTime(FallOutcome.NEVER_FALLS, math.inf, theta_end, math.nan, e)
        if on_crest:
            return ToppleTime(FallOutcome.CREST, math.inf, theta_end, math.nan, e)
        if e > 1.0:
            return ToppleTime(FallOutcome.NEVER_FALLS, math.inf, theta_end, math.nan, e)
        backward_first = True
    if e >= 1.0:
        m = 2.0 / (e + 1.0)
        t = math.sqrt(m) / omega0 * (ellipkinc(math.pi / 2 - theta0 / 2, m) - ellipkinc(math.pi / 2 - theta_end / 2, m))
    else:
        mp = (e + 1.0) / 2.0
        s = math.sqrt(mp)

        def beta(th: float) -> float:
            return math.asin(min(1.0, math.cos(th / 2) / s))

        b0, b1 = beta(theta0), beta(theta_end)
        if backward_first:
            t = (2.0 * ellipk(mp) - ellipkinc(b0, mp) - ellipkinc(b1, mp)) / omega0
        else:
            t = (ellipkinc(b0, mp) - ellipkinc(b1, mp)) / omega0
    return ToppleTime(FallOutcome.FALLS, float(t), theta_end, rate_end(), e)


@dataclasses.dataclass(frozen=True)
class EdgePendulum:
    """The 2-D pendulum of a CoM about a horizontal pivot line.

    Attributes:
        pivot: the point of the line nearest the CoM's ground projection [m], (3,).
        normal: horizontal unit outward normal of the line (the fall direction) [-], (3,).
        theta: lean about the line [rad] (+ beyond it).
        theta_dot: lean rate [rad/s].
        length: pivot-to-CoM distance in the normal plane [m].
        energy_ratio: e = E / E_crest [-].
    """

    pivot: np.ndarray
    normal: np.ndarray
    theta: float
    theta_dot: float
    length: float
    energy_ratio: float

    def com_at(self, theta: float) -> np.ndarray:
        """CoM position [m] when the pendulum leans ``theta`` (motion in the normal plane only)."""
        return self.pivot + self.length * (math.sin(theta) * self.normal + math.cos(theta) * np.array([0, 0, 1.0]))

    def com_velocity_at(self, theta: float, theta_dot: float) -> np.ndarray:
        """CoM velocity [m/s] at lean ``theta`` and rate ``theta_dot``."""
        return self.length * theta_dot * (math.cos(theta) * self.normal - math.sin(theta) * np.array([0, 0, 1.0]))


def edge_pendulum(com, com_velocity, point, normal, g: float = GRAVITY) -> EdgePendulum:
    """The 2-D pendulum of (G, dG/dt) about the horizontal line through ``point`` with outward ``normal``.

    The motion along the line is dropped: a body rotating about a fixed line moves no point along it.
    """
    com = np.asarray(com, float)
    vel = np.asarray(com_velocity, float)
    n = np.array([normal[0], normal[1], 0.0], float)
    n /= np.linalg.norm(n)
    p = np.asarray(point, float).copy()
    p[2] = 0.0 if len(point) < 3 else p[2]
    along = np.array([-n[1], n[0], 0.0])
    rel = com - p
    pivot = p + along * float(rel @ along)
    d = float(rel @ n)
    h = float(rel[2])
    length = math.hypot(d, h)
    theta = math.atan2(d, h)
    theta_dot = (float(vel @ n) * h - float(vel[2]) * d) / (length * length)
    e = float(energy_ratio(theta, theta_dot, length, 1.0, g))
    return EdgePendulum(pivot, n, theta, theta_dot, length, e)


# ------------------------------------------------------------------ spherical pendulum
def _spherical_rhs(_t, y, g):
    r, v = y[:3], y[3:]
    lam = (g * r[2] - v @ v) / (r @ r)   # rod force per unit mass / L, keeps |r| constant
    return np.concatenate([v, np.array([0.0, 0.0, -g]) + lam * r])


@dataclasses.dataclass(frozen=True)
class SphericalResult:
    """Spherical pendulum run (positions relative to the pivot).

    Attributes:
        time: time reached [s] (the threshold crossing, or the duration asked for).
        position: CoM relative to the pivot at ``time`` [m], (3,).
        velocity: CoM velocity at ``time`` [m/s], (3,).
        reached_threshold: the lean reached ``theta_threshold`` before the duration.
    """

    time: float
    position: np.ndarray
    velocity: np.ndarray
    reached_threshold: bool

    @property
    def lean(self) -> float:
        """Lean from the vertical at ``time`` [rad]."""
        return math.atan2(math.hypot(self.position[0], self.position[1]), self.position[2])


def simulate_spherical(r0, v0, duration: float, theta_threshold: float | None = None, g: float = GRAVITY,
                       rtol: float = 1e-10, atol: float = 1e-12) -> SphericalResult:
    """Point mass on a rigid rod about a corner (paper 1 §III-A), ``solve_ivp`` with a lean event.

    Args:
        r0: CoM relative to the pivot corner [m], (3,).
        v0: CoM velocity [m/s], (3,); its radial part is removed (the rod is rigid).
        duration: longest time to simulate [s].
        theta_threshold: stop when the lean reaches it [rad] (None: run the whole duration).
    """
    r0 = np.asarray(r0, float)
    v0 = np.asarray(v0, float)
    v0 = v0 - r0 * (v0 @ r0) / (r0 @ r0)
    events = None
    if theta_threshold is not None:
        c = math.cos(theta_threshold)

        def lean_event(_t, y, g):
            return y[2] - c * math.sqrt(y[:3] @ y[:3])

        lean_event.terminal = True
        lean_event.direction = -1
        events = lean_event
    sol = solve_ivp(_spherical_rhs, (0.0, duration), np.concatenate([r0, v0]), args=(g,), rtol=rtol, atol=atol,
                    events=events, method="DOP853")
    hit = bool(events is not None and sol.t_events[0].size > 0)
    y = sol.y_events[0][0] if hit else sol.y[:, -1]
    t = float(sol.t_events[0][0]) if hit else float(sol.t[-1])
    return SphericalResult(t, y[:3].copy(), y[3:].copy(), hit)


def spherical_rk4(r0, v0, duration, steps: int = 8, g: float = GRAVITY) -> tuple[np.ndarray, np.ndarray]:
    """Batched spherical pendulums at a fixed time: classic RK4, ``steps`` steps (one per case).

    Used by the per-tick decision where ``solve_ivp``'s Python overhead (~1 ms a case) would not fit;
    ``test_toppling`` checks it against :func:`simulate_spherical` (8 steps over 0.45 s: 5 um, 0.1 mm/s).
    The rod length is restored at the end (the constraint drifts by O(dt^5)). The decision has 3
    cases: written on Python floats (measured 0.04 ms for 3 cases against 0.3 ms as numpy (k, 6)
    arrays, whose per-call overhead dominates at this size); the same arithmetic, per component.

    Args:
        r0: CoM relative to each pivot [m], (k, 3).
        v0: CoM velocities [m/s], (k, 3) (radial parts removed).
        duration: time [s], scalar or (k,).
    Returns:
        (positions (k, 3), velocities (k, 3)) at ``duration``.
    """
    r0 = np.array(r0, float, ndmin=2)
    v0 = np.array(v0, float, ndmin=2)
    k = len(r0)
    dur = np.broadcast_to(np.asarray(duration, float), (k,)).tolist()
    R = np.empty((k, 3))
    V = np.empty((k, 3))
    for i, ((x, y, z), (vx, vy, vz)) in enumerate(zip(r0.tolist(), v0.tolist())):
        l2 = x * x + y * y + z * z
        vr = (vx * x + vy * y + vz * z) / l2
        vx, vy, vz = vx - x * vr, vy - y * vr, vz - z * vr
        il2 = 1.0 / l2
        dt = dur[i] / steps
        h2, h6 = 0.5 * dt, dt / 6.0
        for _ in range(steps):
            # a = lam r - g z_hat with lam = (g z - |v|^2) / L^2 (rod force per unit mass, keeps |r| = L)
            lam = (g * z - (vx * vx + vy * vy + vz * vz)) * il2
            a1x, a1y, a1z = lam * x, lam * y, lam * z - g
            x2, y2, z2 = x + h2 * vx, y + h2 * vy, z + h2 * vz
            u2x, u2y, u2z = vx + h2 * a1x, vy + h2 * a1y, vz + h2 * a1z
            lam = (g * z2 - (u2x * u2x + u2y * u2y + u2z * u2z)) * il2
            a2x, a2y, a2z = lam * x2, lam * y2, lam * z2 - g
            x3, y3, z3 = x + h2 * u2x, y + h2 * u2y, z + h2 * u2z
            u3x, u3y, u3z = vx + h2 * a2x, vy + h2 * a2y, vz + h2 * a2z
            lam = (g * z3 - (u3x * u3x + u3y * u3y + u3z * u3z)) * il2
            a3x, a3y, a3z = lam * x3, lam * y3, lam * z3 - g
            x4, y4, z4 = x + dt * u3x, y + dt * u3y, z + dt * u3z
            u4x, u4y, u4z = vx + dt * a3x, vy + dt * a3y, vz + dt * a3z
            lam = (g * z4 - (u4x * u4x + u4y * u4y + u4z * u4z)) * il2
            a4x, a4y, a4z = lam * x4, lam * y4, lam * z4 - g
            x, y, z = (x + h6 * (vx + 2.0 * (u2x + u3x) + u4x), y + h6 * (vy + 2.0 * (u2y + u3y) + u4y),
                       z + h6 * (vz + 2.0 * (u2z + u3z) + u4z))
            vx, vy, vz = (vx + h6 * (a1x + 2.0 * (a2x + a3x) + a4x), vy + h6 * (a1y + 2.0 * (a2y + a3y) + a4y),
                          vz + h6 * (a1z + 2.0 * (a2z + a3z) + a4z))
        sc = math.sqrt(l2 / (x * x + y * y + z * z))
        x, y, z = x * sc, y * sc, z * sc
        vr = (vx * x + vy * y + vz * z) / l2
        R[i] = (x, y, z)
        V[i] = (vx - x * vr, vy - y * vr, vz - z * vr)
    return R, V


__all__ = ["CREST_TOLERANCE", "EdgePendulum", "FallOutcome", "SphericalResult", "ToppleTime", "edge_pendulum",
           "energy_ratio", "lean_rate", "separatrix_margin", "simulate_spherical", "spherical_rk4", "time_to_lean"]
