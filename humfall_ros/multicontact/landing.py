"""Landing severity of a contact-adding transition (paper 2, Sec. III-A and III-E, eq. 10).

When a transition adds a contact the limb arrives with a velocity (the
touchdown velocity of its contact points, split into the surface's normal and
tangential directions) and the inelastic impact of eq. 10 turns the pre-impact
velocity q̇⁻ into q̇⁺ through the impulse Λ. What the impact costs is what
it absorbs, ΔE = E_K(q̇⁻) − E_K(q̇⁺) ≥ 0 (the energy the contact and the
limb take), and the normal impulse on the landing limb.

Limits (``LandingLimits``) per limb class, on the touchdown normal speed [m/s]
and the energy absorbed [J]; the URDF has no structural limits, so these are
configuration (config/multicontact_planner.yaml says where the defaults come
from). The tree search ranks plans whose landings break them after all others
(or refuses them).
"""
from __future__ import annotations

import dataclasses

import numpy as np

from humfall_ros.multicontact import contacts as C
from humfall_ros.multicontact.model import FEET, PlanarModel
from humfall_ros.multicontact.modes import Environment, Mode


# [m/s or J] a landing at its limit to within the NLP's tolerance (OptConfig.feasibility_tol) is within it
LIMIT_TOL = 1e-4


@dataclasses.dataclass(frozen=True)
class LandingLimits:
    """Per-limb landing limits (inf: no limit).

    Attributes:
        hand_normal_speed_max: touchdown speed of a hand into its surface [m/s].
        foot_normal_speed_max: touchdown speed of a foot point (toe or heel) into the ground [m/s].
        hand_energy_max: energy one hand landing may absorb (eq. 10) [J].
        foot_energy_max: energy one foot landing may absorb (eq. 10) [J].
    """

    hand_normal_speed_max: float = float("inf")
    foot_normal_speed_max: float = float("inf")
    hand_energy_max: float = float("inf")
    foot_energy_max: float = float("inf")

    def speed_max(self, extremity: str) -> float:
        return self.foot_normal_speed_max if extremity in FEET else self.hand_normal_speed_max

    def energy_max(self, extremity: str) -> float:
        return self.foot_energy_max if extremity in FEET else self.hand_energy_max


@dataclasses.dataclass(frozen=True)
class LandingReport:
    """One landing (a contact added by a transition), eq. 10.

    Attributes:
        limb: the extremity that lands (LF, RF, LH, RH).
        surface: 'ground' or 'wall'.
        time: touchdown time from the start of the plan [s] (nan when not on a plan).
        normal_speed: touchdown speed into the surface, the largest over the limb's points [m/s] (>= 0: approaching).
        tangential_speed: touchdown speed along the surface at the same point [m/s] (absolute value).
        pre_impact_ke: E_K just before the impact [J].
        post_impact_ke: E_K just after the impact [J].
        absorbed_energy: pre_impact_ke - post_impact_ke [J].
        normal_impulse: normal impulse on the landing limb (sum over its points) [N s].
        tangential_impulse: tangential impulse on the landing limb [N s].
        impulse_friction_ratio: |tangential| / normal impulse of the landing limb; above the friction
            coefficient the sticking impact of eq. 10 needs more friction than eq. 5 allows (the limb would slide).
        within_limits: both limits of the limb met.
        exceeded: which limits were broken ('' if none).
    """

    limb: str
    surface: str
    time: float
    normal_speed: float
    tangential_speed: float
    pre_impact_ke: float
    post_impact_ke: float
    absorbed_energy: float
    normal_impulse: float
    tangential_impulse: float
    impulse_friction_ratio: float
    within_limits: bool
    exceeded: str

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def landing_report(model: PlanarModel, q, v_minus, target_mode: Mode, limb: str, env: Environment,
                   limits: LandingLimits | None = None, time: float = float("nan")
                   ) -> tuple[LandingReport, np.ndarray]:
    """Report of ``limb`` landing at state (q, v⁻) into ``target_mode``; also returns q̇⁺ (eq. 10)."""
    limits = limits or LandingLimits()
    q = np.asarray(q, float)
    v_minus = np.asarray(v_minus, float)
    rows = C.contact_rows(target_mode, env)
    v_plus, impulse = C.impact_map(model, q, v_minus, rows)
    surface = env.surface_of(limb)
    n_dir = np.array(C.row_direction(C.ContactRow(limb, limb, surface, "n")))
    t_dir = np.array(C.row_direction(C.ContactRow(limb, limb, surface, "t")))
    points = [f"{limb}_toe", f"{limb}_heel"] if limb in FEET else [limb]
    best = None
    for p in points:
        vel = model.point_jacobian(p, q) @ v_minus
        vn, vt = -float(n_dir @ vel), abs(float(t_dir @ vel))   # approach speed (into the surface) > 0
        if best is None or vn > best[0]:
            best = (vn, vt)
    pre = model.kinetic_energy(q, v_minus)
    post = model.kinetic_energy(q, v_plus)
    imp_n = float(sum(impulse[i] for i, r in enumerate(rows) if r.extremity == limb and r.axis == "n"))
    imp_t = float(sum(impulse[i] for i, r in enumerate(rows) if r.extremity == limb and r.axis == "t"))
    exceeded = []
    # a landing NLP that bounds the touchdown speed (touchdown_speed_constraint) meets the
    # bound to IPOPT's tolerance (1.5000000038 m/s measured): that is within the limit
    if best[0] > limits.speed_max(limb) + LIMIT_TOL:
        exceeded.append(f"touchdown speed {best[0]:.2f} m/s > {limits.speed_max(limb):g} m/s")
    if pre - post > limits.energy_max(limb) + LIMIT_TOL:
        exceeded.append(f"absorbed energy {pre - post:.1f} J > {limits.energy_max(limb):g} J")
    rep = LandingReport(limb=limb, surface=surface, time=float(time), normal_speed=best[0],
                        tangential_speed=best[1], pre_impact_ke=pre, post_impact_ke=post,
                        absorbed_energy=pre - post, normal_impulse=imp_n, tangential_impulse=imp_t,
                        impulse_friction_ratio=abs(imp_t) / imp_n if imp_n > 1e-12 else float("inf"),
                        within_limits=not exceeded, exceeded="; ".join(exceeded))
    return rep, v_plus


__all__ = ["LIMIT_TOL", "LandingLimits", "LandingReport", "landing_report"]
