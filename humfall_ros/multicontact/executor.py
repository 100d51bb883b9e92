"""multicontact_executor: a plan of the planar fall planner executed on the 3-D robot
(issue 14; paper 2 only re-simulated its plans in its own planar model).

A controller under the contract (``humfall_ros.control.contract``), source
``"multicontact"``: from its first tick it tracks the plan's sagittal joint
trajectories (the planar model's joints: hip pitch, knee, ankle pitch, shoulder
pitch, elbow of both sides, by name in the 3-D model's joint order) with
position and velocity targets from the plan's splines (cubic Hermite on (q, q̇)
between knots, eq. 7); every other joint is held where it was at the first tick.
Segments follow each other at their planned durations, with the **contact events**
of the feet as the switch when the centroidal state sees them: a transition that
lands a foot ends early when that foot is loaded before its planned end, and its
last knot is held (up to ``landing_wait``) while the foot is still in the air at
its planned end. Hands have no contact flag in the observation, so hand landings
switch at their planned times. After the last segment the final posture is held.
"""
from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial.transform import Rotation

from humfall_ros.control.contract import JointTargets, Observation
from humfall_ros.multicontact.collocation import Segment, hermite_eval
from humfall_ros.multicontact.model import FEET


@dataclasses.dataclass(frozen=True)
class ExecutorConfig:
    """Attributes:
        landing_wait: longest hold of a foot landing's last knot waiting for touchdown [s].
        early_switch: a foot touchdown this close to the planned end (or later) may end the segment [s].
    """

    landing_wait: float = 0.2
    early_switch: float = 0.15


class MulticontactExecutor:
    """Tracks a multi-contact plan (``segments``: transitions then the terminal self-motion).

    Args:
        segments: the plan (``FallPlanner.plan(...)["segments"]`` or ``Segment.from_dict``).
        planar_joint_names: joint names of the plan's actuated coordinates (``PlanarModel.joint_names``).
        joint_names: the 3-D model's joints in command order (``HumanoidModel.joint_names``).
    """

    source = "multicontact"

    def __init__(self, segments: list[Segment], planar_joint_names: list[str], joint_names: list[str],
                 cfg: ExecutorConfig | None = None):
        if not segments:
            raise ValueError("an empty plan")
        missing = [j for j in planar_joint_names if j not in joint_names]
        if missing:
            raise ValueError(f"plan joints not in the robot: {missing}")
        self.segments = list(segments)
        self.cfg = cfg or ExecutorConfig()
        self.index = np.array([joint_names.index(j) for j in planar_joint_names])
        self.n_joints = len(joint_names)
        self.reset()

    def reset(self) -> None:
        self._t0: float | None = None
        self._hold: np.ndarray | None = None
        self._seg = 0
        self._seg_start = 0.0
        self.switches: list[tuple[int, float, str]] = []   # (segment entered, plan time, why)

    # ------------------------------------------------------------------ plan
    @staticmethod
    def sample(seg: Segment, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Joint positions and velocities of ``seg`` at time ``t`` from its start (clamped)."""
        t = float(np.clip(t, seg.time[0], seg.time[-1]))
        k = int(np.clip(np.searchsorted(seg.time, t, side="right") - 1, 0, len(seg.time) - 2))
        q, dq = hermite_eval(seg.time[k], seg.time[k + 1], seg.q[k], seg.v[k], seg.q[k + 1], seg.v[k + 1], t)
        return q[3:], dq[3:]

    def _foot_loaded(self, obs: Observation, foot: str) -> bool:
        return bool(obs.state.left_contact if foot == "LF" else obs.state.right_contact)

    # ------------------------------------------------------------------ step
    def step(self, observation: Observation) -> JointTargets:
        t = observation.time
        if self._t0 is None:
            self._t0 = t
            base = observation.joint_targets if observation.joint_targets is not None else observation.joint_position
            self._hold = np.asarray(base, float).copy()
        tp = t - self._t0
        while self._seg < len(self.segments) - 1:
            seg = self.segments[self._seg]
            local = tp - self._seg_start
            T = float(seg.time[-1])
            foot_landing = seg.change == "add" and seg.extremity in FEET
            if foot_landing and local >= T - self.cfg.early_switch and self._foot_loaded(observation, seg.extremity):
                why = "touchdown"
            elif local >= T and not foot_landing:
                why = "planned"
            elif foot_landing and local >= T + self.cfg.landing_wait:
                why = "landing wait over"
            else:
                break
            self._seg += 1
            self._seg_start = tp
            self.switches.append((self._seg, tp, why))
        seg = self.segments[self._seg]
        q, dq = self.sample(seg, tp - self._seg_start)
        if tp - self._seg_start > float(seg.time[-1]):
            dq = np.zeros_like(dq)      # holding the last knot (plan over, or waiting for a touchdown)
        pos = self._hold.copy()
        vel = np.zeros(self.n_joints)
        pos[self.index] = q
        vel[self.index] = dq
        return JointTargets(positions=pos, velocities=vel)


def planar_state(planar_model, joint_names: list[str], q3, v3) -> tuple[np.ndarray, np.ndarray]:
    """The planar planner's state (x, z, pitch, sagittal joints) of a 3-D free-flyer state.

    ``q3``, ``v3``: pinocchio free-flyer configuration (base position, quaternion xyzw,
    joints in ``joint_names`` order) and velocity (base twist in the base frame, joint
    rates), e.g. ``SimWorld.pinocchio_state()``. The planar root is the same root link
    (a PX-PZ-RY composite joint, so its rates are the world x, z velocities and the
    pitch rate); out-of-plane motion is dropped, not checked.
    """
    q3 = np.asarray(q3, float)
    v3 = np.asarray(v3, float)
    R = Rotation.from_quat(q3[3:7]).as_matrix()
    q = np.zeros(planar_model.n)
    v = np.zeros(planar_model.n)
    q[0], q[1] = q3[0], q3[2]
    q[2] = float(np.arctan2(R[0, 2], R[2, 2]))          # rotation about the world y axis
    lin, ang = R @ v3[:3], R @ v3[3:6]
    v[0], v[1], v[2] = lin[0], lin[2], ang[1]
    for i, j in enumerate(planar_model.joint_names):
        k = joint_names.index(j)
        q[3 + i] = q3[7 + k]
        v[3 + i] = v3[6 + k]
    return q, v


__all__ = ["ExecutorConfig", "MulticontactExecutor", "planar_state"]
