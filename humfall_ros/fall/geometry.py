"""Fall geometry of paper 1: support-polygon edges, the leading edge or corner, the avoidance angle (Fig. 5).

All points are 2-D ground coordinates [m] in the world frame unless a docstring says (3,).
Polygons are convex and counter-clockwise (``humfall_ros.model.humanoid.support_polygon``).
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np


@dataclasses.dataclass(frozen=True)
class PolygonEdges:
    """The boundary pieces a toppling robot can rotate about.

    Attributes:
        start, end: edge end points [m], (k, 2); a corner (one-point polygon) has start == end.
        normal: horizontal unit outward normals [-], (k, 2) (NaN for a corner: it depends on the CoM).
    """

    start: np.ndarray
    end: np.ndarray
    normal: np.ndarray

    def __len__(self) -> int:
        return len(self.start)


def polygon_edges(polygon) -> PolygonEdges:
    """Edges of a convex CCW polygon with outward normals; a segment gives both sides, a point one corner."""
    p = np.asarray(polygon, float).reshape(-1, 2)
    if len(p) == 0:
        return PolygonEdges(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros((0, 2)))
    if len(p) == 1:
        return PolygonEdges(p.copy(), p.copy(), np.full((1, 2), np.nan))
    if len(p) == 2:
        a, b = p[[0, 1]], p[[1, 0]]
    else:
        a, b = p, np.roll(p, -1, axis=0)
    e = b - a
    length = np.linalg.norm(e, axis=1, keepdims=True)
    n = np.column_stack([e[:, 1], -e[:, 0]]) / np.maximum(length, 1e-12)  # outward of a CCW edge
    return PolygonEdges(a, b, n)


def nearest_on_segments(point, start, end) -> tuple[np.ndarray, np.ndarray]:
    """Nearest points on segments to ``point`` and their distances (vectorised over segments)."""
    q = np.asarray(point, float)[:2]
    e = end - start
    den = np.maximum(np.sum(e * e, axis=1), 1e-18)
    t = np.clip(np.sum((q - start) * e, axis=1) / den, 0.0, 1.0)
    near = start + t[:, None] * e
    return near, np.linalg.norm(near - q, axis=1)


def nearest_on_boundary(point, polygon) -> np.ndarray:
    """The point of a convex polygon's boundary nearest ``point`` [m], (2,)."""
    edges = polygon_edges(polygon)
    near, dist = nearest_on_segments(point, edges.start, edges.end)
    return near[int(np.argmin(dist))]


def inside_convex(point, polygon, tolerance: float = 0.0) -> bool:
    """True when ``point`` is inside a convex CCW polygon (at least ``tolerance`` [m] from every edge)."""
    p = np.asarray(polygon, float).reshape(-1, 2)
    if len(p) < 3:
        return False
    edges = polygon_edges(p)
    d = np.sum((np.asarray(point, float)[:2] - edges.start) * edges.normal, axis=1)
    return bool(np.all(d <= -tolerance))


