"""Paper 3's ZMP/CoG state-space models, their gains and closed-form responses. No rclpy, no simulator.

Both axes share the LIPM (eq. 1) ``p = x - xddot / omega_c^2`` and the first-order ZMP lag
(eq. 2) ``d pbar/dt = omega_f (p - pbar)``: ``pbar`` is the ZMP the stabilised robot is
expected to realise, ``p`` the generated CoG's own (LIPM) ZMP; the input is the CoG
acceleration.

* **Minor axis** (eq. 3-7): state ``[pbar_x, x, xdot]``, feedback ``xddot = -k . state``
  (eq. 4 with zero references), characteristic polynomial ``D_x`` (eq. 5). The closed-form
  response is the Heaviside expansion of ``(sI - A_cl)^-1 X(0)``; its numerator polynomials
  (eq. 6-7) are our own derivation (``test_estop_statespace`` re-derives them with sympy).
  The printed eq. 7 has two errors: ``C_x4 = -k_x1`` (printed ``+k_x1``) and ``C_x5``'s
  ``s`` coefficient is ``-omega_f k_x1/omega_c^2 + k_x3 + omega_f`` (printed with the
  opposite sign). Gains come from pole placement by matching eq. 5's coefficients (linear in
  ``k``; tested against ``scipy.signal.place_poles``), the poles from an optimal regulator
  (``scipy.linalg.solve_continuous_are``) at a nominal CoG height.
* **Major axis** (eq. 8-16): relative state ``[r, ydot]`` with ``r = y - pbar_y`` (eq. 8, 9),
  feedback ``yddot = -k_y1 r - k_y2 ydot`` (eq. 12), characteristic ``D_y`` (eq. 13); with
  ``pbar_y(0) = 0`` (the origin of the stop frame) the responses are eq. 14-16:
  ``pbar_y(t) = n1 e^(alpha t) + n2 e^(beta t) + n3``. Gains from the poles by eq. 19-20.

Units: positions [m], velocities [m/s], rates and poles [1/s].
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from humfall_ros.dynamics.pendulum import GRAVITY


class StateSpaceError(ValueError):
    """Parameters for which the model is undefined (omega_f == omega_c, repeated poles, ...)."""


def omega_of_height(cog_height: float, g: float = GRAVITY) -> float:
    """Natural angular frequency of the LIPM omega_c = sqrt(g / z_c) [1/s] (eq. 1)."""
    if not cog_height > 0:
        raise StateSpaceError(f"CoG height must be > 0, got {cog_height}")
    return math.sqrt(g / cog_height)


# --------------------------------------------------------------------------- modal form
@dataclasses.dataclass(frozen=True)
class ModalResponse:
    """Outputs ``y_j(t) = constant_j + Re(sum_i coefficients[j, i] exp(rates[i] t))``.

    Attributes:
        rates: the modes' exponents (the closed-loop poles) [1/s], (m,), complex.
        coefficients: residues per output and mode, (n_out, m), complex.
        constant: the final value per output (the residue at s = 0, if any), (n_out,).
    """

    rates: np.ndarray
    coefficients: np.ndarray
    constant: np.ndarray

    def __call__(self, t) -> np.ndarray:
        """Outputs at times ``t`` [s] (scalar or (k,)): (n_out,) or (n_out, k)."""
        t = np.asarray(t, float)
        if t.ndim == 0:
            return (self.coefficients @ np.exp(self.rates * float(t))).real + self.constant
        e = np.exp(np.multiply.outer(self.rates, t.ravel()))   # (m, k) complex
        out = (self.coefficients @ e).real + self.constant[:, None]
        return out.reshape((-1,) + t.shape)

    def derivative(self, order: int = 1) -> ModalResponse:
        """The response of the time derivative (the constant drops)."""
        return ModalResponse(self.rates, self.coefficients * self.rates ** order, np.zeros_like(self.constant))

    def combine(self, weights) -> ModalResponse:
        """Linear combination of the outputs: ``weights`` (n_new, n_out)."""
        W = np.asarray(weights, float)
        return ModalResponse(self.rates, W @ self.coefficients, W @ self.constant)


def _residue_response(num_coeffs: np.ndarray, den_roots, constant_root: bool) -> ModalResponse:
    """Heaviside expansion of N_j(s) / D(s) with distinct roots of D (plus a root at 0 if ``constant_root``).

    ``num_coeffs``: (n_out, deg+1) numerator polynomials, highest power first.
    ``den_roots``: the roots of the monic D without the root at 0.
    """
    roots = [complex(r) for r in den_roots]
    scale = max(1.0, max(abs(r) for r in roots))
    num = np.asarray(num_coeffs, float)
    rows = num.tolist()
    coefficients = np.empty((len(rows), len(roots)), complex)
    for i, lam in enumerate(roots):
        dprime = lam if constant_root else 1.0 + 0j    # D'(lam) of the monic (s) D(s)
        for j, other in enumerate(roots):
            if j != i:
                if abs(lam - other) < 1e-6 * scale:
                    raise StateSpaceError(f"repeated poles {roots}: the closed form needs distinct poles")
                dprime *= lam - other
        for o, row in enumerate(rows):
            value = 0j
            for c in row:                              # Horner
                value = value * lam + c
            coefficients[o, i] = value / dprime
    if constant_root:
        prod = 1.0 + 0j
        for r in roots:
            if abs(r) < 1e-12:
                raise StateSpaceError("a pole at 0 next to the integrator")
            prod *= -r
        constant = (num[:, -1] / prod).real
    else:
        constant = np.zeros(num.shape[0])
    return ModalResponse(np.array(roots, complex), coefficients, constant)


# --------------------------------------------------------------------------- Minor axis
@dataclasses.dataclass(frozen=True)
class MinorAxisModel:
    """Eq. 3: state ``[pbar_x, x, xdot]``, input ``xddot``.

    Attributes:
        omega_c: LIPM natural frequency [1/s].
        omega_f: ZMP lag cut-off (eq. 2) [1/s].
    """

    omega_c: float
    omega_f: float

    @property
    def A(self) -> np.ndarray:
        a = self.omega_f
        return np.array([[-a, a, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, 0.0]])

    @property
    def B(self) -> np.ndarray:
        return np.array([[-self.omega_f / self.omega_c ** 2], [0.0], [1.0]])

    def characteristic(self, k) -> np.ndarray:
        """Coefficients of D_x(s) (eq. 5), highest power first, for gains ``k`` (3,)."""
        k1, k2, k3 = (float(v) for v in k)
        a, w = self.omega_f, self.omega_c ** 2
        return np.array([1.0, -a * k1 / w + k3 + a, k2 + k3 * a, (k1 + k2) * a])

    def gains_for_poles(self, poles) -> np.ndarray:
        """Gains ``k`` (3,) whose D_x (eq. 5) has roots ``poles`` (3, closed under conjugation).

        D_x's coefficients are affine in ``k``: matching them is a 3 x 3 linear solve (tested
        against ``scipy.signal.place_poles``).
        """
        p1, p2, p3 = (complex(p) for p in poles)
        d2 = -(p1 + p2 + p3).real                      # (s - p1)(s - p2)(s - p3) = s^3 + d2 s^2 + d1 s + d0
        d1 = (p1 * p2 + p1 * p3 + p2 * p3).real
        d0 = -(p1 * p2 * p3).real
        a, w = self.omega_f, self.omega_c ** 2
        # -a/w k1 + k3 = d2 - a ; k2 + a k3 = d1 ; a (k1 + k2) = d0
        k3 = (d2 - a + (d0 - a * d1) / w) / (1.0 - a * a / w) if abs(1.0 - a * a / w) > 1e-12 else math.nan
        k2 = d1 - a * k3
        k1 = d0 / a - k2
        if not math.isfinite(k3):
            raise StateSpaceError("omega_f == omega_c: the Minor-axis gains are undefined")
        return np.array([k1, k2, k3])

    def closed_loop(self, k) -> np.ndarray:
        return self.A - self.B @ np.asarray(k, float).reshape(1, 3)

    def numerators(self, k, state0) -> np.ndarray:
        """Numerators of [Pbar_x(s), X(s), Xdot(s)] over D_x(s) for initial ``state0`` (eq. 6-7, derived).

        Rows of adj(sI - A_cl) times the initial state; returns (3, 3) coefficients, highest
        power first (the third row is the velocity, which eq. 6-7 do not print).
        """
        k1, k2, k3 = (float(v) for v in k)
        a, w = self.omega_f, self.omega_c ** 2
        p0, x0, v0 = (float(v) for v in state0)
        # adj(sI - A_cl) entries as polynomials in s (our derivation; sympy in the test)
        C = [[[1.0, k3, k2], [0.0, a * k2 / w + a, k3 * a], [0.0, a * k3 / w, a * k2 / w + a]],
             [[0.0, 0.0, -k1], [1.0, -a * k1 / w + k3 + a, k3 * a], [0.0, 1.0, -a * k1 / w + a]],
             [[0.0, -k1, 0.0], [0.0, -k2, -(k1 + k2) * a], [1.0, -a * k1 / w + a, 0.0]]]
        C = np.array(C)
        return C[:, 0] * p0 + C[:, 1] * x0 + C[:, 2] * v0

    def response(self, k, state0, poles=None) -> ModalResponse:
        """Closed-form [pbar_x, x, xdot](t) from ``state0`` (eq. 6-7 by residues); distinct poles.

        ``poles``: the roots of D_x if known (those the gains were placed at), else found here.
        """
        poles = np.roots(self.characteristic(k)) if poles is None else poles
        return _residue_response(self.numerators(k, state0), poles, constant_root=False)


def lqr_poles(model: MinorAxisModel, weights, r: float) -> np.ndarray:
    """Closed-loop poles of the optimal regulator of eq. 3 (``solve_continuous_are``).

    Args:
        model: the Minor-axis model at the nominal CoG height.
        weights: state weights ``Q = diag(q_pbar, q_x, q_xdot)`` [1/m^2, 1/m^2, s^2/m^2].
        r: input weight ``R`` [s^4/m^2].
    Returns:
        the three poles [1/s] (sorted by real part; a conjugate pair stays a pair).
    """
    from scipy.linalg import solve_continuous_are

    Q = np.diag(np.asarray(weights, float))
    R = np.array([[float(r)]])
    P = solve_continuous_are(model.A, model.B, Q, R)
    K = np.linalg.solve(R, model.B.T @ P)
    poles = np.linalg.eigvals(model.A - model.B @ K)
    return poles[np.argsort(poles.real)]


# --------------------------------------------------------------------------- Major axis
@dataclasses.dataclass(frozen=True)
class MajorAxisModel:
    """Eq. 9: relative state ``[r, ydot]`` (``r = y - pbar_y``, eq. 8), input ``yddot``."""

    omega_c: float
    omega_f: float

    def __post_init__(self):
        if abs(self.omega_f - self.omega_c) < 1e-9 * self.omega_c:
            raise StateSpaceError("omega_f == omega_c: eq. 19-20 are singular")

    @property
    def A(self) -> np.ndarray:
        return np.array([[-self.omega_f, 1.0], [0.0, 0.0]])

    @property
    def B(self) -> np.ndarray:
        return np.array([[self.omega_f / self.omega_c ** 2], [1.0]])

    def characteristic(self, k) -> np.ndarray:
        """Coefficients of D_y(s) (eq. 13), highest power first."""
        k1, k2 = (float(v) for v in k)
        a, w = self.omega_f, self.omega_c ** 2
        return np.array([1.0, a + a * k1 / w + k2, k1 + k2 * a])

    def gains_for_poles(self, alpha: float, beta: float) -> np.ndarray:
        """``[k_y1, k_y2]`` placing the roots of D_y at ``alpha``, ``beta`` (eq. 19-20)."""
        a, w = self.omega_f, self.omega_c ** 2
        den = 1.0 - w / a ** 2
        k1 = -w * (1.0 + (alpha + beta) / a + alpha * beta / a ** 2) / den           # eq. 19
        k2 = (w * (alpha + beta) / a ** 2 + (w + alpha * beta) / a) / den            # eq. 20
        return np.array([k1, k2])

    def numerators(self, k, y0: float, ydot0: float) -> np.ndarray:
        """Numerators of [Pbar_y, Y, Ydot](s) over H(s) = s D_y(s) (eq. 14-15; Ydot's over D_y times s)."""
        k1, k2 = (float(v) for v in k)
        a, w = self.omega_f, self.omega_c ** 2
        c_y1 = np.array([0.0, a * k1 / w + a, k2 * a])
        c_y2 = np.array([0.0, a * k2 / w, a * k1 / w + a])
        c_y3 = np.array([1.0, a * k1 / w + a + k2, k2 * a])
        c_y4 = np.array([0.0, 1.0, a * k1 / w + a])
        # Ydot(s) = (-k1 r0 + (s + a + a k1/w) ydot0) / D_y, written over s D_y
        c_v = np.array([1.0, a + a * k1 / w, 0.0]) * ydot0 + np.array([0.0, -k1 * y0, 0.0])
        return np.array([c_y1 * y0 + c_y2 * ydot0, c_y3 * y0 + c_y4 * ydot0, c_v])

    def response(self, k, y0: float, ydot0: float, poles=None) -> ModalResponse:
        """Closed-form [pbar_y, y, ydot](t) with pbar_y(0) = 0 (eq. 16 and its CoG counterpart).

        ``poles``: the roots of D_y if known, else found here.
        """
        poles = np.roots(self.characteristic(k)) if poles is None else poles
        return _residue_response(self.numerators(k, y0, ydot0), poles, constant_root=True)


@dataclasses.dataclass(frozen=True)
class MajorAxisSolution:
    """Eq. 16: ``pbar_y(t) = n1 e^(alpha t) + n2 e^(beta t) + n3`` and the CoG counterpart.

    Attributes:
        alpha, beta: the poles [1/s].
        gains: ``[k_y1, k_y2]`` (eq. 19-20).
        n: ``(n1, n2, n3)`` of the filtered ZMP pbar_y [m]; n3 is also the final CoG (eq. 21).
        m: the CoG's mode coefficients ``(m1, m2, n3)`` [m].
        response: [pbar_y, y, ydot](t).
    """

    alpha: float
    beta: float
    gains: np.ndarray
    n: tuple[float, float, float]
    m: tuple[float, float, float]
    response: ModalResponse

    @property
    def n3(self) -> float:
        return self.n[2]


def solve_major(model: MajorAxisModel, alpha: float, beta: float, y0: float, ydot0: float) -> MajorAxisSolution:
    """Gains (eq. 19-20) and the closed-form response (eq. 16) for poles ``alpha != beta`` (real, < 0)."""
    if not (alpha < 0 and beta < 0) or abs(alpha - beta) < 1e-9:
        raise StateSpaceError(f"need distinct negative poles, got alpha={alpha}, beta={beta}")
    k = model.gains_for_poles(alpha, beta)
    resp = model.response(k, y0, ydot0, poles=(alpha, beta))
    coeffs = resp.coefficients
    n = (float(coeffs[0, 0].real), float(coeffs[0, 1].real), float(resp.constant[0]))
    m = (float(coeffs[1, 0].real), float(coeffs[1, 1].real), float(resp.constant[1]))
    return MajorAxisSolution(float(alpha), float(beta), k, n, m, resp)


def lipm_zmp(response: ModalResponse, omega_c: float) -> ModalResponse:
    """The generated CoG's own LIPM ZMP ``p = y - yddot / omega_c^2`` (eq. 1) from [pbar, y, ydot]."""
    y = response.combine([[0.0, 1.0, 0.0]])
    ydd = response.combine([[0.0, 0.0, 1.0]]).derivative()
    return ModalResponse(y.rates, y.coefficients - ydd.coefficients / omega_c ** 2, y.constant)


def supremum_two_modes(c0: float, c1: float, r1: float, c2: float, r2: float) -> tuple[float, float]:
    """(max, min) over t >= 0 of ``c0 + c1 e^(r1 t) + c2 e^(r2 t)`` (real, r1 != r2 < 0), in closed form.

    Candidates: t = 0, t -> inf, and the one stationary point ``c1 r1 e^(r1 t) = -c2 r2 e^(r2 t)``.
    """
    vals = [c0 + c1 + c2, c0]
    if c1 != 0.0 and c2 != 0.0:
        ratio = -c2 * r2 / (c1 * r1)
        if ratio > 0:
            t = math.log(ratio) / (r1 - r2)
            if t > 0:
                vals.append(c0 + c1 * math.exp(r1 * t) + c2 * math.exp(r2 * t))
    return max(vals), min(vals)


def return_home(theta0, theta_dot0, t_b: float, t) -> tuple[np.ndarray, np.ndarray]:
    """Joint stop of §V (eq. 23): position and velocity at ``t`` [s] (clamped to [0, T_b]).

    ``theta(t) = theta0 + thd0 t - thd0 t^2 / T_b + thd0 t^3 / (3 T_b^2)`` reaches zero velocity
    and zero acceleration at ``T_b`` [s], at ``theta0 + thd0 T_b / 3``.
    """
    th0 = np.asarray(theta0, float)
    thd0 = np.asarray(theta_dot0, float)
    if not t_b > 0:
        return th0.copy(), np.zeros_like(thd0)
    tc = min(max(float(t), 0.0), t_b)
    pos = th0 + thd0 * (tc - tc ** 2 / t_b + tc ** 3 / (3.0 * t_b ** 2))
    vel = thd0 * (1.0 - tc / t_b) ** 2
    return pos, vel


def stop_duration_within_limits(theta0, theta_dot0, lower, upper, t_b: float) -> float:
    """The largest T_b' <= ``t_b`` whose eq. 23 end point ``theta0 + thd0 T_b'/3`` stays in [lower, upper].

    Eq. 23 is monotonic (velocity ``thd0 (1 - t/T_b)^2`` never changes sign), so the end point
    is the extreme. A joint already outside its limits gives 0 (stop at once).
    """
    th0 = np.asarray(theta0, float)
    thd0 = np.asarray(theta_dot0, float)
    room = np.where(thd0 > 0, np.asarray(upper, float) - th0, th0 - np.asarray(lower, float))
    speed = np.abs(thd0)
    with np.errstate(divide="ignore", invalid="ignore"):
        limit = np.where(speed > 1e-12, 3.0 * np.maximum(room, 0.0) / speed, math.inf)
    return float(min(t_b, float(np.min(limit)) if len(limit) else t_b))


def fit_zmp_lag(t, zmp_reference, cop) -> tuple[float, float]:
    """Fit eq. 2's cut-off ``omega_f`` [1/s] to executed CoP against the reference ZMP (one axis).

    Least squares over omega_f of the simulated first-order lag ``dpbar/dt = omega_f (p_ref - pbar)``
    (exact zero-order-hold discretisation per sample, ``pbar(0) = cop(0)``) against the measured
    CoP; scipy's bounded scalar minimiser over log omega_f in [0.5, 500].

    Args:
        t: sample times [s], (n,), increasing.
        zmp_reference: reference ZMP along one axis [m], (n,).
        cop: executed CoP along that axis [m], (n,).
    Returns:
        (omega_f [1/s], RMS residual [m]).
    """
    from scipy.optimize import minimize_scalar

    t = np.asarray(t, float)
    ref = np.asarray(zmp_reference, float)
    meas = np.asarray(cop, float)
    if not (len(t) == len(ref) == len(meas) >= 3) or np.any(np.diff(t) <= 0):
        raise ValueError("fit_zmp_lag needs >= 3 increasing samples of equal length")
    dt = np.diff(t)

    def simulate(omega: float) -> np.ndarray:
        decay = np.exp(-omega * dt)
        out = np.empty_like(meas)
        out[0] = meas[0]
        for i in range(1, len(t)):
            out[i] = ref[i - 1] + (out[i - 1] - ref[i - 1]) * decay[i - 1]
        return out

    def cost(log_omega: float) -> float:
        e = simulate(math.exp(log_omega)) - meas
        return float(e @ e)

    res = minimize_scalar(cost, bounds=(math.log(0.5), math.log(500.0)), method="bounded",
                          options={"xatol": 1e-6})
    omega = math.exp(res.x)
    return omega, math.sqrt(cost(res.x) / len(t))


__all__ = ["MajorAxisModel", "MajorAxisSolution", "MinorAxisModel", "ModalResponse", "StateSpaceError",
           "fit_zmp_lag", "lipm_zmp", "lqr_poles", "omega_of_height", "return_home", "solve_major",
           "stop_duration_within_limits", "supremum_two_modes"]
