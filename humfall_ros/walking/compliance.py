"""Sole sinkage feed-forward: the planned load of each foot, pressed into its compliant contact. No rclpy.

The joints are stiff position servos, the soles are not: each sole touches the ground through a
spring-damper contact (the URDF's ``<contact>`` stiffness ``k`` and damping ``c`` at each of the
sole's corners, as the simulator's box-on-plane contact has them). With both soles commanded at
z = 0 in double support, the robot's joint posture fixes the feet's *relative* heights, so the only
way the load can move from the rear to the front foot is the whole robot rocking on those springs
(measured at 1 km/h: a ~1 mrad rocking mode of the robot on its soles, excited by the 0.1 s ZMP
transfer and the landing; the CoP lags the reference by 15 cm in mid double support and overshoots
by 7-13 cm at the switch to single support, docs/walking.md phase 4).

Feed-forward: each foot's target is pressed into the ground by the sinkage its planned load needs,
``delta_s = (f_s - tau df_s/dt) / K`` (``K = n k`` for ``n`` corner springs, ``tau = c / k``; the
damper's share subtracted so ``K delta + C d(delta)/dt = f``). The planned loads split the weight
by the reference ZMP: projected on the segment between the two sole centres,
``alpha = (p - a)·(b - a) / |b - a|^2`` (clipped to [0, 1]) gives ``f_b = alpha m g``,
``f_a = (1 - alpha) m g``; in single support the stance sole carries all. The planned motion is then
also an equilibrium of the robot on its soles (no rocking needed), and a landing foot meets the
ground at the height the load split wants.
"""
from __future__ import annotations

import dataclasses
import xml.etree.ElementTree as ET

import numpy as np

from humfall_ros.model.humanoid import SIDES, HumanoidModel


def sole_contact(model: HumanoidModel) -> tuple[float, float]:
    """(vertical stiffness [N/m], damping [N s/m]) of one sole: the URDF ``<contact>`` stiffness and damping of
    the foot link at each sole corner, times the corner count. (0, 0) when the URDF states none (rigid)."""
    root = ET.parse(model.urdf_path).getroot()
    link = root.find(f"link[@name='{model.foot_link[SIDES[0]]}']")
    contact = link.find("contact") if link is not None else None
    if contact is None or contact.find("stiffness") is None:
        return 0.0, 0.0
    n = len(model.sole_corners_local[SIDES[0]])
    k = float(contact.find("stiffness").get("value"))
    d = contact.find("damping")
    return n * k, n * (float(d.get("value")) if d is not None else 0.0)


@dataclasses.dataclass(frozen=True)
class FootShare:
    """One sole's share of a ZMP reference: normal force [N] and that sole's own CoP (x, y) [m]."""

    force: float
    cop: np.ndarray


def distribute_zmp(zmp, sole_centres: dict, stance: str | None, total: float) -> dict:
    """side -> :class:`FootShare` of the reference ZMP ``zmp`` [m] (xy) carrying ``total`` [N].

    The wrench distribution of Kajita et al. 2010 ("Biped walking stabilization based on linear inverted
    pendulum tracking", IROS 2010, sec. III-B; its ankle torques are here each sole's own CoP): in double
    support the ZMP's projection on the segment ``a -> b`` between the sole centres, ``alpha = (p - a)·(b - a)
    / |b - a|^2`` clipped to [0, 1], splits the force, ``f_b = alpha F``, ``f_a = (1 - alpha) F``; the part of
    ``p`` off that clipped point, ``r = p - (a + alpha (b - a))``, moves both soles' CoPs alike (each sole's CoP
    = its centre + r), so ``(f_a p_a + f_b p_b) / F = p`` exactly. In single support the stance sole carries
    ``total`` with its CoP on ``p``; the other sole carries 0 (its CoP: its centre)."""
    p = np.asarray(zmp, float)[:2]
    c = {s: np.asarray(sole_centres[s], float)[:2] for s in SIDES}
    if stance is not None:
        return {s: FootShare(float(total), p.copy()) if s == stance else FootShare(0.0, c[s].copy()) for s in SIDES}
    a, b = c[SIDES[0]], c[SIDES[1]]
    ab = b - a
    n2 = float(ab @ ab)
    alpha = 0.5 if n2 < 1e-12 else float(np.clip((p - a) @ ab / n2, 0.0, 1.0))
    r = p - (a + alpha * ab)
    return {SIDES[0]: FootShare((1.0 - alpha) * total, a + r), SIDES[1]: FootShare(alpha * total, b + r)}


def planned_loads(zmp, sole_centres: dict, stance: str | None, weight: float) -> dict:
    """Normal load of each sole [N] for the reference ZMP ``zmp`` [m] (xy): ``stance`` carries ``weight`` in single
    support; in double support the split of the module docstring (:func:`distribute_zmp`'s forces).
    ``sole_centres``: side -> (x, y) [m]."""
    return {s: sh.force for s, sh in distribute_zmp(zmp, sole_centres, stance, weight).items()}


def sole_sinkage(loads: dict, loads_next: dict, dt: float, stiffness: float, damping: float) -> dict:
    """side -> sinkage [m] (>= 0: the sole's target goes that far below the ground) for the planned loads [N] of
    this tick and the next (``dt`` [s] apart): ``(f - tau df/dt) / K``, ``tau = C / K`` (module docstring)."""
    if stiffness <= 0:
        return {s: 0.0 for s in loads}
    tau = damping / stiffness
    return {s: max(0.0, (f - tau * (loads_next[s] - f) / dt) / stiffness) for s, f in loads.items()}


__all__ = ["FootShare", "distribute_zmp", "planned_loads", "sole_contact", "sole_sinkage"]
