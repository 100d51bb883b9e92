"""The optimal protective step of paper 1 §III-B (eq. 4): brute force over cases and cells.

Cases in double support: no change, lift the left / right foot (and keep it up), step with
the left / right foot to a cell (x, y, beta) of its allowable stepping zone
(``fall.stepping_zone``). In single support (walking): continue the planned step, re-target the
swing foot over the cells, keep it lifted.

Per case, the toppling pendulum predicts the state at touchdown (``touchdown_time`` after the
decision): about the current leading edge (no change: 2-D, the motion along the edge dropped)
or about the stance sole's leading corner (lift / step: the spherical pendulum; the 2-D one
when two corners tie, i.e. the fall is along the sole's axis). Batched fixed-step RK4
(``toppling.spherical_rk4``) for all cases at once. Q2 is the capture point of that state
(eq. 1-2).

**P2 (the paper leaves it undefined; ours):** the point of the candidate's new support polygon
nearest Q2. For Q2 outside the polygon the robot then topples about the edge (or corner)
through P2, along P2->Q2, which is the edge normal there (paper 1 §II-C). The new support
polygon is the hull of the stance sole's pivot corner(s) and the landing sole's four corners
(lift: the pivot corner(s) alone; no change: the current soles' hull).

**Capture:** Q2 inside the new polygon by at least ``capture_margin``: no fall is predicted.
Captures rank above every fall (among them the deepest Q2 wins); falls rank by the avoidance
angle alpha2 = angle(Q2 P2 T) (eq. 4, Fig. 5).

Vectorisation: for N cells everything is evaluated in each cell's sole frame, where the landing
sole is one fixed rectangle and only Q2 and the 1-2 pivots move (``_hull_eval``: a clamp, the
pivot -> corner segments and a separation test); no Python loop over cells.
"""
from __future__ import annotations

import dataclasses
import enum
import itertools
import math
import time

import numpy as np

from humfall_ros.dynamics.pendulum import GRAVITY
from humfall_ros.dynamics.toppling import spherical_rk4
from humfall_ros.fall.geometry import (
    avoidance_angle_xy,
    inside_convex_xy,
    nearest_on_boundary_xy,
    polygon_margin_xy,
    rotation_z,
)
from humfall_ros.fall.stepping_zone import SteppingZone
from humfall_ros.model.humanoid import support_polygon


class StepCase(enum.Enum):
    NO_CHANGE = "no_change"
    LIFT_LEFT = "lift_left"
    LIFT_RIGHT = "lift_right"
    STEP_LEFT = "step_left"
    STEP_RIGHT = "step_right"
    CONTINUE_STEP = "continue_step"   # single support: the planned step
    NO_TARGET = "no_target"           # nothing to avoid: no step

    @property
    def swing(self) -> str | None:
        return {"lift_left": "l", "step_left": "l", "lift_right": "r", "step_right": "r"}.get(self.value)


FALL_RANKINGS = ("paper", "edge")


@dataclasses.dataclass(frozen=True)
class SearchConfig:
    """Grid and model parameters of the search (``config/safe_fall_controller.yaml``).

    Attributes:
        cell_xy: cell size in x and y [m].
        cell_yaw: cell size in beta [rad].
        capture_margin: Q2 this deep inside the new polygon is a capture [m].
        corner_tie: stance corners within this of the leading one along the fall direction pivot as an edge [m].
        obstacle_clearance: landing soles keep this far from obstacle footprints [m].
        rk4_steps: fixed RK4 steps of the pendulum prediction [-].
        min_zone_cells: a zone with fewer (x, y) cells than this is also sampled at half or a quarter
            of the cell size, to hold about this many (0: the grid as it falls) [-].
        capture_depth: among the captures at least this deep, the shortest step ranks first (ours; 0: the
            deepest capture ranks first, which puts the landing at the zone's far edge) [m].
        cop_delay: how long after touchdown the CoP stays on the stance pivot before the balance can move it
            into the new polygon (ours; 0: at once, the paper's capture): Q2 is taken that much later on the
            linear pendulum about the pivot, :func:`delayed_capture_point` [s].
        capture_offset: Q2 is taken this much further along the CoM's horizontal motion at touchdown (ours; 0:
            the paper's Q2): a capture then needs Q2 this deep plus ``capture_margin`` along the motion, and a
            fall's alpha2 is measured from the shifted Q2 (a shallow capture is ranked as the fall it becomes
            when it fails) [m].
        max_step_length: landing cells farther than this from the swing sole's position at the decision are
            left out (ours; 0: none). Measured: longer steps than ~0.43 m miss the prediction (side steps land
            early and up to 24 cm short, long forward steps up to 176 ms late) [m].
        fall_ranking: what predicted falls rank by (eq. 4's alpha2): ``paper`` (paper 1's angle(Q2 P2 T)),
            ``edge`` (ours: the avoidance angle of the fall about the new support's edge or corner,
            :func:`_alpha_edge`) [-]. (The smaller of the two was tried, session 20: it chose what the paper's angle
            chose on every decision measured, that angle being the lower one.)
        fall_heading_horizon: the horizon of :func:`_alpha_edge` for ``edge`` [s].
    """

    cell_xy: float = 0.04
    cell_yaw: float = 0.15
    capture_margin: float = 0.02
    corner_tie: float = 0.01
    obstacle_clearance: float = 0.03
    rk4_steps: int = 8
    min_zone_cells: int = 0
    capture_depth: float = 0.0
    cop_delay: float = 0.0
    capture_offset: float = 0.0
    max_step_length: float = 0.0
    fall_ranking: str = "paper"
    fall_heading_horizon: float = 0.5

    def __post_init__(self):
        if self.fall_ranking not in FALL_RANKINGS:
            raise ValueError(f"fall_ranking {self.fall_ranking!r}: one of {FALL_RANKINGS}")


