"""Multi-body correction of the LIPM pattern: Kajita's second preview stage, online. No rclpy.

The cart-table CoM of the first stage ignores what the legs (38 % of the mass) do to the ZMP
through the centroidal angular momentum. Kajita et al. (ICRA 2003, the multi-body ZMP loop)
run the whole-body motion of the first-stage pattern, compute its ZMP ``p_mb`` with the full
model, and feed the error ``Δp = p_ref - p_mb`` as the reference of a second preview controller
on the same cart-table model; its CoM ``Δc`` is added to the first stage's CoM.

Online, the pattern runs ``D`` ticks ahead of the command: each tick the *look-ahead* IK takes
the first-stage sample of tick k + D, the ZMP of that motion is computed from the rate of the
centroidal momentum (pinocchio ``computeCentroidalMomentum``, backward difference)::

    f = dh_lin/dt + m g e_z,   L' = dh_ang/dt (about the CoM)
    p_x = c_x - (c_z f_x + L'_y) / f_z,   p_y = c_y - (c_z f_y - L'_x) / f_z

(derived in test_walking_pattern: zero horizontal moment of the contact wrench about p), and the
second preview stage, with the errors of ticks k .. k + D as its preview, gives ``Δc`` at tick k.
"""
from __future__ import annotations

import collections
import dataclasses
from collections.abc import Callable

import numpy as np
import pinocchio as pin

from humfall_ros.dynamics.pendulum import GRAVITY
from humfall_ros.model.humanoid import HumanoidModel
from humfall_ros.model.ik import WholeBodyIK
from humfall_ros.walking.pattern import PatternSample, WalkingPattern
from humfall_ros.walking.preview import PreviewController


def multibody_zmp(com, momentum_rate_linear, momentum_rate_angular, mass: float) -> np.ndarray:
    """ZMP on z = 0 of a motion with CoM ``com`` [m] and centroidal momentum rates [N], [N m]."""
    f = np.asarray(momentum_rate_linear, float) + np.array([0.0, 0.0, mass * GRAVITY])
    dL = np.asarray(momentum_rate_angular, float)
    c = np.asarray(com, float)
    return np.array([c[0] - (c[2] * f[0] + dL[1]) / f[2], c[1] - (c[2] * f[1] - dL[0]) / f[2], 0.0])


class MomentumZmp:
    """Multi-body ZMP of a sequence of configurations (backward difference of the centroidal momentum)."""

    def __init__(self, model: HumanoidModel, dt: float):
        self.m = model
        self.data = model.model.createData()
        self.dt = float(dt)
        self.prev: np.ndarray | None = None

    def reset(self) -> None:
        self.prev = None

    def update(self, q, v) -> np.ndarray | None:
        """ZMP [m] (3,) of the step that ended at (q, v); None on the first call."""
        pin.computeCentroidalMomentum(self.m.model, self.data, q, v)
        h = np.concatenate([self.data.hg.linear, self.data.hg.angular])
        com = self.data.com[0].copy()
        prev, self.prev = self.prev, h
        if prev is None:
            return None
        dh = (h - prev) / self.dt
        return multibody_zmp(com, dh[:3], dh[3:], self.m.total_mass)


@dataclasses.dataclass
class CorrectedSample:
    sample: PatternSample           # with the corrected CoM
    com_offset: np.ndarray          # Δc [m] (3,)
    planned_multibody_zmp: np.ndarray  # ZMP of the first-stage whole-body motion at this tick [m] (3,)


class MultiBodyCorrection:
    """Runs ``pattern`` ``lookahead`` ticks ahead and corrects its CoM (module docstring).

    Args:
        model: the robot model.
        pattern: the first-stage pattern (it is stepped here).
        q0: configuration the look-ahead IK starts from (nq,).
        tasks: sample -> IK tasks (the controller's).
        lookahead: D [ticks]; the second stage's preview horizon.
        ik: the look-ahead IK (its own instance: it keeps no state, but shares no data).
    """

    def __init__(self, model: HumanoidModel, pattern: WalkingPattern, q0, tasks: Callable[[PatternSample], list],
                 lookahead: int, ik: WholeBodyIK):
        self.m = model
        self.pattern = pattern
        self.tasks = tasks
        self.ik = ik
        self.q = np.asarray(q0, float).copy()
        self.zmp = MomentumZmp(model, pattern.dt)
        self.D = int(lookahead)
        cfg = pattern.cfg
        self.stage2 = PreviewController(pattern.dt, cfg.com_height, self.D * pattern.dt, cfg.preview_q, 0.0,
                                        cfg.preview_r)
        self.stage2.reset((0.0, 0.0))
        self.samples: collections.deque = collections.deque()
        self.errors: collections.deque = collections.deque()
        self.p_mb: collections.deque = collections.deque()
        for _ in range(self.D + 1):
            self._advance()

    def _advance(self) -> None:
        s = self.pattern.step()
        r = self.ik.solve(self.q, self.tasks(s), self.pattern.dt)
        self.q = r.q
        p = self.zmp.update(r.q, r.v)
        if p is None:  # first tick: no rate yet
            p = s.zmp.copy()
        self.samples.append(s)
        self.p_mb.append(p)
        self.errors.append(s.zmp[:2] - p[:2])

    def step(self) -> CorrectedSample:
        """The corrected sample of the current tick (the pattern moves one tick further ahead)."""
        self._advance()
        e = np.array(self.errors)  # ticks k .. k + D + 1
        st = self.stage2.step(e[0], e[1:self.D + 1])
        s = self.samples.popleft()
        self.errors.popleft()
        p = self.p_mb.popleft()
        off = np.array([st[0, 0], st[0, 1], 0.0])
        s = dataclasses.replace(s, com=s.com + off,
                                com_velocity=s.com_velocity + np.array([st[1, 0], st[1, 1], 0.0]))
        return CorrectedSample(s, off, p)


__all__ = ["CorrectedSample", "MomentumZmp", "MultiBodyCorrection", "multibody_zmp"]
