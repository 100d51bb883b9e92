"""The stop's final posture (paper 3, §IV-C and §VI): reachable within the joint limits, else crouch, else fall back.

No rclpy, no simulator. Eq. 21 says where the CoG ends (n3 along the Major axis, 0 along the
Minor); before moving, :func:`final_posture` asks the shared whole-body IK
(:mod:`humfall_ros.model.ik`) for a posture with both feet held where they are (hard frame
tasks), the trunk upright and the CoG there, every joint ``joint_margin`` inside its URDF
limits -- the rear hip's extension limit and the knee's straight stop are the ones that bind
on long steps. When the horizontal CoG target is reachable only lower (a stretched knee or
hip), the stop plans a waist **crouch** (the paper's HRP-2 crouched above 1.8 km/h): a
quintic of the CoG height to ``clearance`` below the height the IK could reach, and the
ZMP prediction is redone with that vertical motion. If no crouch down to
``crouch_min_cog_height`` gives a reachable posture with that whole clearance, or the ZMP leaves the polygon, the
**fallback** ``min_n3_crouch`` plans with beta = -omega_f (the smallest n3 this model can give
with -omega_f <= beta: n3 equals eq. 22's bound y0 + ydot0/omega_c), with the crouch the posture
needs or, if none suffices, the deepest one, and runs it with ``feasible=False``; ``fallback: none``
keeps the nominal plan (still ``feasible=False``), to show what the prediction predicted.

This module is the IK check (:class:`PostureSolver`); the crouch search and the fallback that use it
are :func:`humfall_ros.estop.planner.settle_posture` (the planner re-plans with the crouch).
"""
from __future__ import annotations

import dataclasses
import math
import time

import numpy as np
import pinocchio as pin

from humfall_ros.estop.frame import FootPose
from humfall_ros.model.humanoid import SIDES, HumanoidModel
from humfall_ros.model.ik import ComTask, FrameTask, OrientationTask, PostureTask, WholeBodyIK


@dataclasses.dataclass(frozen=True)
class PostureCheck:
    """Outcome of one final-posture IK.

    Attributes:
        reachable: the CoG target reached with the feet held, inside the joint limits by the margin.
        q: the final configuration (nq,).
        cog_height_target: the CoG height asked for [m] above the ground.
        cog_height_reached: the CoG height of ``q`` [m] above the ground.
        com_error: horizontal CoG error of ``q`` [m].
        joint_margin: smallest joint distance to its URDF limits [rad].
        binding_joints: the joints at their (margin) limit.
        iterations: IK steps.
        solve_time: wall time [s].
    """

    reachable: bool
    q: np.ndarray
    cog_height_target: float
    cog_height_reached: float
    com_error: float
    joint_margin: float
    binding_joints: tuple[str, ...]
    iterations: int
    solve_time: float


def configuration_from_feet(model: HumanoidModel, joints, feet: dict[str, FootPose], side: str = "l") -> np.ndarray:
    """A full configuration (nq,) with ``joints`` and the base placed so foot ``side`` is at its pose."""
    q = model.configuration([0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0], np.asarray(joints, float))
    data = model.model.createData()
    pin.framesForwardKinematics(model.model, data, q)
    local = data.oMf[model.frame_ids[model.foot_link[side]]]
    world = pin.SE3(np.asarray(feet[side].rotation, float), np.asarray(feet[side].position, float))
    base = world * local.inverse()
    q[:3] = base.translation
    q[3:7] = pin.Quaternion(base.rotation).coeffs()
    return q


def _yaw_rotation(feet: dict[str, FootPose]) -> np.ndarray:
    """Upright rotation with the mean heading of the feet."""
    h = sum(np.asarray(feet[s].rotation, float)[:2, 0] for s in SIDES)
    yaw = math.atan2(h[1], h[0])
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


