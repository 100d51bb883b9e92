"""Contact kinematics of the planar model: constraint rows, force bases and the
impact map (paper 2, eq. 3, 4, 10).

A flat foot on the ground has three independent holonomic rows: toe
tangential, toe normal, heel normal (toe and heel tangential rows are the same
row once the foot is flat, and keeping both would make the constraint Jacobian
rank deficient for the NLP solver). Its force is (f_t at the toe, f_n toe,
f_n heel); friction acts on the total normal force of the foot. A hand is a
point contact with rows (tangential, normal) and force (f_t, f_n).
"""
from __future__ import annotations

import dataclasses

import casadi as ca
import numpy as np

from humfall_ros.multicontact.model import FEET, PlanarModel
from humfall_ros.multicontact.modes import Environment, Mode

# Surface frames: (normal, tangent) in (x, z).
_NORMAL = {"ground": (0.0, 1.0), "wall": (-1.0, 0.0)}
_TANGENT = {"ground": (1.0, 0.0), "wall": (0.0, 1.0)}


@dataclasses.dataclass(frozen=True)
class ContactRow:
    """One holonomic row: coordinate of ``point`` along ``axis`` ('t' or 'n')."""

    extremity: str
    point: str
    surface: str
    axis: str  # 't' tangential, 'n' normal


def contact_rows(mode: Mode, env: Environment) -> list[ContactRow]:
    rows = []
    for e in mode:
        s = env.surface_of(e)
        if e in FEET:
            rows += [ContactRow(e, f"{e}_toe", s, "t"), ContactRow(e, f"{e}_toe", s, "n"),
                     ContactRow(e, f"{e}_heel", s, "n")]
        else:
            rows += [ContactRow(e, e, s, "t"), ContactRow(e, e, s, "n")]
    return rows


def row_direction(row: ContactRow) -> tuple[float, float]:
    return _NORMAL[row.surface] if row.axis == "n" else _TANGENT[row.surface]


def surface_offset(surface: str, env: Environment) -> float:
    """Signed distance phi = n . p + offset (ground: z; wall: wall_x - x)."""
    return float(env.wall_x) if surface == "wall" else 0.0


def row_value_sx(model: PlanarModel, row: ContactRow, q) -> ca.SX:
    """Coordinate of the row's point along its direction (symbolic)."""
    p = model.f_point[row.point](q)
    d = row_direction(row)
    return d[0] * p[0] + d[1] * p[1]


def rows_jacobian(model: PlanarModel, rows: list[ContactRow], q) -> np.ndarray:
    """Numeric J (len(rows) x n) of the holonomic rows (eq. 4)."""
    J = np.zeros((len(rows), model.n))
    for i, r in enumerate(rows):
        d = row_direction(r)
        Jp = model.point_jacobian(r.point, q)
        J[i] = d[0] * Jp[0] + d[1] * Jp[1]
    return J


def rows_value(model: PlanarModel, rows: list[ContactRow], q) -> np.ndarray:
    out = np.zeros(len(rows))
    for i, r in enumerate(rows):
        d = row_direction(r)
        p = model.point(r.point, q)
        out[i] = d[0] * p[0] + d[1] * p[1]
    return out


def signed_distance(model: PlanarModel, point: str, surface: str, env: Environment, q) -> float:
    p = model.point(point, q)
    if surface == "ground":
        return float(p[1])
    return float(env.wall_x - p[0])


def normal_row_indices(rows: list[ContactRow]) -> list[int]:
    return [i for i, r in enumerate(rows) if r.axis == "n"]


def friction_groups(rows: list[ContactRow]) -> list[tuple[int, list[int]]]:
    """(tangential row, normal rows) per extremity, for the cone of eq. 5."""
    groups = []
    by_ext: dict[str, tuple[list, list]] = {}
    for i, r in enumerate(rows):
        t, n = by_ext.setdefault(r.extremity, ([], []))
        (t if r.axis == "t" else n).append(i)
    for t, n in by_ext.values():
        groups.append((t[0], n))
    return groups


def impact_map(model: PlanarModel, q, v_minus, rows: list[ContactRow]) -> tuple[np.ndarray, np.ndarray]:
    """Inelastic impact, eq. 10: [D -J^T; J 0][v+; Lambda] = [D v-; 0].

    Returns the post-impact velocity and the impulse (one per row). The KKT
    matrix is solved in least squares so that redundant rows stay harmless.
    """
    q = np.asarray(q, float)
    v_minus = np.asarray(v_minus, float)
    D = model.D(q)
    J = rows_jacobian(model, rows, q)
    k = J.shape[0]
    K = np.block([[D, -J.T], [J, np.zeros((k, k))]])
    rhs = np.concatenate([D @ v_minus, np.zeros(k)])
    sol = np.linalg.lstsq(K, rhs, rcond=None)[0]
    return sol[: model.n], sol[model.n:]


def forces_per_point(rows: list[ContactRow], lam: np.ndarray) -> np.ndarray:
    """(N x rows) forces -> N x (2 * contact points): (tangential, normal) per point.

    A foot's tangential force is carried by its toe row; its heel reports 0.
    """
    lam = np.atleast_2d(lam)
    cols = []
    points = []
    for r in rows:
        if r.point not in points:
            points.append(r.point)
    for p in points:
        t = [i for i, r in enumerate(rows) if r.point == p and r.axis == "t"]
        n = [i for i, r in enumerate(rows) if r.point == p and r.axis == "n"]
        cols.append(lam[:, t[0]] if t else np.zeros(lam.shape[0]))
        cols.append(lam[:, n[0]])
    return np.stack(cols, axis=1) if cols else np.zeros((lam.shape[0], 0))
