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


def heading(v) -> float:
    """Heading of a horizontal vector [rad] (atan2(y, x))."""
    return math.atan2(float(v[1]), float(v[0]))


def rotation_z(yaw: float) -> np.ndarray:
    """2 x 2 rotation by ``yaw`` [rad]."""
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s], [s, c]])


__all__ = ["PolygonEdges", "avoidance_angle", "heading", "inside_convex", "nearest_on_boundary",
           "nearest_on_segments", "polygon_edges", "rotation_z"]