class PostureSolver:
    """Final-posture IK (feet fixed, trunk upright, CoG at a target) on the shared :class:`WholeBodyIK`.

    Args:
        model: the robot model.
        joint_margin: joints stay this far inside their limits [rad].
        dt: IK step [s] (the joint speed limits bound a step's motion).
        max_iterations: IK steps at most.
        tolerance: CoG / foot error that counts as reached [m].
    """

    def __init__(self, model: HumanoidModel, joint_margin: float, dt: float, max_iterations: int, tolerance: float):
        self.m = model
        self.ik = WholeBodyIK(model, position_margin=joint_margin)
        self.joint_margin = joint_margin
        self.dt = dt
        self.max_iterations = max_iterations
        self.tolerance = tolerance
        # the legs move the CoG (the paper moves the waist); the upper body holds its posture, weighted above the
        # CoG task (1e3): the stop's IK, stepping 2 ms at a time, moves the legs first (posture weight 1e-4 against
        # the upper body's 10) and ends at a leg joint's stop with the chest upright; at weight 10 here the check's
        # 60 long steps leaned the chest 0.24 rad forward instead and passed a posture the stop never takes
        legs = {n for s in SIDES for n in model.joint_names if n.startswith(f"{s}_") and
                any(k in n for k in ("hip", "knee", "ankle"))}
        self._data = model.model.createData()
        self._foot_ids = {s: model.frame_ids[model.foot_link[s]] for s in SIDES}
        self._posture_weights = np.array([1e-6 if n in legs else 1e4 for n in model.joint_names])

    def _errors(self, q, feet) -> tuple[np.ndarray, float]:
        """(CoG (3,), largest foot position error [m]) at ``q``."""
        m, d = self.m.model, self._data
        com = pin.centerOfMass(m, d, q).copy()   # runs the forward kinematics
        pin.updateFramePlacements(m, d)
        err = max(float(np.linalg.norm(d.oMf[self._foot_ids[s]].translation - feet[s].position)) for s in SIDES)
        return com, err

    def solve(self, q_seed: np.ndarray, feet: dict[str, FootPose], com_target: np.ndarray,
              ground: float) -> PostureCheck:
        """The posture from ``q_seed`` with the CoG at ``com_target`` [m] (world (3,)), ``ground`` the floor z [m]."""
        t0 = time.perf_counter()
        m = self.m
        target = np.asarray(com_target, float)
        tasks = [FrameTask(m.foot_link[s], pin.SE3(np.asarray(feet[s].rotation, float),
                                                   np.asarray(feet[s].position, float)), hard=True) for s in SIDES]
        tasks.append(ComTask(target, weight=1000.0))
        tasks.append(OrientationTask(m.root_link, _yaw_rotation(feet), weight=10.0))
        tasks.append(PostureTask(np.asarray(q_seed, float)[7:].copy(), weight=self._posture_weights))
        q = np.asarray(q_seed, float).copy()
        it = 0
        for it in range(1, self.max_iterations + 1):
            r = self.ik.solve(q, tasks, self.dt)
            step = float(np.max(np.abs(r.v))) * self.dt
            q = r.q
            com, feet_err = self._errors(q, feet)
            horiz = float(np.hypot(*(target[:2] - com[:2])))
            vert = abs(float(target[2] - com[2]))
            if horiz < self.tolerance and feet_err < self.tolerance and vert < self.tolerance:
                break
            if step < 1e-6:  # stuck at the limits
                break
        horiz = float(np.hypot(*(target[:2] - com[:2])))
        vert = abs(float(target[2] - com[2]))
        qj = q[7:]
        lo, hi = m.limits.lower, m.limits.upper
        margin = float(min(np.min(qj - lo), np.min(hi - qj)))
        binding = tuple(n for n, a, lo_, hi_ in zip(m.joint_names, qj, lo, hi)
                        if min(a - lo_, hi_ - a) < self.joint_margin + 1e-3)
        reachable = (horiz < self.tolerance and feet_err < self.tolerance and vert < self.tolerance
                     and margin >= self.joint_margin - 1e-6)
        return PostureCheck(bool(reachable), q, float(target[2] - ground), float(com[2] - ground), horiz, margin,
                            binding, it, time.perf_counter() - t0)


__all__ = ["PostureCheck", "PostureSolver", "configuration_from_feet"]
