"""The walking stabiliser: DCM feedback through the CoM reference plus stance-ankle CoP damping. No rclpy.

The joints are stiff position servos, so neither the ZMP nor the ankle torque is commanded
directly. Two loops act on the *measured* state (the estimator's values, never ground truth),
all relative to the feet (leg odometry drifts in the world, the feet drift with it):

1. **DCM (capture point) feedback to the CoM reference**: with the capture-point error
   ``e = (xi - f)_measured - (xi - f)_reference`` (xi = c + dc/dt / omega, f = mid-point of the
   ankles), the CoM handed to the IK is ``c_ref - k_dcm e`` (clipped to ``com_feedback_max``).
   A stiff-jointed robot whose CoM reference moves against its capture-point error has to push
   its ZMP the other way (the ZMP -> CoM relation of the LIPM, ``ddc = omega^2 (c - p)``), which is
   the DCM control law ``p = p_ref + (1 + k / omega) e`` realised through the servos.
2. **Ankle damping control of the CoP** (single support): the stance ankle pitch and roll are
   offset by ``d(theta)/dt = k_cop (p_ref - p_measured) - theta / T`` (a leaky integral, so the
   offset returns to 0 on the swing foot before it lands; in double support faster, with
   ``T_ds``: a rear foot still tilted by its stance offset loads its toe and the soles' planned
   sinkage no longer holds the load split), clipped to
   ``walk_ankle_max_offset``. Ankle pitch > 0 turns the toes down (CoP forward), ankle roll > 0
   lifts the sole's +y edge (CoP towards -y); errors are taken in the stance sole's axes.
3. **CoP integral** (single support): the CoM reference is shifted by ``Δc`` with
   ``d(Δc)/dt = -k_i (p_measured - p_ref)`` (feet relative, stance sole axes, clipped to
   ``zmp_integral_max``; held in double support, where the CoP error is the load distribution). A
   slowly varying CoM shift moves the ZMP of the commanded motion by the same amount (cart-table:
   ``p = c - dd(c) / omega^2``), so a steady CoP bias of the simulated robot (measured +4.5 cm
   forward at 1 km/h while the multi-body ZMP of the actual motion is on the reference, see
   docs/walking.md) is removed step after step.
4. **Foot height difference control of the CoP** (double support; the "foot force difference
   control" of Kajita et al., IROS 2010, on the CoP instead of the two foot forces, which the
   estimator does not give): the stiff-jointed robot moves its load between the feet only by
   pressing one sole deeper into its compliant contact than the other, so the front sole's target
   goes down by ``u / 2`` and the rear one's up by ``u / 2`` with
   ``du/dt = -k_fh e_a - u / T_fh``, ``e_a`` the feet-relative CoP error along the rear -> front
   sole-centre axis of the reference (clipped to ``foot_height_max``; leaks to 0 in single support).

   **With per-foot forces** (``foot_force_gain`` > 0: the estimator's per-foot normal forces, each from its
   own ankle F/T sensor) loop 4 is Kajita et al.'s foot force difference control itself (IROS 2010, eq. 13-14;
   as jrl-umi3218/lipm_walking_controller's ``Stabilizer::updateFootForceDifferenceControl``): the CoP
   alone cannot tell the load split (the total CoP can sit on its reference while the rear foot still
   carries 100-200 N and the front foot's own CoP is ahead of its centre, docs/walking.md phase 5), the two
   forces can. ``dz = z_l - z_r`` (sole target heights) with
   ``d(dz)/dt = k_f ((f_l - f_r) - (f_l^d - f_r^d)) - dz / T_fh``: the overloaded sole goes up, the other
   down, ``+-dz / 2``. The references ``f^d`` split the *measured* total ``f_l + f_r`` by the reference ZMP
   (:func:`humfall_ros.walking.compliance.distribute_zmp`), so the robot's vertical acceleration is not read
   as a split error. Acts while the estimator sees both feet in contact in double support, leaks otherwise.
5. **Per-foot CoP damping** (double support, ``foot_cop_gain`` > 0): each sole carrying more than
   ``foot_cop_min_force`` turns its ankle towards its own reference CoP (the distribution's, the sole centre
   shifted with the ZMP reference off the feet axis) with loop 2's law on that foot's own measured CoP,
   ``d(theta)/dt = k (f_s / W) (p^d_s - p_s) - theta / T_ds`` (``W`` the robot's weight: the torque error
   ``f_s (p^d_s - p_s)`` of Kajita et al. 2010's ankle torque control per foot, normalised): so
   the front sole's CoP is at its centre, not at an edge, when the rear foot lifts and it becomes the stance.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from humfall_ros.dynamics.pendulum import GRAVITY
from humfall_ros.model.humanoid import SIDES, HumanoidModel
from humfall_ros.walking.compliance import distribute_zmp


@dataclasses.dataclass
class StabilizerOutput:
    """com_offset: added to the CoM reference [m] (3,); ankle: side -> (pitch, roll) offsets [rad]."""

    com_offset: np.ndarray
    ankle: dict
    foot_z: dict                      # side -> sole target height offset [m] (loop 4)
    capture_point_error: np.ndarray   # [m] (2,), feet relative
    zmp_error: np.ndarray             # measured CoP - reference ZMP, feet relative [m] (2,)


class WalkingStabilizer:
    """See the module docstring. Gains in :class:`LocomotionConfig` units."""

    def __init__(self, model: HumanoidModel, dt: float, dcm_gain: float, com_feedback_max: float,
                 cop_gain: float, cop_time_constant: float, ankle_max_offset: float, zmp_integral_gain: float = 0.0,
                 zmp_integral_max: float = 0.06, foot_height_gain: float = 0.0,
                 foot_height_time_constant: float = 0.05, foot_height_max: float = 0.001,
                 cop_time_constant_ds: float | None = None, foot_force_gain: float = 0.0,
                 foot_cop_gain: float = 0.0, foot_cop_min_force: float = 150.0):
        self.dt = float(dt)
        self.foot_force_gain = float(foot_force_gain)
        self.foot_cop_gain = float(foot_cop_gain)
        self.foot_cop_min_force = float(foot_cop_min_force)
        self.weight = model.total_mass * GRAVITY
        self.foot_height_gain = float(foot_height_gain)
        self.foot_height_tau = float(foot_height_time_constant)
        self.foot_height_max = float(foot_height_max)
        self.zmp_integral_gain = float(zmp_integral_gain)
        self.zmp_integral_max = float(zmp_integral_max)
        self.dcm_gain = float(dcm_gain)
        self.com_feedback_max = float(com_feedback_max)
        self.cop_gain = float(cop_gain)
        self.tau = float(cop_time_constant)
        self.tau_ds = self.tau if cop_time_constant_ds is None else float(cop_time_constant_ds)
        self.ankle_max = float(ankle_max_offset)
        self.pitch_index = {s: model.joint_index(f"{s}_ankle_pitch") for s in SIDES}
        self.roll_index = {s: model.joint_index(f"{s}_ankle_roll") for s in SIDES}
        self.reset()

    def reset(self) -> None:
        self.ankle = {s: np.zeros(2) for s in SIDES}
        self.zmp_integral = np.zeros(2)   # CoM shift of the CoP integral, in the stance sole's axes [m]
        self.foot_height = 0.0            # u of loop 4 [m]: front sole down u / 2, rear up u / 2
        self.front: str | None = None     # the front foot of the last double support
        self.foot_dz = 0.0                # dz = z_l - z_r of loop 4 with forces [m]
        self.force_error = 0.0            # (f_l - f_r) - (f_l^d - f_r^d) of the last tick [N] (0: loop idle)

    def update(self, measured_cp, measured_cop, measured_feet_center, ref_cp, ref_zmp, ref_feet_center,
               stance: str | None, stance_yaw: float, sole_centres: dict | None = None,
               transfer_to: str | None = None, swing_loaded: bool = False, foot_forces: dict | None = None,
               foot_cops: dict | None = None, contacts: dict | None = None) -> StabilizerOutput:
        """One tick. Positions [m] in their own frames (measured: the estimator's world, reference:
        the pattern's); ``stance``: the single-support foot or None (double support);
        ``sole_centres``: side -> reference sole centre (x, y) [m], ``transfer_to``: the foot the double
        support's ZMP reference moves onto (loop 4; None: loop 4 leaks); ``swing_loaded``: the estimator
        sees the swing foot in contact (an early touchdown): loops 2 and 3 hold off, since the measured
        CoP is then no longer the stance foot's alone (winding the stance ankle up against it tilted
        the rear foot by 0.5 deg at an early touchdown, which an e-stop then took over).
        ``foot_forces`` / ``foot_cops`` / ``contacts``: side -> the estimator's per-foot normal force [N], own CoP
        [m] (measured frame) and contact flag, for loops 4 (with forces) and 5; None: those loops leak."""
        mf = np.asarray(measured_feet_center, float)[:2]
        rf = np.asarray(ref_feet_center, float)[:2]
        e_cp = (np.asarray(measured_cp, float)[:2] - mf) - (np.asarray(ref_cp, float)[:2] - rf)
        e_zmp = (np.asarray(measured_cop, float)[:2] - mf) - (np.asarray(ref_zmp, float)[:2] - rf)
        off = np.clip(-self.dcm_gain * e_cp, -self.com_feedback_max, self.com_feedback_max)
        c, s = math.cos(stance_yaw), math.sin(stance_yaw)
        e_local = np.array([c * e_zmp[0] + s * e_zmp[1], -s * e_zmp[0] + c * e_zmp[1]])
        ss = stance if not swing_loaded else None   # loops 2 and 3 act on the stance foot's CoP only
        if ss is not None and self.zmp_integral_gain > 0:  # 3. CoP integral (single support only)
            self.zmp_integral = self.zmp_integral - self.dt * self.zmp_integral_gain * e_local
            n = float(np.linalg.norm(self.zmp_integral))
            if n > self.zmp_integral_max:
                self.zmp_integral *= self.zmp_integral_max / n
        zi = self.zmp_integral
        off = off + np.array([c * zi[0] - s * zi[1], s * zi[0] + c * zi[1]])
        both = (stance is None and foot_forces is not None and sole_centres is not None
                and (contacts is None or all(contacts[sd] for sd in SIDES)))
        shares = distribute_zmp(ref_zmp, sole_centres, None, sum(foot_forces[sd] for sd in SIDES)) if both else None
        for side in SIDES:
            a = self.ankle[side]
            rate = -a / (self.tau if stance is not None else self.tau_ds)
            if side == ss:
                rate = rate + self.cop_gain * np.array([-e_local[0], e_local[1]])
            elif (shares is not None and self.foot_cop_gain > 0 and foot_cops is not None
                  and foot_forces[side] > self.foot_cop_min_force):   # 5. per-foot CoP damping (double support)
                e_s = (np.asarray(foot_cops[side], float)[:2] - mf) - (shares[side].cop - rf)
                cy, sy = math.cos(stance_yaw), math.sin(stance_yaw)
                e_s = np.array([cy * e_s[0] + sy * e_s[1], -sy * e_s[0] + cy * e_s[1]])
                # on the ankle torque error f_s (p_s - p^d_s) / W: at full load loop 2's law, and a rate of
                # correction that does not grow as the sole unloads (its CoP moves ~K_rot / f_s per radian)
                w_s = foot_forces[side] / max(self.weight, 1e-9)
                rate = rate + self.foot_cop_gain * w_s * np.array([-e_s[0], e_s[1]])
            self.ankle[side] = np.clip(a + self.dt * rate, -self.ankle_max, self.ankle_max)
        # loop 4 on the forces when they are given (the controller gates them by speed), else on the CoP;
        # the idle one leaks, so a speed change hands over without a jump
        forces = self.foot_force_gain > 0 and foot_forces is not None
        fz_f = self._foot_force_difference(foot_forces, shares if forces else None)
        fz_c = self._foot_height(e_zmp, stance, sole_centres, None if forces else transfer_to)
        foot_z = {sd: fz_c[sd] + fz_f[sd] for sd in SIDES}
        return StabilizerOutput(np.array([off[0], off[1], 0.0]), {k: v.copy() for k, v in self.ankle.items()},
                                foot_z, e_cp, e_zmp)

    def _foot_height(self, e_zmp, stance, sole_centres, transfer_to) -> dict:
        """Loop 4 (module docstring): side -> sole target height offset [m]."""
        u = self.foot_height
        rate = -u / self.foot_height_tau
        if stance is None and transfer_to is not None and sole_centres is not None and self.foot_height_gain > 0:
            self.front = transfer_to
            rear = SIDES[0] if transfer_to == SIDES[1] else SIDES[1]
            ab = np.asarray(sole_centres[transfer_to], float)[:2] - np.asarray(sole_centres[rear], float)[:2]
            n = float(np.linalg.norm(ab))
            if n > 1e-6:
                rate = rate - self.foot_height_gain * float(np.asarray(e_zmp, float)[:2] @ ab) / n
        self.foot_height = float(np.clip(u + self.dt * rate, -self.foot_height_max, self.foot_height_max))
        if self.front is None:
            return {s: 0.0 for s in SIDES}
        rear = SIDES[0] if self.front == SIDES[1] else SIDES[1]
        return {self.front: -0.5 * self.foot_height, rear: 0.5 * self.foot_height}

    def _foot_force_difference(self, foot_forces: dict | None, shares: dict | None) -> dict:
        """Loop 4 with per-foot forces (module docstring): side -> sole target height offset [m]."""
        dz = self.foot_dz
        rate = -dz / self.foot_height_tau
        self.force_error = 0.0
        if shares is not None:
            l, r = SIDES
            self.force_error = (foot_forces[l] - foot_forces[r]) - (shares[l].force - shares[r].force)
            rate += self.foot_force_gain * self.force_error   # the overloaded sole goes up
        self.foot_dz = float(np.clip(dz + self.dt * rate, -self.foot_height_max, self.foot_height_max))
        return {SIDES[0]: 0.5 * self.foot_dz, SIDES[1]: -0.5 * self.foot_dz}

    def apply(self, q_joints: np.ndarray, out: StabilizerOutput) -> np.ndarray:
        """Joint targets with the ankle offsets added (a copy)."""
        q = np.array(q_joints, float)
        for side in SIDES:
            q[self.pitch_index[side]] += out.ankle[side][0]
            q[self.roll_index[side]] += out.ankle[side][1]
        return q


__all__ = ["StabilizerOutput", "WalkingStabilizer"]