def avoidance_angle(p, q, target):
    """Avoidance angle alpha at P between P->Q (the fall direction) and P->T (Fig. 5) [rad], vectorised.

    Args:
        p: CoP P [m], (..., 2).
        q: reference point Q (capture point) [m], (..., 2).
        target: target T [m], (..., 2).
    Returns:
        alpha in [0, pi] [rad]; 0 falls onto T, pi straight away; NaN when P == Q or P == T.
    """
    p = np.asarray(p, float)[..., :2]
    a = np.asarray(q, float)[..., :2] - p
    b = np.asarray(target, float)[..., :2] - p
    na = np.linalg.norm(a, axis=-1)
    nb = np.linalg.norm(b, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        c = np.sum(a * b, axis=-1) / (na * nb)
    out = np.arccos(np.clip(c, -1.0, 1.0))
    return np.where((na < 1e-9) | (nb < 1e-9), np.nan, out)


def polygon_margin_xy(qx: float, qy: float, pts: list) -> float:
    """``humanoid.point_in_polygon_margin`` (signed distance, > 0 inside) on Python floats, the same arithmetic.

    For the per-tick callers with a handful of points (FTB, the search's single-polygon cases), where
    numpy's per-call overhead costs more than the arithmetic. ``pts``: [(x, y), ...] CCW [m].
    """
    k = len(pts)
    if k < 3:
        if k == 0:
            return -math.inf
        ax, ay = pts[0]
        if k == 1:
            return -math.sqrt((qx - ax) ** 2 + (qy - ay) ** 2)
        ex, ey = pts[1][0] - ax, pts[1][1] - ay
        t = min(max(((qx - ax) * ex + (qy - ay) * ey) / max(ex * ex + ey * ey, 1e-12), 0.0), 1.0)
        return -math.sqrt((qx - (ax + t * ex)) ** 2 + (qy - (ay + t * ey)) ** 2)
    margin = math.inf
    for i in range(k):
        (ax, ay), (bx, by) = pts[i], pts[(i + 1) % k]
        ex, ey = bx - ax, by - ay
        length = math.hypot(ex, ey)
        if length < 1e-12:
            continue
        margin = min(margin, ((qx - ax) * -ey + (qy - ay) * ex) / length)
    return margin


def inside_convex_xy(qx: float, qy: float, pts: list, tolerance: float = 0.0) -> bool:
    """:func:`inside_convex` on Python floats (``pts`` [(x, y), ...] CCW [m])."""
    k = len(pts)
    if k < 3:
        return False
    for i in range(k):
        (ax, ay), (bx, by) = pts[i], pts[(i + 1) % k]
        ex, ey = bx - ax, by - ay
        length = max(math.sqrt(ex * ex + ey * ey), 1e-12)
        if (qx - ax) * (ey / length) + (qy - ay) * (-ex / length) > -tolerance:
            return False
    return True


def nearest_on_boundary_xy(qx: float, qy: float, pts: list, closed: bool = True) -> tuple[float, float]:
    """:func:`nearest_on_boundary` on Python floats: the nearest point of the polygon's edges (``closed``)
    or of the polyline ``pts`` (a segment: two points, ``closed=False``) [m]."""
    best, out = math.inf, pts[0]
    segs = list(zip(pts, pts[1:] + pts[:1])) if closed else list(zip(pts[:-1], pts[1:]))
    for (ax, ay), (bx, by) in segs:
        ex, ey = bx - ax, by - ay
        t = min(max(((qx - ax) * ex + (qy - ay) * ey) / max(ex * ex + ey * ey, 1e-18), 0.0), 1.0)
        nx, ny = ax + t * ex, ay + t * ey
        d = math.sqrt((nx - qx) ** 2 + (ny - qy) ** 2)
        if d < best:
            best, out = d, (nx, ny)
    return out


def avoidance_angle_xy(px: float, py: float, qx: float, qy: float, tx: float, ty: float) -> float:
    """:func:`avoidance_angle` of one point triple on Python floats [rad] (NaN when P == Q or P == T)."""
    ax, ay, bx, by = qx - px, qy - py, tx - px, ty - py
    na, nb = math.sqrt(ax * ax + ay * ay), math.sqrt(bx * bx + by * by)
    if na < 1e-9 or nb < 1e-9:
        return math.nan
    return math.acos(min(max((ax * bx + ay * by) / (na * nb), -1.0), 1.0))


def heading(v) -> float:
    """Heading of a horizontal vector [rad] (atan2(y, x))."""
    return math.atan2(float(v[1]), float(v[0]))


def rotation_z(yaw: float) -> np.ndarray:
    """2 x 2 rotation by ``yaw`` [rad]."""
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s], [s, c]])


__all__ = ["PolygonEdges", "avoidance_angle", "avoidance_angle_xy", "heading", "inside_convex", "inside_convex_xy",
           "nearest_on_boundary", "nearest_on_boundary_xy", "nearest_on_segments", "polygon_edges",
           "polygon_margin_xy", "rotation_z"]
