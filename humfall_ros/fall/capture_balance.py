"""The capture balance after a captured protective step (ours; paper 1 stops at the step's touchdown).

From the touchdown of a step whose Q2 the decision predicted inside the new support polygon
(``fall.controller.SafeFallController``, phase ``landed``): a settle posture (both soles flat where they landed,
the CoM over their middle or over the segment between their centres nearest the capture point, the trunk
upright; the shared IK, ``model.ik``) is blended in over ``settle_s``, and the ankle strategy
(``control.standing.StandingBalance``) holds the CoM at that reference on top of it. Options (off by default,
session 39): a hip strategy (``control.standing.hip_flexion_profile``, scaled down with the capture point's margin
in the soles' hull at the start) and the multi-contact executor's lateral balance
(``control.standing.lateral_roll_sensed``).

Why a balance at all: holding the landed posture stiffly let the robot rock from sole to sole with a growing
amplitude (walking_push: captured in x, toppled sideways 1.2 s after touchdown); the step leaves the robot on sole
edges, and without the settle posture it rocked from one sole corner to the other until it fell.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from humfall_ros.control.contract import Observation
from humfall_ros.control.standing import StandingBalance, hip_flexion_profile, lateral_roll_sensed
from humfall_ros.control.step_control import StepController, sensed_soles
from humfall_ros.fall.geometry import nearest_on_segments
from humfall_ros.model.humanoid import SIDES, HumanoidModel, point_in_polygon_margin, support_polygon


@dataclasses.dataclass(frozen=True)
class CaptureBalanceConfig:
    """The capture balance's settings: ``SafeFallConfig.balance`` builds them from the node's declared parameters
    (each described there, with its default: ``settle_s``, ``settle_target``, ``balance_kp`` ...
    ``balance_lateral_max``)."""

    settle_s: float
    settle_target: str
    kp: float
    kd: float
    max_offset: float
    hip_flex_rad: float
    hip_rise_s: float
    hip_hold_s: float
    hip_release_s: float
    hip_margin_m: float
    lateral_gain: float
    lateral_damping: float
    lateral_max: float


class CaptureBalance:
    """One capture balance, from its first :meth:`command` (the balance's start) on.

    Attributes (set at the start): ``start`` [s]; ``margin``: the capture point's margin inside both soles' hull
    then [m] (NaN without an IMU reading); ``settle``: the settle posture's joints; ``settle_converged``: whether
    its IK converged; ``balancer``: the ankle strategy (``StandingBalance``; its ``reference`` is the CoM's, relative
    to the feet's centre)."""

    def __init__(self, model: HumanoidModel, config: CaptureBalanceConfig, stepper: StepController,
                 hold: np.ndarray):
        self.m, self.config, self.stepper = model, config, stepper
        self.balance_from = np.asarray(hold, float).copy()
        self.settle = self.balance_from.copy()
        self.start: float | None = None
        self.margin = math.nan
        self.settle_converged = False
        self.balancer: StandingBalance | None = None
        self._hip_pitch = [model.joint_index(f"{sd}_hip_pitch") for sd in SIDES]
        self._ankle_roll = [model.joint_index(f"{sd}_ankle_roll") for sd in SIDES]
        self._hip_roll = [model.joint_index(f"{sd}_hip_roll") for sd in SIDES]

    @property
    def reference(self):
        return None if self.balancer is None else self.balancer.reference

    def settled(self, time: float) -> bool:
        """Is the settle posture fully blended in at ``time`` [s] (the hand-back may come)?"""
        return self.start is not None and time - self.start >= self.config.settle_s - 1e-9

    def over(self, time: float) -> bool:
        """Is the settle posture blended in and the hip strategy (if any) back at ``time`` [s]?"""
        c = self.config
        hip = c.hip_rise_s + c.hip_hold_s + c.hip_release_s if c.hip_flex_rad > 0 else 0.0
        return self.settled(time) and time - self.start >= hip - 1e-9

    def _begin(self, obs: Observation) -> None:
        c, s = self.config, obs.state
        self.start = obs.time
        ref = None
        sensed = sensed_soles(self.m, obs.joint_position, obs.inputs.get("imu"), s.com)
        if sensed is not None:
            q, soles = sensed
            corners = np.vstack(list(soles.values()))
            mid = corners.mean(axis=0)
            self.margin = point_in_polygon_margin(np.asarray(s.capture_point, float)[:2], support_polygon(corners))
            if c.settle_target == "spine":
                mid = self.spine_point(np.asarray(s.capture_point, float)[:2])
            ref = mid - np.asarray(s.feet_center, float)[:2]
            if c.settle_s > 0:
                self.settle = self.settle_posture(q, mid)
        self.balancer = StandingBalance(self.m, dict(zip(self.m.joint_names, self.settle)), c.kp, c.kd,
                                        c.max_offset)
        self.balancer.reference = ref

    def command(self, obs: Observation) -> np.ndarray:
        """This tick's joint position targets (model order); the first call starts the balance."""
        c, s = self.config, obs.state
        if self.balancer is None:
            self._begin(obs)
        a = 1.0 if c.settle_s <= 0 else min(1.0, (obs.time - self.start) / c.settle_s)
        w = 0.5 - 0.5 * math.cos(math.pi * a)
        self.balancer.nominal = (1.0 - w) * self.balance_from + w * self.settle
        if c.hip_flex_rad > 0.0:
            # the hip strategy: both hips flex from the balance's start (hip pitch < 0 flexes), by less the deeper
            # the capture point was inside the soles' hull then (hip_margin_m)
            amp = c.hip_flex_rad
            if c.hip_margin_m > 0.0:
                depth = self.margin if math.isfinite(self.margin) else 0.0
                amp *= float(np.clip(1.0 - depth / c.hip_margin_m, 0.0, 1.0))
            flex = hip_flexion_profile(obs.time - self.start, amp, c.hip_rise_s, c.hip_hold_s,
                                       c.hip_release_s)
            self.balancer.nominal[self._hip_pitch] -= flex
        pos = self.balancer.command(s.com, s.com_velocity, s.support_polygon, s.feet_center)
        if c.lateral_gain > 0.0:
            # the ankle rolls, and the hip rolls opposite, move the CoM sideways to the segment between the soles'
            # centres
            d = lateral_roll_sensed(self.m, obs, c.lateral_gain, c.lateral_damping,
                                    c.lateral_max)
            if d is not None:
                pos = pos.copy()
                pos[self._ankle_roll] += d
                pos[self._hip_roll] -= d
                pos = np.clip(pos, self.m.limits.lower, self.m.limits.upper)
        return pos

    def spine_point(self, point) -> np.ndarray:
        """The point of the segment between the two soles' centres nearest ``point`` (after ``forward``) [m], (2,).

        The CoM goes on towards the capture point after a step; the soles' middle is on that segment, but where
        the CoM comes to rest the hull is the front sole's width around the segment, not around the middle: with
        the CoM held over the middle sideways it left the hull over its diagonal side (500 N deferred: stopped in x
        0.5 m on, toppled to the right)."""
        a, b = (self.m.sole_corners(sd)[:, :2].mean(axis=0) for sd in SIDES)
        return nearest_on_segments(point, a[None], b[None])[0][0]

    def settle_posture(self, q: np.ndarray, mid: np.ndarray) -> np.ndarray:
        """Joints that put both soles flat on the ground where they are (x, y, yaw) and the CoM over ``mid`` at its
        present height, the trunk upright (the shared IK, ``model.ik``). The step leaves the robot on sole
        edges (the swing target was pressed into the ground, the stance sole rolled): measured, it then
        rocked from one sole corner to the other until it fell."""
        from humfall_ros.model.ik import ComTask, FrameTask, OrientationTask, PostureTask

        m = self.m
        m.forward(q)
        tasks = []
        yaws = []
        for sd in SIDES:
            M = m.frame_placement(m.sole_frame[sd])
            yaw = math.atan2(M.rotation[1, 0], M.rotation[0, 0])
            yaws.append(yaw)
            flat = StepController.landing_placement(M.translation[0], M.translation[1], yaw, 0.0)
            tasks.append(FrameTask(m.sole_frame[sd], flat, weight=100.0))
        com = m.com(q)
        heading = math.atan2(sum(math.sin(y) for y in yaws), sum(math.cos(y) for y in yaws))
        tasks += [ComTask(np.array([mid[0], mid[1], com[2]]), weight=10.0),
                  OrientationTask(m.imu_frame, StepController.landing_placement(0, 0, heading).rotation, weight=1.0),
                  PostureTask(np.asarray(q, float)[7:], weight=1e-3)]
        r = self.stepper.ik.solve_to_convergence(q, tasks, dt=0.05, max_iterations=100, tolerance=1e-3)
        self.settle_converged = bool(getattr(r, "converged", False))
        return np.clip(np.asarray(r.q, float)[7:], m.limits.lower, m.limits.upper)


__all__ = ["CaptureBalance", "CaptureBalanceConfig"]