@dataclasses.dataclass
class Footprint:
    """An obstacle's ground rectangle: centre [m] (2,), half sizes [m] (2,), yaw [rad]."""

    center: np.ndarray
    half_size: np.ndarray
    yaw: float


@dataclasses.dataclass
class FallSituation:
    """What the search needs at the decision (world frame, ground z = 0).

    Attributes:
        com, com_velocity: G [m] and dG/dt [m/s], (3,).
        cop: P1 [m], (3,) or (2,).
        capture_point: Q1 [m].
        leading_edge: (start, end) [m] of the current leading edge (equal points: a corner), (2,) each.
        edge_normal: its outward normal (the fall direction) [-], (2,).
        soles: sole corners per side [m], {"l": (4, 2), "r": (4, 2)} (CCW), the feet as they are now.
        sole_poses: (x, y, yaw) of each sole [m, m, rad].
        target: T [m], (2,), or None.
        touchdown_time: time from the decision to the swing foot's touchdown [s].
        control_duration: dT to theta_threshold about the leading edge [s] (reported).
        zones: allowable stepping zones by swing side ({} in single support without re-targeting).
        obstacles: ground footprints the landing sole must avoid.
        single_support: the stance side while walking ("l"/"r"), None in double support.
        planned_landing: the gait's planned (x, y, yaw) of the swing sole (single support).
        swing_com_gain: by swing side, the CoM's horizontal shift per horizontal move of that sole (2 x 2) [m/m]
            (``HumanoidModel.swing_com_gain``); given, each landing cell's Q2 moves by it times the step (ours:
            the swing leg's mass carried to the landing, which eq. 1-2's rigid pendulum leaves out). {}: the paper.
    """

    com: np.ndarray
    com_velocity: np.ndarray
    cop: np.ndarray
    capture_point: np.ndarray
    leading_edge: tuple[np.ndarray, np.ndarray]
    edge_normal: np.ndarray
    soles: dict
    sole_poses: dict
    target: np.ndarray | None
    touchdown_time: float
    control_duration: float
    zones: dict = dataclasses.field(default_factory=dict)
    obstacles: list = dataclasses.field(default_factory=list)
    single_support: str | None = None
    planned_landing: np.ndarray | None = None
    swing_com_gain: dict = dataclasses.field(default_factory=dict)


def shifted_q2(q2, cells, start, gain) -> np.ndarray:
    """Q2 per landing cell (n, 2): ``q2`` plus ``gain`` (2 x 2) times the step from ``start`` (x, y) to each cell
    (ours, ``FallSituation.swing_com_gain``); ``q2`` broadcast when the gain or the start is unknown."""
    cells = np.asarray(cells, float).reshape(-1, 3)
    q2 = np.asarray(q2, float)[:2]
    if gain is None or start is None:
        return np.broadcast_to(q2, (len(cells), 2))
    return q2 + (cells[:, :2] - np.asarray(start, float)[:2]) @ np.asarray(gain, float).T


@dataclasses.dataclass
class CaseResult:
    """The best candidate of one case."""

    case: StepCase
    p2: np.ndarray
    q2: np.ndarray
    alpha2: float           # [rad], NaN for a capture
    captured: bool
    margin: float           # Q2's depth inside the polygon [m] (< 0 outside)
    landing: np.ndarray | None  # (x, y, yaw) of the landing sole
    polygon: np.ndarray     # the new support polygon (k, 2)
    com_touchdown: np.ndarray
    cells: int = 0
    capture_margin: float = 0.02
    step_length: float = 0.0    # swing sole start -> landing [m] (0: no step)
    capture_depth: float = 0.0  # SearchConfig.capture_depth

    @property
    def score(self) -> float:
        if self.captured:
            return float(_capture_key(self.margin, self.step_length, self.capture_margin, self.capture_depth))
        return self.alpha2 if math.isfinite(self.alpha2) else -1.0


def _capture_key(margin, step_length, capture_margin: float, capture_depth: float):
    """Rank of an inside Q2 (captures above shallow insides above every fall, whose key is alpha2 < 4).

    Deepest first; with ``capture_depth`` > 0 the captures at least that deep rank above the others, shortest step
    first (margins are well under 0.5 m, so 1e3 + 0.5 + ... is above every 1e3 + margin)."""
    margin = np.asarray(margin, float)
    base = np.where(margin >= capture_margin, 1e3, 5e2) + margin
    if capture_depth <= 0.0:
        return base
    deep = margin >= max(capture_depth, capture_margin)
    return np.where(deep, 1e3 + 0.5 + 0.49 / (1.0 + np.asarray(step_length, float)), base)


@dataclasses.dataclass
class StepDecision:
    """The decision of eq. 4 (what ``safe_fall/decision`` carries, see controller.SafeFallDecision)."""

    best: CaseResult
    cases: dict
    p1: np.ndarray
    q1: np.ndarray
    alpha1: float
    touchdown_time: float
    control_duration: float
    cell_count: int
    search_time: float
    reason: str = ""


def _pivot(soles: dict, stance: str, direction, tie: float) -> np.ndarray:
    """The stance sole's corner(s) furthest along the fall direction (1 corner, or 2 tying: an edge)."""
    c = soles[stance]
    proj = c @ direction
    keep = proj >= proj.max() - tie
    return c[keep]


