"""Return home, step 3 (paper 3 §V): the feet aligned by one step after the stop. No rclpy, no simulator.

After the stop (eq. 16), the joints' stop (eq. 23) and the upper body home, the robot stands with its feet
a step apart. §V: the feet are then aligned by stepping. Here one step through the walking library:

1. the foot to move is the rear one along the feet's mean heading (the one farther from the side-by-side
   stance beside the other); it lands beside the stance (front) foot at the standard step width
   (``walking.footsteps.step_width``, the model's hip spacing, plus an offset), with the stance foot's yaw, flat;
2. a ZMP reference (the walking pattern's kind: min-jerk transfers between sole centres) moves from the CoG's
   rest point onto the stance sole centre (double support), stays there through the swing (single support),
   then moves to the middle of both soles; the CoG follows from walking's ZMP preview control
   (``walking.preview.PreviewController.rollout``, Kajita 2003) at the current CoG height, starting from rest
   at the current CoG (bumpless: position and velocity continuous);
3. the swing sole follows walking's swing trajectory (``walking.swing.swing_foot``: min-jerk horizontally,
   ``apex sin^2(pi tau)`` vertically, zero velocity at lift-off and touchdown); its rotation is interpolated on
   SO(3) with the same min-jerk phase.

``plan_alignment`` returns an :class:`AlignPlan` (or None when the feet are already aligned within
``min_offset``); ``AlignPlan.sample(t)`` gives the CoG reference, the ZMP reference, the support and the
swing sole placement at ``t`` [s] after the alignment's start.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pinocchio as pin

from humfall_ros.model.humanoid import SIDES, HumanoidModel
from humfall_ros.walking.footsteps import other, step_width
from humfall_ros.walking.preview import PreviewController
from humfall_ros.walking.swing import min_jerk, swing_foot


@dataclasses.dataclass(frozen=True)
class AlignSettings:
    """Timing and geometry of the alignment step (config/estop_planner.yaml ``align_*``).

    Attributes:
        lead_time: the ZMP reference held at the CoG's rest point first, so the preview (which anticipates its
            reference) starts from rest without a jump of its ZMP [s].
        shift_time: CoG transfer onto the stance sole, and back to the middle afterwards [s].
        load_time: double support with the ZMP on the stance sole before lift-off [s].
        swing_time: the single support [s].
        settle_time: double support after the return before the step counts as done [s].
        apex: swing sole height at mid-swing [m].
        unload_height: during the load phase the swing sole's target rises this much (min-jerk) before the
            swing, so the position-servoed legs let go of the internal force between the feet gradually, not in
            the lift-off tick [m].
        width_offset: added to the model's hip spacing to give the final lateral foot distance [m].
        min_offset: feet closer than this to side by side (along and across) are not stepped [m].
        preview_horizon: preview time of the ZMP preview control [s]; preview_r: its jerk weight.
    """

    lead_time: float = 1.0
    shift_time: float = 0.8
    load_time: float = 0.2
    swing_time: float = 0.8
    settle_time: float = 1.0
    apex: float = 0.04
    unload_height: float = 0.003
    width_offset: float = 0.0
    min_offset: float = 0.01
    preview_horizon: float = 1.6
    preview_r: float = 1e-7


@dataclasses.dataclass(frozen=True)
class AlignSample:
    """The alignment's references at one instant (world).

    Attributes:
        com, com_velocity: CoG reference [m], [m/s] (3,) (z constant).
        zmp: the preview's cart-table ZMP [m] (3,), z = ground; zmp_ref: the ZMP reference [m] (3,).
        support: "double", or "single_l" / "single_r" (the stance side).
        swing: the swing sole's placement (sole frame), ``pin.SE3``; swing_velocity: its linear velocity [m/s] (3,).
        done: the whole step, return and settle are over.
    """

    com: np.ndarray
    com_velocity: np.ndarray
    zmp: np.ndarray
    zmp_ref: np.ndarray
    support: str
    swing: pin.SE3
    swing_velocity: np.ndarray
    done: bool


def _yaw(R: np.ndarray) -> float:
    return math.atan2(R[1, 0], R[0, 0])


def _rot_z(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclasses.dataclass(frozen=True)
class AlignPlan:
    """One alignment step (module docstring). Times in [s] after the alignment's start.

    Attributes:
        stance, swing: sides.
        stance_sole, swing_start, swing_end: sole placements (``pin.SE3``, world).
        heading: the feet's mean heading [rad]; width: the final lateral distance of the sole frames [m].
        offset_before: the swing sole's offset from its side-by-side place along the heading [m] (signed, behind
            < 0); lateral_before: its lateral distance to the stance sole minus ``width`` [m].
        t_lift, t_touch, t_return_end, duration: lift-off, touchdown, end of the CoG's return, end [s];
        t_load: the end of the transfer onto the stance sole (the load phase runs to ``t_lift``) [s].
        dt: sample period [s]; com_z: CoG height (world z) [m]; ground: the sole height [m].
        states: preview-control CoG states (K, 3, 2) (c, dc, ddc per x, y); zmp_ref: (K, 2) [m].
        apex: swing apex [m].
    """

    stance: str
    swing: str
    stance_sole: pin.SE3
    swing_start: pin.SE3
    swing_end: pin.SE3
    heading: float
    width: float
    offset_before: float
    lateral_before: float
    t_lift: float
    t_touch: float
    t_return_end: float
    duration: float
    dt: float
    com_z: float
    ground: float
    states: np.ndarray
    zmp_ref: np.ndarray
    apex: float
    omega: float = dataclasses.field(default=math.nan)
    t_load: float = dataclasses.field(default=math.nan)
    unload: float = 0.0

    def swing_ankle_weight(self, t: float) -> float:
        """How much of the stabiliser's ankle offsets the swing ankle gets at ``t`` [s] (1 in double support, 0 in
        the single support; ramped over the load phase before lift-off and as long after touchdown, so a sole
        still on the ground is never turned in one tick)."""
        ramp = max(self.t_lift - self.t_load, 1e-9)
        if t <= self.t_load:
            return 1.0
        if t < self.t_lift:
            return float(1.0 - (t - self.t_load) / ramp)
        if t < self.t_touch:
            return 0.0
        return float(min(1.0, (t - self.t_touch) / ramp))

    def sample(self, t: float) -> AlignSample:
        """The references ``t`` [s] after the start (clamped to [0, duration])."""
        k = int(min(max(round(t / self.dt), 0), len(self.states) - 1))
        c = self.states[k]
        com = np.array([c[0, 0], c[0, 1], self.com_z])
        vel = np.array([c[1, 0], c[1, 1], 0.0])
        if t >= self.duration:                # the end is at rest by construction: exactly
            vel = np.zeros(3)
        z = c[0] - c[2] / self.omega ** 2
        zmp = np.array([z[0], z[1], self.ground])
        zr = np.array([*self.zmp_ref[k], self.ground])
        t_ss = self.t_touch - self.t_lift
        up = np.array([0.0, 0.0, self.unload])
        if t < self.t_lift:
            support, sv = "double", np.zeros(3)
            swing = self.swing_start
            if t > self.t_load and self.unload > 0:
                tl = self.t_lift - self.t_load
                s, ds = min_jerk((t - self.t_load) / tl)
                swing = pin.SE3(self.swing_start.rotation, self.swing_start.translation + s * up)
                sv = ds / tl * up
        elif t < self.t_touch:
            support = f"single_{self.stance}"
            tau = (t - self.t_lift) / t_ss
            pos, _, sv, _ = swing_foot(self.swing_start.translation + up, self.swing_end.translation, 0.0, 0.0,
                                       self.apex, tau, t_ss)
            s, _ = min_jerk(tau)
            R0, R1 = self.swing_start.rotation, self.swing_end.rotation
            swing = pin.SE3(R0 @ pin.exp3(s * pin.log3(R0.T @ R1)), pos)
        else:
            support, swing, sv = "double", self.swing_end, np.zeros(3)
        return AlignSample(com, vel, zmp, zr, support, swing, sv, t >= self.duration)


def rear_side(sole_centers: dict, heading: float) -> str:
    """The side whose sole centre is further back along ``heading`` [rad]."""
    h = np.array([math.cos(heading), math.sin(heading)])
    return min(SIDES, key=lambda s: float(np.asarray(sole_centers[s], float)[:2] @ h))


def side_by_side_offsets(soles: dict, heading: float, width: float, stance: str) -> tuple[float, float]:
    """(along, lateral) offset [m] of the other sole (frame origin) from its place beside ``stance``: along the
    heading (signed) and across it (the lateral distance minus ``width``)."""
    sw = other(stance)
    h = np.array([math.cos(heading), math.sin(heading)])
    n = np.array([-h[1], h[0]])                                  # to the left
    d = np.asarray(soles[sw].translation, float)[:2] - np.asarray(soles[stance].translation, float)[:2]
    return float(d @ h), float(abs(d @ n) - width)


def plan_alignment(model: HumanoidModel, soles: dict, sole_centers: dict, com, dt: float,
                   settings: AlignSettings | None = None) -> AlignPlan | None:
    """Plan the alignment step (module docstring).

    Args:
        model: the robot model (step width: ``walking.footsteps.step_width``).
        soles: side -> the sole frame's placement (``pin.SE3``, world) where the feet stand.
        sole_centers: side -> the sole rectangle's centre [m] (3,) (the ZMP points).
        com: the CoG [m] (3,) at the start, at rest.
        dt: sample period [s].
        settings: :class:`AlignSettings`.
    Returns:
        The plan, or None when the feet are already side by side within ``min_offset`` (along and across).
    Raises:
        ValueError: non-finite input or a CoG not above the soles.
    """
    st = settings or AlignSettings()
    com = np.asarray(com, float)
    if not np.all(np.isfinite(com)) or not all(np.all(np.isfinite(soles[s].translation)) for s in SIDES):
        raise ValueError("alignment: non-finite CoG or feet")
    yaws = {s: _yaw(soles[s].rotation) for s in SIDES}
    heading = math.atan2(sum(math.sin(y) for y in yaws.values()), sum(math.cos(y) for y in yaws.values()))
    width = step_width(model) + st.width_offset
    swing = rear_side(sole_centers, heading)
    stance = other(swing)
    along, lateral = side_by_side_offsets(soles, heading, width, stance)
    if abs(along) < st.min_offset and abs(lateral) < st.min_offset:
        return None
    ground = 0.5 * sum(float(sole_centers[s][2]) for s in SIDES)
    z_c = float(com[2] - ground)
    if z_c <= 0.1:
        raise ValueError(f"alignment: CoG height {z_c:.3f} m above the soles is not a standing robot")
    # the swing sole's target: beside the stance sole at the step width, with the stance yaw, flat
    sy = yaws[stance]
    side = 1.0 if swing == "l" else -1.0
    ss = soles[stance]
    target = ss.translation + _rot_z(sy) @ np.array([0.0, side * width, 0.0])
    target[2] = ss.translation[2]
    swing_end = pin.SE3(_rot_z(sy), target)
    # the swing's sole centre lands where the sole frame's offset to it puts it (same geometry, stance yaw)
    c_off = swing_end.rotation @ (soles[swing].rotation.T @ (np.asarray(sole_centers[swing], float)
                                                             - soles[swing].translation))
    end_center = target + c_off
    p0 = com[:2].copy()
    p_stance = np.asarray(sole_centers[stance], float)[:2]
    p_mid = 0.5 * (p_stance + end_center[:2])
    n = lambda s: max(1, round(s / dt))                        # noqa: E731
    n_lead = n(st.lead_time)
    n_shift, n_load, n_swing, n_settle = n(st.shift_time), n(st.load_time), n(st.swing_time), n(st.settle_time)
    pc = PreviewController(dt, z_c, st.preview_horizon, r=st.preview_r)
    n_prev = pc.n_preview

    def transfer(a, b, k):
        s = np.array([min_jerk((i + 1) / k)[0] for i in range(k)])
        return a + s[:, None] * (b - a)

    ref = np.vstack([np.repeat(p0[None], n_lead, axis=0), transfer(p0, p_stance, n_shift),
                     np.repeat(p_stance[None], n_load + n_swing, axis=0), transfer(p_stance, p_mid, n_shift),
                     np.repeat(p_mid[None], n_settle + n_prev + 1, axis=0)])
    pc.reset(p0)
    states = pc.rollout(ref)
    states = np.concatenate([np.array([[p0, [0.0, 0.0], [0.0, 0.0]]]), states], axis=0)   # k = 0: the start
    zmp_ref = ref[:len(states)]
    t_lift = (n_lead + n_shift + n_load) * dt
    t_touch = t_lift + n_swing * dt
    t_ret = t_touch + n_shift * dt
    duration = t_ret + n_settle * dt
    return AlignPlan(stance, swing, ss, soles[swing], swing_end, heading, width, along, lateral, t_lift, t_touch,
                     t_ret, duration, dt, float(com[2]), ground, states, zmp_ref, st.apex, pc.omega,
                     (n_lead + n_shift) * dt, st.unload_height)


__all__ = ["AlignPlan", "AlignSample", "AlignSettings", "plan_alignment", "rear_side", "side_by_side_offsets"]
