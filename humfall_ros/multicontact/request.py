"""A ``plan_fall`` request checked and turned into the planner's initial state (no search here).

Request fields mirror humfall_interfaces/srv/PlanFall: q, v (planar, may be empty), kinetic_energy,
direction, initial_mode, wall_distance, time_budget. Used by the tree search's planner (``planner.py``) and
the library re-plan (``library.py``) alike.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from humfall_ros.multicontact import contacts as C
from humfall_ros.multicontact.initial_state import nominal_configuration, velocity_for_energy
from humfall_ros.multicontact.model import EXTREMITIES, FEET, PlanarModel
from humfall_ros.multicontact.modes import Environment, mode_label, parse_mode


@dataclasses.dataclass
class ValidRequest:
    q: np.ndarray
    v: np.ndarray
    mode: tuple
    env: Environment
    time_budget: float


class InvalidRequest(ValueError):
    pass


def _finite(name, values):
    arr = np.asarray(values, float).ravel()
    if not np.all(np.isfinite(arr)):
        raise InvalidRequest(f"{name} contains a non-finite number")
    return arr


def validate(model: PlanarModel, req: dict, cfg) -> ValidRequest:
    """Check a request and build the initial state; raises InvalidRequest(reason). ``cfg``: the
    planner's ``PlannerConfig`` (its budgets, limits, tolerances and stance)."""
    n = model.n
    q = _finite("q", req.get("q") or [])
    v = _finite("v", req.get("v") or [])
    ke = float(req.get("kinetic_energy", 0.0) or 0.0)
    direction = float(req.get("direction", 1.0) if req.get("direction", None) is not None else 1.0)
    wall = float(req.get("wall_distance", 0.0) or 0.0)
    budget = float(req.get("time_budget", 0.0) or 0.0)
    for name, x in (("kinetic_energy", ke), ("direction", direction), ("wall_distance", wall),
                    ("time_budget", budget)):
        if not math.isfinite(x):
            raise InvalidRequest(f"{name} is not a finite number")
    if len(q) not in (0, n):
        raise InvalidRequest(f"q has {len(q)} entries, expected {n} ({', '.join(model.coordinate_names)}) or none")
    if len(v) not in (0, n):
        raise InvalidRequest(f"v has {len(v)} entries, expected {n} or none")
    try:
        mode = parse_mode(req.get("initial_mode") or "LF/RF")
    except ValueError as e:
        raise InvalidRequest(f"initial_mode: {e}") from None
    env = Environment.from_distance(wall)
    if budget < 0:
        raise InvalidRequest("time_budget must be >= 0 (0: node default)")
    budget = cfg.time_budget if budget == 0 else budget
    if budget > cfg.max_time_budget:
        raise InvalidRequest(f"time_budget {budget:g} s exceeds the maximum {cfg.max_time_budget:g} s")
    if len(q) == 0:
        q = nominal_configuration(model, cfg.stance)
    # configuration: limits, penetration, wall, mode consistency
    j = q[3:]
    bad = [model.joint_names[i] for i in range(model.m)
           if j[i] < model.q_min[i] - 1e-9 or j[i] > model.q_max[i] + 1e-9]
    if bad:
        i = model.joint_names.index(bad[0])
        raise InvalidRequest(f"configuration outside joint limits: {bad[0]} = {j[i]:.3f} not in "
                             f"[{model.q_min[i]:.3f}, {model.q_max[i]:.3f}]")
    if not -math.pi <= q[2] <= math.pi:
        raise InvalidRequest("root_pitch must be in [-pi, pi]")
    pts = model.all_points(q)
    low = min(pts, key=lambda k: pts[k][1])
    if pts[low][1] < -cfg.penetration_tolerance:
        raise InvalidRequest(f"configuration penetrates the ground: {low} at z = {pts[low][1]:.3f} m")
    if env.has_wall:
        com = model.com(q)
        if env.wall_x <= com[0]:
            raise InvalidRequest(f"impossible environment: wall at x = {env.wall_x:.3f} m is behind the "
                                 f"robot's centre of mass (x = {com[0]:.3f} m)")
        front = max(pts, key=lambda k: pts[k][0])
        if pts[front][0] >= env.wall_x - cfg.penetration_tolerance:
            raise InvalidRequest(f"impossible environment: wall at x = {env.wall_x:.3f} m is inside the "
                                 f"robot ({front} at x = {pts[front][0]:.3f} m)")
    for e in EXTREMITIES:
        names = [f"{e}_toe", f"{e}_heel"] if e in FEET else [e]
        surf = env.surface_of(e)
        dist = [C.signed_distance(model, p, surf, env, q) for p in names]
        if e in mode and max(abs(x) for x in dist) > cfg.contact_tolerance:
            raise InvalidRequest(f"contact mode {mode_label(mode)} does not match the configuration: "
                                 f"{e} is {max(dist):.3f} m from the {surf}"
                                 + (" (a foot in contact must be flat)" if e in FEET else ""))
    rows = C.contact_rows(mode, env)
    if len(v) == 0:
        if ke < 0:
            raise InvalidRequest("kinetic_energy must be >= 0")
        if ke > cfg.max_kinetic_energy:
            raise InvalidRequest(f"kinetic_energy {ke:g} J exceeds the maximum {cfg.max_kinetic_energy:g} J")
        if direction == 0:
            raise InvalidRequest("direction must be +1 (forward) or -1 (backward)")
        v = velocity_for_energy(model, q, mode, ke, direction, env)
    else:
        cv = C.rows_jacobian(model, rows, q) @ v
        if len(cv) and np.abs(cv).max() > cfg.velocity_tolerance:
            raise InvalidRequest(f"velocity moves the contacts of mode {mode_label(mode)} "
                                 f"(|J v| = {np.abs(cv).max():.3f} m/s)")
    fast = [model.joint_names[i] for i in range(model.m) if abs(v[3 + i]) > model.v_max[i] + 1e-9]
    if fast:
        raise InvalidRequest(f"joint velocity above its limit: {fast[0]}")
    return ValidRequest(q=q, v=v, mode=mode, env=env, time_budget=budget)


__all__ = ["InvalidRequest", "ValidRequest", "validate"]