def _pendulum_start(com, vel, pivots: list[np.ndarray]):
    """Initial (r, v) relative to each case's pivot; a 2-point pivot is an edge: the motion along it is dropped.

    Python floats (3 cases a decision): numpy's per-call overhead was most of its cost.
    """
    gx, gy, gz = (float(x) for x in com)
    vx, vy, vz = (float(x) for x in vel)
    r0, v0 = [], []
    for pv in pivots:
        pts = np.asarray(pv, float).tolist()
        if len(pts) >= 2:
            (ax, ay), (bx, by) = pts[0], pts[-1]
            length = math.sqrt((bx - ax) ** 2 + (by - ay) ** 2)
            ex, ey = (bx - ax) / max(length, 1e-12), (by - ay) / max(length, 1e-12)
            t = min(max((gx - ax) * ex + (gy - ay) * ey, 0.0), length)
            px, py = ax + t * ex, ay + t * ey
            along = vx * ex + vy * ey
            v = (vx - ex * along, vy - ey * along, vz)
        else:
            px, py = pts[0]
            v = (vx, vy, vz)
        r0.append((gx - px, gy - py, gz))
        v0.append(v)
    return np.array(r0), np.array(v0)


def predict_touchdown(com, com_velocity, pivots: list[np.ndarray], duration: float, steps: int = 8,
                      g: float = GRAVITY, cop_delay: float = 0.0,
                      offset: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """CoM, its velocity and the capture point (eq. 1-2) ``duration`` after now, per pivot set.

    ``cop_delay`` > 0: the capture point is the one ``cop_delay`` later with the CoP still on the pivot
    (:func:`delayed_capture_point`). ``offset`` > 0: the capture point moved that far on along the CoM's
    horizontal velocity at touchdown (``SearchConfig.capture_offset``). Returns (com (k, 3), velocity (k, 3),
    capture point (k, 2)).
    """
    com = np.asarray(com, float)
    vel = np.asarray(com_velocity, float)
    r0, v0 = _pendulum_start(com, vel, pivots)
    if duration <= 0:
        r, v = r0, v0
    else:
        r, v = spherical_rk4(r0, v0, duration, steps, g)
    G = (com[None, :] - r0) + r
    z = np.maximum(G[:, 2], 1e-3)
    Q = G[:, :2] + np.sqrt(z / g)[:, None] * v[:, :2]
    if cop_delay > 0.0:
        Q = delayed_capture_point(Q, com[None, :2] - r0[:, :2], z, cop_delay, g)
    if offset > 0.0:
        speed = np.linalg.norm(v[:, :2], axis=1)
        Q = Q + offset * v[:, :2] / np.maximum(speed, 1e-9)[:, None] * (speed > 1e-9)[:, None]
    return G, v, Q


def delayed_capture_point(q, cop, com_height, delay: float, g: float = GRAVITY) -> np.ndarray:
    """The capture point ``delay`` later with the CoP held at ``cop`` (ours; the linear inverted pendulum).

    The capture point xi = c + c'/omega obeys xi' = omega (xi - p) for a CoP p (omega = sqrt(g / z)), so with p
    held: xi(t) = p + (xi(0) - p) exp(omega t). Used for the robot's balance response after touchdown: the CoP
    does not jump into the new support polygon on the touchdown tick (measured at 1.3x standing_push: it stays
    under the CoM for ~0.15 s while the capture point runs on).

    Args:
        q: capture points (k, 2) [m]; cop: CoPs (k, 2) [m]; com_height: z (k,) [m]; delay [s].
    """
    q = np.asarray(q, float)
    p = np.asarray(cop, float)
    omega = np.sqrt(g / np.maximum(np.asarray(com_height, float), 1e-3))
    return p + (q - p) * np.exp(omega * delay)[:, None]


def _hull_eval(cells: np.ndarray, sole_local: np.ndarray, pivot: np.ndarray, q: np.ndarray, target: np.ndarray):
    """Per landing cell: nearest point P2 of hull(landing sole, pivot) to q, inside margin, alpha (vectorised).

    Evaluated in each cell's sole frame, where the sole is one fixed axis-aligned rectangle and
    only q and the pivot point(s) move. The hull's boundary lies on the rectangle's boundary and
    the segments pivot -> sole corner (and pivot -> pivot), so for q outside the hull the nearest
    point over those pieces (the rectangle taken filled: a clamp) is the nearest hull point. q is
    inside iff it is in the rectangle, or some point of the set lies beyond the line through that
    nearest point normal to it (the separation test). Inside, the margin reported is the distance
    to the nearest piece: a lower bound of the depth (exact when the nearest piece is a hull edge);
    ``_inside_margin`` gives the exact depth and is what the tests compare against.

    Args:
        cells: landing sole poses (N, 3) = (x, y, yaw) [m, m, rad].
        sole_local: the sole rectangle's corners in its frame (4, 2) [m].
        pivot: the stance pivot corner(s) (K, 2) [m], K = 1 or 2.
        q: Q2 [m], (2,). target: T [m], (2,).
    Returns:
        (P2 (N, 2) [m], margin (N,) [m], > 0 inside, alpha (N,) [rad]).

    Layout: the segments are rows of (S, N) arrays (S = 4 K, + 1 for an edge pivot), so the
    reductions over the pieces run along the long axis (a min over axis 1 of (N, 9) costs 10x more).
    """
    h = _hull_core(cells, sole_local, pivot, q)
    p2x, p2y = h.p2()
    return np.column_stack([p2x, p2y]), h.margin, _alpha(p2x, p2y, q, target)


CHUNK_ELEMENTS = 9000   # cells x segments per block of the hull evaluation (cache-sized)


@dataclasses.dataclass
class _Hull:
    """:func:`_hull_core`'s result: nearest point (bx, by) in each sole frame, the frames, the margin."""

    cells: np.ndarray
    cos: np.ndarray
    sin: np.ndarray
    bx: np.ndarray
    by: np.ndarray
    margin: np.ndarray

    def p2(self, i: int | slice | None = None):
        """P2 in the world [m]: (x (N,), y (N,)) (of the cells ``i``, a slice), or of cell ``i`` (an int) as floats."""
        if i is None or isinstance(i, slice):
            i = slice(None) if i is None else i
            c, s, bx, by = self.cos[i], self.sin[i], self.bx[i], self.by[i]
            return self.cells[i, 0] + c * bx - s * by, self.cells[i, 1] + s * bx + c * by
        c, s, bx, by = float(self.cos[i]), float(self.sin[i]), float(self.bx[i]), float(self.by[i])
        return float(self.cells[i, 0]) + c * bx - s * by, float(self.cells[i, 1]) + s * bx + c * by


def _alpha_edge(p2x, p2y, q, g_td, v_td, target, vertices, horizon: float, g: float = GRAVITY,
                corner_tol: float = 1e-3) -> np.ndarray:
    """alpha of the fall about the new support (ours), vectorised over cells [rad]: the angle at P2 between T and
    where the CoM goes from P2 ``horizon`` [s] after touchdown (``g_td``, ``v_td``).

    P2 inside an edge: the robot topples about that edge, so the linear pendulum acts across it only (the CoP follows
    the CoM along the edge): across, r_n cosh(w T) + v_n / w sinh(w T); along, r_e + v_e T (r = CoM - P2, w =
    sqrt(g / z)). P2 at a corner: the point pendulum in both directions, whose heading tends to P2 -> Q2 (paper 1)
    as T grows. P2 is the nearest boundary point to an outside Q2, so inside an edge the edge's outward normal is
    (Q2 - P2) / |Q2 - P2|; P2 within ``corner_tol`` of one of ``vertices`` (N, V, 2) is a corner (point pendulum).
    """
    p = np.column_stack([np.broadcast_to(p2x, np.shape(p2x)), np.broadcast_to(p2y, np.shape(p2y))]).reshape(-1, 2)
    q = np.broadcast_to(np.asarray(q, float)[..., :2], p.shape)
    g_td = np.asarray(g_td, float).reshape(-1)
    w = math.sqrt(g / max(float(g_td[2]), 1e-3))
    ch, sh = math.cosh(w * horizon), math.sinh(w * horizon)
    r = g_td[:2][None, :] - p
    v = np.asarray(v_td, float).reshape(-1)[:2][None, :]
    n = q - p
    n = n / np.maximum(np.linalg.norm(n, axis=1), 1e-12)[:, None]
    e = np.column_stack([-n[:, 1], n[:, 0]])
    along = np.sum(e * r, axis=1) + np.sum(e * v, axis=1) * horizon
    across = np.sum(n * r, axis=1) * ch + np.sum(n * v, axis=1) / w * sh
    h = e * along[:, None] + n * across[:, None]
    corner = np.min(np.linalg.norm(np.asarray(vertices, float) - p[:, None, :], axis=2), axis=1) < corner_tol
    h = np.where(corner[:, None], r * ch + v / w * sh, h)
    t = np.asarray(target, float)[:2][None, :] - p
    nh, nt = np.linalg.norm(h, axis=1), np.linalg.norm(t, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        alpha = np.arccos(np.clip(np.sum(h * t, axis=1) / (nh * nt), -1.0, 1.0))
    return np.where((nh < 1e-12) | (nt < 1e-9), np.nan, alpha)


def _fall_alpha(cells, sole_local, pivot, p2x, p2y, q2, g_td, v_td, target, cfg: SearchConfig) -> np.ndarray:
    """The landing cells' alpha2 [rad] as ``cfg.fall_ranking`` says: paper 1's angle(Q2 P2 T), or with the touchdown
    velocity known, :func:`_alpha_edge` on each cell's hull (its sole corners and the pivot)."""
    if cfg.fall_ranking == "paper" or v_td is None:
        return _alpha(p2x, p2y, q2, target)
    verts = np.concatenate([sole_corners_at(cells, sole_local),
                            np.broadcast_to(pivot, (len(cells),) + pivot.shape)], axis=1)
    return _alpha_edge(p2x, p2y, q2, g_td, v_td, target, verts, cfg.fall_heading_horizon)


def _alpha(p2x, p2y, q, target) -> np.ndarray:
    """alpha = angle(Q2 P2 T) (Fig. 5) per cell [rad] (NaN when P2 is on Q2 or T); ``q`` (2,) or per cell (n, 2)."""
    q = np.asarray(q, float)
    ux, uy = q[..., 0] - p2x, q[..., 1] - p2y
    vx, vy = target[0] - p2x, target[1] - p2y
    nu, nv = np.hypot(ux, uy), np.hypot(vx, vy)
    with np.errstate(invalid="ignore", divide="ignore"):
        alpha = np.arccos(np.clip((ux * vx + uy * vy) / (nu * nv), -1.0, 1.0))
    return np.where((nu < 1e-9) | (nv < 1e-9), np.nan, alpha)


def _hull_core(cells: np.ndarray, sole_local: np.ndarray, pivot: np.ndarray, q: np.ndarray) -> _Hull:
    """The nearest point and the margin of :func:`_hull_eval` (its docstring), without P2 in the world and alpha.

    ``pivot`` (K, 2), or per cell (K, N, 2); ``q`` (2,), or per cell (N, 2) (several cases in one call).
    In blocks of at most ``CHUNK_ELEMENTS`` / S cells: the (S, N) buffers then stay in the core's cache
    (measured: K = 2, 1,000 cells 0.32 ms, 2,000 cells 0.94 ms in one block).
    """
    n_seg = 4 * pivot.shape[0] + (1 if pivot.shape[0] == 2 else 0)
    block = max(256, CHUNK_ELEMENTS // n_seg)
    n_blocks = max(1, round(len(cells) / block))
    if n_blocks > 1:
        block = -(-len(cells) // n_blocks)   # equal blocks of about CHUNK_ELEMENTS (no small remainder)
        parts = [_hull_core(cells[i:i + block], sole_local, pivot if pivot.ndim == 2 else pivot[:, i:i + block],
                            q if q.ndim == 1 else q[i:i + block]) for i in range(0, len(cells), block)]
        return _Hull(cells, *(np.concatenate([getattr(h, f) for h in parts])
                              for f in ("cos", "sin", "bx", "by", "margin")))
    x0, y0 = sole_local.min(axis=0)
    x1, y1 = sole_local.max(axis=0)
    n = len(cells)
    npiv = pivot.shape[0]
    X, Y = cells[:, 0], cells[:, 1]
    c, s = np.cos(cells[:, 2]), np.sin(cells[:, 2])
    if q.ndim == 1:
        dx, dy = q[0] - X, q[1] - Y
    else:
        dx, dy = q[:, 0] - X, q[:, 1] - Y
    qx, qy = c * dx + s * dy, -s * dx + c * dy                     # q in each sole frame (N,)
    if pivot.ndim == 2:
        pdx, pdy = pivot[:, 0:1] - X, pivot[:, 1:2] - Y
    else:
        pdx, pdy = pivot[:, :, 0] - X, pivot[:, :, 1] - Y
    px, py = c * pdx + s * pdy, -s * pdx + c * pdy                   # the pivots in each sole frame (K, N)
    # the rectangle, filled
    rx, ry = np.clip(qx, x0, x1), np.clip(qy, y0, y1)
    in_rect = (rx == qx) & (ry == qy)
    inner = np.minimum(np.minimum(qx - x0, x1 - qx), np.minimum(qy - y0, y1 - qy))
    d2_rect = np.where(in_rect, inner * inner, (qx - rx) ** 2 + (qy - ry) ** 2)
    # segments (S, N): pivot k -> corner j (k-major), then pivot 0 -> pivot 1
    cx = np.array([x1, x0, x0, x1])[:, None]
    cy = np.array([y1, y1, y0, y0])[:, None]
    ax, ay, ex, ey = (np.empty((n_seg, n)) for _ in range(4))
    for k in range(npiv):
        rows = slice(4 * k, 4 * k + 4)
        ax[rows], ay[rows] = px[k], py[k]
        np.subtract(cx, px[k], out=ex[rows])
        np.subtract(cy, py[k], out=ey[rows])
    if npiv == 2:
        ax[8], ay[8] = px[0], py[0]
        np.subtract(px[1], px[0], out=ex[8])
        np.subtract(py[1], py[0], out=ey[8])
    # t = clip((w . e) / max(|e|^2, 1e-18), 0, 1) with w = q - a; nearest a + t e; d2 = |q - nearest|^2,
    # in place in four (S, N) buffers (the temporaries of the plain expressions overflowed the cache)
    t, nx, ny, d2 = (np.empty((n_seg, n)) for _ in range(4))
    np.subtract(qx, ax, out=t)
    t *= ex
    np.subtract(qy, ay, out=nx)
    nx *= ey
    t += nx                                   # w . e
    np.multiply(ex, ex, out=nx)
    np.multiply(ey, ey, out=ny)
    nx += ny
    np.maximum(nx, 1e-18, out=nx)             # |e|^2
    t /= nx
    np.clip(t, 0.0, 1.0, out=t)
    np.multiply(t, ex, out=nx)
    nx += ax
    np.multiply(t, ey, out=ny)
    ny += ay
    np.subtract(qx, nx, out=d2)
    d2 *= d2
    np.subtract(qy, ny, out=t)
    t *= t
    d2 += t
    flat = np.argmin(d2, axis=0) * n + np.arange(n)
    d2_seg = d2.ravel()[flat]
    use_rect = d2_rect <= d2_seg
    # nearest point in the sole frame (inside the rectangle: q itself; not used for captures)
    bx = np.where(use_rect, rx, nx.ravel()[flat])
    by = np.where(use_rect, ry, ny.ravel()[flat])
    dist = np.sqrt(np.minimum(d2_rect, d2_seg))
    # separation test: some point of the set beyond the line through the nearest point, normal to q - it
    mx, my = qx - bx, qy - by
    beyond = np.maximum(((cx - bx) * mx + (cy - by) * my).max(axis=0), ((px - bx) * mx + (py - by) * my).max(axis=0))
    inside = in_rect | (beyond > 1e-9 * np.maximum(np.hypot(mx, my), 1e-12))
    return _Hull(cells, c, s, bx, by, np.where(inside, dist, -dist))


def _inside_margin(pts: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Depth of q inside the hulls of point sets (n, M, 2) [m] (vectorised hull-edge test)."""
    M = pts.shape[1]
    pairs = np.array(list(itertools.combinations(range(M), 2)))
    a = pts[:, pairs[:, 0]]
    e = pts[:, pairs[:, 1]] - a
    rel = pts[:, None, :, :] - a[:, :, None, :]
    cr = e[:, :, None, 0] * rel[..., 1] - e[:, :, None, 1] * rel[..., 0]
    left = np.all(cr >= -1e-9, axis=2)
    right = np.all(cr <= 1e-9, axis=2)
    length = np.maximum(np.hypot(e[..., 0], e[..., 1]), 1e-12)
    qa = q - a
    cq = (e[..., 0] * qa[..., 1] - e[..., 1] * qa[..., 0]) * np.where(left, 1.0, -1.0) / length
    return np.min(np.where((left | right) & (length > 1e-9), cq, np.inf), axis=1)


def zone_cells(zone: SteppingZone, cfg: SearchConfig, obstacles: list[Footprint], start=None) -> np.ndarray:
    """Landing poses (n, 3) = (x, y, yaw) on the grid inside the zone and off the obstacles (and within
    ``cfg.max_step_length`` of ``start``, the swing sole's x, y, when both are given)."""
    (x0, x1), (y0, y1) = zone.x_range, zone.y_range
    if x1 <= x0 or y1 <= y0:
        return np.zeros((0, 3))
    lo = max(zone.center[2] - zone.half_extent_eq8[2], zone.yaw_range[0])
    hi = min(zone.center[2] + zone.half_extent_eq8[2], zone.yaw_range[1])
    if hi < lo:
        return np.zeros((0, 3))
    nyaw = max(1, math.floor((hi - lo) / cfg.cell_yaw) + 1)
    yaws = np.linspace(lo, hi, nyaw) if nyaw > 1 else np.array([0.5 * (lo + hi)])
    # the zone's tests split into a position part and a yaw part: test the (x, y) grid and the yaws
    # apart and combine (the same cells, in the same x, y, yaw order, as the (x, y, yaw) grid tested whole)
    def grid(cell: float) -> np.ndarray:
        xs = np.arange(x0 + cell / 2, x1, cell)
        ys = np.arange(y0 + cell / 2, y1, cell)
        xy = np.column_stack([np.repeat(xs, len(ys)), np.tile(ys, len(xs))])
        keep = zone.contains_xy(xy)
        if obstacles and len(xy):
            keep &= ~_hits_obstacles(xy, obstacles, cfg.obstacle_clearance)
        if cfg.max_step_length > 0.0 and start is not None and len(xy):
            keep &= np.hypot(xy[:, 0] - float(start[0]), xy[:, 1] - float(start[1])) <= cfg.max_step_length
        return xy[keep]

    xy = grid(cfg.cell_xy)
    # a sliver of a zone (the separatrix and the reach leave a few cells) is sampled finer, at half or a
    # quarter of the cell, so that it holds about min_zone_cells: the grid would otherwise decide which
    # part of it exists (measured: 12 cells of a step_left zone missed the landing that halving the
    # cells found, alpha2 47 -> 76 deg)
    if len(xy) < cfg.min_zone_cells:
        halvings = min(2, math.ceil(0.5 * math.log2(cfg.min_zone_cells / max(len(xy), 1))))
        # the finer lattice does not hold the coarse cells: keep both, so that sampling finer never
        # loses the grid's best landing (walking_push: alpha2 predicted 143.5 deg by the grid, 136 without it)
        xy = np.vstack([xy, grid(cfg.cell_xy / 2 ** halvings)])
    yaws = yaws[zone.contains_yaw(yaws)]
    if len(xy) == 0 or len(yaws) == 0:
        return np.zeros((0, 3))
    return np.column_stack([np.repeat(xy, len(yaws), axis=0), np.tile(yaws, len(xy))])


def sole_corners_at(poses: np.ndarray, local: np.ndarray) -> np.ndarray:
    """Sole corners (n, 4, 2) of sole poses (n, 3) [m, m, rad]; ``local`` (4, 2) in the sole frame."""
    c, s = np.cos(poses[:, 2]), np.sin(poses[:, 2])
    x = local[None, :, 0] * c[:, None] - local[None, :, 1] * s[:, None] + poses[:, None, 0]
    y = local[None, :, 0] * s[:, None] + local[None, :, 1] * c[:, None] + poses[:, None, 1]
    return np.stack([x, y], axis=2)


def _hits_obstacles(cells: np.ndarray, obstacles: list[Footprint], clearance: float) -> np.ndarray:
    hit = np.zeros(len(cells), bool)
    for ob in obstacles:
        R = rotation_z(-ob.yaw)
        rel = (cells[:, :2] - ob.center) @ R.T
        hit |= np.all(np.abs(rel) <= ob.half_size + clearance + 0.15, axis=1)  # 0.15: sole half-length and more
    return hit


def case_pivots(sit: FallSituation, cfg: SearchConfig) -> tuple[list[str], list[np.ndarray]]:
    """(stance sides, pivot point sets): the current leading edge first, then each stance sole's pivot."""
    p1 = np.asarray(sit.cop, float)[:2]
    q1 = np.asarray(sit.capture_point, float)[:2]
    u = np.asarray(sit.edge_normal, float)[:2]
    if not np.all(np.isfinite(u)) or np.linalg.norm(u) < 1e-9:
        u = q1 - p1
    u = u / max(float(np.linalg.norm(u)), 1e-12)
    edge = np.array([np.asarray(sit.leading_edge[0], float)[:2], np.asarray(sit.leading_edge[1], float)[:2]])
    if np.linalg.norm(edge[1] - edge[0]) < 1e-6:
        edge = edge[:1]
    stance_sides = [sit.single_support] if sit.single_support else ["r", "l"]   # lift left = stance right
    return stance_sides, [edge] + [_pivot(sit.soles, s, u, cfg.corner_tie) for s in stance_sides]


def search(sit: FallSituation, sole_local: np.ndarray, cfg: SearchConfig | None = None,
           prediction: tuple[np.ndarray, np.ndarray] | None = None) -> StepDecision:
    """Eq. 4 over the cases (module docstring); ``sole_local`` (4, 2) is the sole rectangle in its frame.

    ``prediction``: (G (k, 3), Q (k, 2)) of :func:`predict_touchdown` for :func:`case_pivots`, if the
    caller already has it (the controller needs it for the stepping zones).
    """
    cfg = cfg or SearchConfig()
    t0 = time.perf_counter()
    com = np.asarray(sit.com, float)
    vel = np.asarray(sit.com_velocity, float)
    p1 = np.asarray(sit.cop, float)[:2]
    q1 = np.asarray(sit.capture_point, float)[:2]
    target = None if sit.target is None else np.asarray(sit.target, float)[:2]
    alpha1 = avoidance_angle_xy(*p1.tolist(), *q1.tolist(), *target.tolist()) if target is not None else math.nan
    stance_sides, pivots = case_pivots(sit, cfg)
    edge = pivots[0]
    if prediction is None:
        G, V, Q = predict_touchdown(com, vel, pivots, sit.touchdown_time, cfg.rk4_steps, cop_delay=cfg.cop_delay,
                                    offset=cfg.capture_offset)
    else:
        G, Q, *rest = prediction
        V = rest[0] if rest else None
    if V is None and cfg.fall_ranking != "paper":
        V = predict_touchdown(com, vel, pivots, sit.touchdown_time, cfg.rk4_steps)[1]
    cases: dict[StepCase, CaseResult] = {}
    if target is None:
        best = CaseResult(StepCase.NO_TARGET, p1, Q[0], math.nan, False, -math.inf, None, edge, G[0])
        return StepDecision(best, {StepCase.NO_TARGET: best}, p1, q1, alpha1, sit.touchdown_time,
                            sit.control_duration, 0, time.perf_counter() - t0, "no target to avoid: no step")
    if not sit.single_support:  # no change: rotate on about the current soles' hull
        poly0 = support_polygon(np.vstack([sit.soles["l"], sit.soles["r"]]).tolist())
        cases[StepCase.NO_CHANGE] = _single(StepCase.NO_CHANGE, poly0, Q[0], target, G[0], cfg,
                                            None if V is None else V[0])
    total_cells = 0
    order: list = []      # the cases in the order eq. 4 lists them (ties go to the first)
    steps: list = []      # (case, cells, pivot, Q2, G) of the step cases, evaluated in one batch
    for k, stance in enumerate(stance_sides, start=1):
        swing = "l" if stance == "r" else "r"
        piv = pivots[k]
        lift_case = StepCase.LIFT_LEFT if swing == "l" else StepCase.LIFT_RIGHT
        step_case = StepCase.STEP_LEFT if swing == "l" else StepCase.STEP_RIGHT
        cases[lift_case] = _single(lift_case, piv, Q[k], target, G[k], cfg,   # single support: keep it lifted
                                   None if V is None else V[k])
        order.append(lift_case)
        if sit.single_support and sit.planned_landing is not None:
            plan = np.asarray(sit.planned_landing, float).reshape(1, 3)
            steps.append((StepCase.CONTINUE_STEP, plan, piv, Q[k], G[k], _sole_xy(sit, swing),
                          None if V is None else V[k], sit.swing_com_gain.get(swing)))
            order.append(StepCase.CONTINUE_STEP)
        zone = sit.zones.get(swing)
        if zone is None:
            continue
        cells = zone_cells(zone, cfg, sit.obstacles, _sole_xy(sit, swing))
        total_cells += len(cells)
        steps.append((step_case, cells, piv, Q[k], G[k], _sole_xy(sit, swing), None if V is None else V[k],
                      sit.swing_com_gain.get(swing)))
        order.append(step_case)
    for (case, *_), r in zip(steps, _cells_batch(steps, target, sole_local, cfg)):
        if r is not None:
            cases[case] = r
    cases = {c: cases[c] for c in [StepCase.NO_CHANGE] + order if c in cases}
    best = max(cases.values(), key=lambda c: c.score)
    return StepDecision(best, cases, p1, q1, alpha1, sit.touchdown_time, sit.control_duration, total_cells,
                        time.perf_counter() - t0)


def _sole_xy(sit: FallSituation, side: str) -> np.ndarray | None:
    """Where the swing sole is now (x, y) [m], for the step length (None: unknown)."""
    pose = (sit.sole_poses or {}).get(side)
    return None if pose is None else np.asarray(pose, float)[:2]


def _single(case: StepCase, poly, q2, target, g_td, cfg: SearchConfig, v_td=None) -> CaseResult:
    """A case without a landing (no change, lift): Q2 against one polygon (or the pivot segment / corner)."""
    poly = np.asarray(poly, float).reshape(-1, 2)
    poly = support_polygon(poly.tolist()) if len(poly) >= 3 else poly
    pts = poly.tolist()
    qx, qy = float(q2[0]), float(q2[1])
    if len(pts) >= 3 and inside_convex_xy(qx, qy, pts, cfg.capture_margin):
        return CaseResult(case, q2.copy(), q2.copy(), math.nan, True, polygon_margin_xy(qx, qy, pts), None, poly,
                          g_td, capture_margin=cfg.capture_margin, capture_depth=cfg.capture_depth)
    if len(pts) >= 2:
        px, py = nearest_on_boundary_xy(qx, qy, pts, closed=len(pts) >= 3)
    else:
        px, py = pts[0]
    if cfg.fall_ranking != "paper" and v_td is not None:
        alpha = float(_alpha_edge(np.array([px]), np.array([py]), q2, g_td, v_td, target, poly[None],
                                  cfg.fall_heading_horizon)[0])
    else:
        alpha = avoidance_angle_xy(px, py, qx, qy, float(target[0]), float(target[1]))
    return CaseResult(case, np.array([px, py]), q2.copy(), alpha, False,
                      -math.sqrt((qx - px) ** 2 + (qy - py) ** 2), None, poly, g_td)


def _cells(case: StepCase, cells: np.ndarray, pivot: np.ndarray, q2, target, g_td, sole_local,
           cfg: SearchConfig, start=None, com_gain=None) -> CaseResult | None:
    """The best landing cell of one case (:func:`_cells_batch` of one); ``start``: the swing sole's x, y now;
    ``com_gain``: :func:`shifted_q2`'s."""
    return _cells_batch([(case, cells, pivot, q2, g_td, start, None, com_gain)], target, sole_local, cfg)[0]


def _cells_batch(groups: list, target, sole_local, cfg: SearchConfig) -> list[CaseResult | None]:
    """The best landing cell of each case ``(case, cells (n, 3), pivot (K, 2), Q2, G at touchdown[, swing sole
    x, y now[, CoM velocity at touchdown[, the swing's CoM gain (:func:`shifted_q2`)]]])``.

    All cases' cells go through one :func:`_hull_core` call (numpy's per-call overhead is paid once);
    a one-corner pivot is padded to two equal corners (the same hull, the same pieces' distances).
    """
    target = np.asarray(target, float)[:2]
    out: list[CaseResult | None] = [None] * len(groups)
    live = [k for k, g in enumerate(groups) if len(g[1])]
    if not live:
        return out
    npiv = max(np.asarray(groups[k][2]).reshape(-1, 2).shape[0] for k in live)
    cells, piv, qs, bounds = [], [], [], []
    start = 0
    for k in live:
        _case, c, pv, q2, _g, *rest = groups[k]
        pv = np.asarray(pv, float).reshape(-1, 2)
        pv = np.vstack([pv, np.repeat(pv[-1:], npiv - len(pv), axis=0)])
        cells.append(c)
        piv.append(np.broadcast_to(pv[:, None, :], (npiv, len(c), 2)))
        qs.append(shifted_q2(q2, c, rest[0] if rest else None, rest[2] if len(rest) > 2 else None))
        bounds.append((start, start + len(c)))
        start += len(c)
    if len(live) == 1:
        g = groups[live[0]]
        C, P, Qc = cells[0], np.asarray(g[2], float).reshape(-1, 2), np.ascontiguousarray(qs[0])
    else:
        C, P, Qc = np.vstack(cells), np.concatenate(piv, axis=1), np.vstack(qs)
    h = _hull_core(C, sole_local, P, Qc)
    for k, (lo, hi) in zip(live, bounds):
        case, c, pv, q2, g_td, *rest = groups[k]
        pivot = np.asarray(pv, float).reshape(-1, 2)
        q2 = Qc[lo:hi]   # Q2 per cell (shifted_q2)
        margin = h.margin[lo:hi]
        inside = margin > 0
        length = _step_lengths(c, rest[0] if rest else None)
        if np.any(inside):   # captures and shallow insides rank above every fall: no alpha needed
            # inside but shallow (by the lower bound): ranks above every fall, below the captures
            key = _capture_key(margin, length, cfg.capture_margin, cfg.capture_depth)
            i = int(np.argmax(np.where(inside, key, -1.0)))
            p2, alpha_i = np.array(h.p2(lo + i)), math.nan
        else:
            p2x, p2y = h.p2(slice(lo, hi))
            v_td = rest[1] if len(rest) > 1 else None
            alpha = _fall_alpha(c, sole_local, pivot, p2x, p2y, q2, g_td, v_td, target, cfg)
            i = int(np.argmax(np.where(np.isfinite(alpha), alpha, -1.0)))
            p2, alpha_i = np.array([p2x[i], p2y[i]]), float(alpha[i])
        poly = support_polygon(np.vstack([sole_corners_at(c[i:i + 1], sole_local)[0], pivot]).tolist())
        out[k] = CaseResult(case, p2.copy(), np.array(q2[i], float), alpha_i, bool(inside[i]), float(margin[i]),
                            c[i].copy(), poly, g_td, len(c), cfg.capture_margin, float(length[i]), cfg.capture_depth)
    return out


def _step_lengths(cells: np.ndarray, start) -> np.ndarray:
    """Distance of each landing cell (x, y) from the swing sole now [m] (zeros when unknown)."""
    cells = np.asarray(cells, float).reshape(-1, 3)
    if start is None:
        return np.zeros(len(cells))
    return np.hypot(cells[:, 0] - float(start[0]), cells[:, 1] - float(start[1]))


def ranked_cells(case: StepCase, cells: np.ndarray, pivot: np.ndarray, q2, target, g_td, sole_local,
                 cfg: SearchConfig, limit: int = 50, start=None, v_td=None, com_gain=None) -> list[CaseResult]:
    """One step case's landing cells as candidates, best first (the order :func:`_cells_batch` picks the best by:
    captures by depth, then shallow insides, then falls by alpha2), the first ``limit``.

    For the controller when the best cell fails the IK's reach check (eq. 9): the next ones are tried."""
    cells = np.asarray(cells, float).reshape(-1, 3)
    if not len(cells):
        return []
    target = np.asarray(target, float)[:2]
    pivot = np.asarray(pivot, float).reshape(-1, 2)
    q2 = np.ascontiguousarray(shifted_q2(q2, cells, start, com_gain))
    h = _hull_core(cells, sole_local, pivot, q2)
    margin = h.margin
    inside = margin > 0
    p2x, p2y = h.p2(slice(0, len(cells)))
    alpha = _fall_alpha(cells, sole_local, pivot, p2x, p2y, q2, g_td, v_td, target, cfg)
    length = _step_lengths(cells, start)
    key = np.where(inside, _capture_key(margin, length, cfg.capture_margin, cfg.capture_depth),
                   np.where(np.isfinite(alpha), alpha, -1.0))
    out = []
    for i in np.argsort(-key, kind="stable")[:limit]:
        poly = support_polygon(np.vstack([sole_corners_at(cells[i:i + 1], sole_local)[0], pivot]).tolist())
        a = math.nan if inside[i] else float(alpha[i])
        out.append(CaseResult(case, np.array([p2x[i], p2y[i]]), q2[i].copy(), a, bool(inside[i]), float(margin[i]),
                              cells[i].copy(), poly, g_td, len(cells), cfg.capture_margin, float(length[i]),
                              cfg.capture_depth))
    return out


__all__ = ["CaseResult", "FallSituation", "Footprint", "SearchConfig", "StepCase", "StepDecision", "predict_touchdown",
           "ranked_cells", "search", "sole_corners_at", "zone_cells"]
