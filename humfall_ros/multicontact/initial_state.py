"""Initial states for the planner: the nominal stance and a pushed velocity of a
given kinetic energy (issue 3, item 4).

The push is modelled as a rigid rotation of the whole robot about the stance
ankle axis (legs, trunk and arms move as one body, the feet stay put), i.e. the
motion of a robot toppling about its ankles right after a shove. The rigid
velocity is made contact-consistent for the given mode with the impact map of
eq. 10 (which is the D-metric projection onto the null space of the contact
Jacobian; it leaves the rotation unchanged for a two-foot stance) and then
scaled so that 1/2 qdot^T D qdot equals the requested energy.
"""
from __future__ import annotations

import math

import numpy as np

from humfall_ros.multicontact import contacts as C
from humfall_ros.multicontact.model import FEET, PlanarModel
from humfall_ros.multicontact.modes import Environment, Mode

DEFAULT_STANCE = {"hip_pitch": -0.2, "knee": 0.4, "ankle_pitch": -0.2, "shoulder_pitch": 0.1, "elbow": -0.3}


def nominal_configuration(model: PlanarModel, stance: dict | None = None) -> np.ndarray:
    """Two feet flat at x = 0 (ankle), soles on z = 0, trunk upright."""
    s = dict(DEFAULT_STANCE)
    s.update(stance or {})
    q = np.zeros(model.n)
    for side in ("l", "r"):
        for jn in ("hip_pitch", "knee", "ankle_pitch", "shoulder_pitch", "elbow"):
            q[model.q_index[f"{side}_{jn}"]] = s[jn]
    # flat feet: the foot pitch is the sum of the leg pitches
    for side in ("l", "r"):
        q[model.q_index[f"{side}_ankle_pitch"]] = -(q[model.q_index[f"{side}_hip_pitch"]]
                                                   + q[model.q_index[f"{side}_knee"]])
    ankle = model.point("l_ankle_pitch", q)
    sole_z = min(model.point("LF_toe", q)[1], model.point("LF_heel", q)[1])
    q[0] -= ankle[0]
    q[1] -= sole_z
    return q


def rigid_rotation_velocity(model: PlanarModel, q, mode: Mode, env: Environment | None = None) -> np.ndarray:
    """Unit-rate rigid rotation about the mean ankle of the feet in contact
    (or about the mean contact point if no foot is in contact), projected onto
    the contact-consistent velocities of ``mode`` (eq. 10)."""
    q = np.asarray(q, float)
    feet = [e for e in mode if e in FEET]
    if feet:
        pivots = [model.point(("l_" if e == "LF" else "r_") + "ankle_pitch", q) for e in feet]
    else:
        pivots = [model.point(e, q) for e in mode]
    pivot = np.mean(pivots, axis=0)
    root = q[:2]
    d = root - pivot
    v = np.zeros(model.n)
    # d/dt of a point rotated about +y by rate w: w * (dz, -dx)
    v[0], v[1], v[2] = d[1], -d[0], 1.0
    for e in feet:  # keep the feet fixed in the world
        v[model.q_index[("l_" if e == "LF" else "r_") + "ankle_pitch"]] = -1.0
    rows = C.contact_rows(mode, env or Environment())
    if rows:
        v, _ = C.impact_map(model, q, v, rows)
    return v


def velocity_for_energy(model: PlanarModel, q, mode: Mode, kinetic_energy: float, direction: float = 1.0,
                        env: Environment | None = None) -> np.ndarray:
    """Velocity with E_K = kinetic_energy, toppling forward (+1) or backward (-1)."""
    if kinetic_energy < 0 or not math.isfinite(kinetic_energy):
        raise ValueError("kinetic energy must be finite and >= 0")
    v = rigid_rotation_velocity(model, q, mode, env)
    ke1 = model.kinetic_energy(q, v)
    if ke1 <= 1e-12:
        raise ValueError("the contact mode leaves no rigid rotation (robot fully constrained)")
    sign = 1.0 if direction >= 0 else -1.0
    return sign * math.sqrt(kinetic_energy / ke1) * v
