"""The sensed contact wrenches obey Newton-Euler with the robot's motion (issue 10, the single-support CoP bias).

Per control tick, the contact force and moment the world reports (``SimWorld.ground_contacts``, which
``foot_wrench`` and ``ground_truth_cop`` are built from) plus gravity and the push must equal the rate of the
robot's linear and angular momentum: pinocchio's centroidal momentum of PyBullet's ground-truth state,
differenced over the tick. The rubber-sole contact chatters at the physics rate, so a reading of the
last physics substep only breaks this by hundreds of newtons (checked here too, so the test can fail).
"""
import numpy as np
import pinocchio as pin
import pybullet as pb
import pytest

from humfall_ros import scenario
from humfall_ros.dynamics.pendulum import GRAVITY
from humfall_ros.model.humanoid import SIDES, load_model
from humfall_ros.sim.closed_loop import ClosedLoop
from humfall_ros.suite import node_params
from humfall_ros.sim.world import SimWorld
from humfall_ros.walking.controller import from_scenario

FORCE_TOL = 2.0      # [N] per tick, each axis (measured: < 0.01 N standing pushed)
MOMENT_TOL = 2.0     # [N m] per tick, each axis, about the world origin (measured max: 0.1 pushed stance, 1.05 walk;
#                      the old last-substep CoP bias was ~25 N m: 4.5 cm x 570 N)


class MomentumRate:
    """Per-tick residual of the reported contact wrench against the momentum rate (all in the world frame)."""

    def __init__(self, world: SimWorld):
        self.w = world
        self.m = world.model
        self.data = self.m.model.createData()
        self.prev = self._momentum()
        self.residuals: list[np.ndarray] = []   # [fx, fy, fz, mx, my, mz] per tick
        self.support: list[int] = []            # feet loaded per tick
        self.contact_fx: list[float] = []       # reported contact force x [N] per tick

    def _momentum(self) -> tuple[np.ndarray, np.ndarray]:
        q, v = self.w.pinocchio_state()
        pin.computeCentroidalMomentum(self.m.model, self.data, q, v)
        com = pin.centerOfMass(self.m.model, self.data, q)
        lin = self.data.hg.linear.copy()
        return lin, self.data.hg.angular + np.cross(com, lin), com   # angular about the world origin

    def tick(self, push_force: np.ndarray, push_point: np.ndarray) -> None:
        """Call right after ``step_control``; push force/point [N, m] (world) applied during the tick."""
        dt = 1.0 / self.w.control_rate
        lin, ang, com = self._momentum()
        lin0, ang0, com0 = self.prev
        self.prev = lin, ang, com
        f, mo = np.zeros(3), np.zeros(3)
        loaded = set()
        for cp in self.w.ground_contacts():
            fc = cp[9] * np.array(cp[7]) + cp[10] * np.array(cp[11]) + cp[12] * np.array(cp[13])
            f += fc
            mo += np.cross(cp[6], fc)
            loaded.add(cp[3])
        self.contact_fx.append(float(f[0]))
        weight = np.array([0.0, 0.0, -self.m.total_mass * GRAVITY])
        ext_f = f + weight + push_force
        ext_m = mo + np.cross(0.5 * (com + com0), weight) + np.cross(push_point, push_force)
        self.residuals.append(np.concatenate([ext_f - (lin - lin0) / dt, ext_m - (ang - ang0) / dt]))
        self.support.append(len(loaded & set(self.w.foot_links.values())))


def _chest_point(w: SimWorld) -> np.ndarray:
    return np.asarray(w._link_frame(w.link_ids["chest"])[0])


def test_pushed_stance_contact_wrench_matches_the_momentum_rate():
    """Servos holding the standing posture, 100 N x 0.4 s on the chest: the robot leans and recovers."""
    w = SimWorld()
    try:
        rate = MomentumRate(w)
        push = np.array([100.0, 0.0, 0.0])
        w.add_push(push, duration=0.4, link="chest", start=0.1)
        n = int(0.8 * w.control_rate)
        moving = []
        for _ in range(n):
            active = w.pushes and w.pushes[0].active(w.time)
            point = _chest_point(w)   # the push acts at the chest origin; it moves < 1 mm in a tick
            w.step_control()
            rate.tick(push if active else np.zeros(3), point)
            moving.append(w.time > 0.1)
        r = np.array(rate.residuals)[np.array(moving)]
        assert np.abs(r[:, :3]).max() < FORCE_TOL, np.abs(r[:, :3]).max(0)
        assert np.abs(r[:, 3:]).max() < MOMENT_TOL, np.abs(r[:, 3:]).max(0)
    finally:
        w.close()


def test_a_walking_step_contact_wrench_matches_the_momentum_rate_and_the_last_substep_alone_does_not():
    """A 1 km/h walk of one step (start, one step, stop) in ClosedLoop, single support included."""
    sc = scenario.load("walking", ["walk.speed_kmh=1.0", "walk.steps=1"])
    ctl = from_scenario(sc, load_model(), node_params(sc, "locomotion"))
    loop = ClosedLoop(sc, controllers=[ctl])
    w = loop.world
    try:
        rate = MomentumRate(w)
        last_substep_fx = []
        end = sc["walk"]["start_time"] + ctl.cfg.crouch_duration + ctl.cfg.start_duration + 2 * ctl.cfg.step_period
        while w.time < end:
            loop.step()
            rate.tick(np.zeros(3), np.zeros(3))
            raw = pb.getContactPoints(w.robot, w.ground, physicsClientId=w.client)
            last_substep_fx.append(sum(cp[9] * cp[7][0] + cp[10] * cp[11][0] + cp[12] * cp[13][0] for cp in raw))
        r = np.array(rate.residuals)[50:]            # after the first settling
        single = np.array(rate.support)[50:] == 1
        assert single.sum() > 100, "the walk has a single support"
        assert np.abs(r[:, :3]).max() < FORCE_TOL, np.abs(r[:, :3]).max(0)
        assert np.abs(r[:, 3:]).max() < MOMENT_TOL, np.abs(r[:, 3:]).max(0)
        # the last physics substep alone is no reading of the tick: in single support its horizontal
        # force is off the tick's mean (which obeys Newton, above) by tens to hundreds of newtons
        off = np.abs(np.array(last_substep_fx)[50:] - np.array(rate.contact_fx)[50:])[single]
        assert off.mean() > 30.0, off.mean()
    finally:
        loop.close()


@pytest.mark.parametrize("side", SIDES)
def test_foot_wrench_is_the_tick_mean_of_that_foot(side):
    w = SimWorld()
    try:
        for _ in range(100):        # 0.2 s: with the 20 ms servo loop the stance still rocks +-13 % at 0.04 s
            w.step_control()
        f, _ = w.foot_wrench(side)
        assert f[2] == pytest.approx(0.5 * w.model.weight, rel=0.1)
    finally:
        w.close()
