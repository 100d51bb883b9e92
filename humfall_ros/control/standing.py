"""Standing balance: hold a posture and keep the CoM over the feet (ankle strategy).

The joints are position-controlled by the simulator; on top of the nominal
posture, the ankles are offset in proportion to the CoM error and velocity
relative to a reference over the support polygon. This is a balance
controller, not a fall controller: pushes beyond what the ankles can absorb
are the FTB's and the safe-fall controller's business.
"""
from __future__ import annotations

import numpy as np

from humfall_ros.model.humanoid import SIDES, HumanoidModel


class StandingBalance:
    def __init__(self, model: HumanoidModel, posture: dict, kp: float = 0.3, kd: float = 0.05,
                 max_offset: float = 0.12):
        self.m = model
        self.nominal = model.joint_vector(posture)
        self.kp, self.kd, self.max_offset = kp, kd, max_offset
        self.reference = None
        self._pitch = [model.joint_index(f"{s}_ankle_pitch") for s in SIDES]
        self._roll = [model.joint_index(f"{s}_ankle_roll") for s in SIDES]

    def reset(self) -> None:
        self.reference = None

    def command(self, com, com_velocity, support_polygon=None, feet_center=None) -> np.ndarray:
        """Joint position targets (model order).

        With ``feet_center`` (mid-point of the ankles, same frame as ``com``), the CoM is
        held relative to the feet, not at a fixed world point: an estimator's odometry
        drifts in the world, and chasing that drift leant a noisy-sensor robot 1.5 deg
        (0.06 deg relative to the feet).
        """
        com = np.asarray(com, float)
        vel = np.asarray(com_velocity, float)
        if feet_center is not None:
            com = com - np.array([feet_center[0], feet_center[1], 0.0])
        if self.reference is None:
            # hold the CoM where the standing posture put it over the feet: a reference
            # elsewhere would step the stiff ankles on the first tick and jolt the robot
            self.reference = com[:2].copy()
        err = com[:2] - self.reference
        # ankle pitch > 0 turns the toes down: the body is pushed back (+x error -> + pitch)
        d_pitch = np.clip(self.kp * err[0] + self.kd * vel[0], -self.max_offset, self.max_offset)
        # ankle roll > 0 tilts the shank towards +y over a flat sole: a +y error needs a - roll
        d_roll = np.clip(-(self.kp * err[1] + self.kd * vel[1]), -self.max_offset, self.max_offset)
        q = self.nominal.copy()
        q[self._pitch] += d_pitch
        q[self._roll] += d_roll
        return np.clip(q, self.m.limits.lower, self.m.limits.upper)
