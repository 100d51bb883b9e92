"""The shared whole-body IK (humfall_ros/model/ik.py): tasks converge, limits hold."""
from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from humfall_ros.model.humanoid import load_model
from humfall_ros.model.ik import (
    ComTask,
    FrameTask,
    IKError,
    OrientationTask,
    PostureTask,
    WholeBodyIK,
)
from humfall_ros.sim.world import STANDING_POSTURE


@pytest.fixture(scope="module")
def model():
    return load_model()


def standing(model):
    q = model.configuration([0, 0, 0], [0, 0, 0, 1], model.joint_vector(STANDING_POSTURE))
    model.forward(q)
    q[2] = -min(model.sole_corners(s)[:, 2].min() for s in ("l", "r"))
    model.forward(q)
    return q


def placements(model, q):
    model.forward(q)
    return {s: pin.SE3(model.frame_placement(model.sole_frame[s])) for s in ("l", "r")}


def test_tasks_converge_within_limits(model):
    q0 = standing(model)
    feet = placements(model, q0)
    target_l = pin.SE3(feet["l"])
    target_l.translation = target_l.translation + np.array([0.15, 0.02, 0.06])
    target_l.rotation = pin.utils.rpyToMatrix(0.0, 0.0, 0.2)
    com_goal = model.com(q0) + np.array([0.02, -0.05, -0.04])
    tasks = [FrameTask("r_sole", feet["r"], hard=True), FrameTask("l_sole", target_l), ComTask(com_goal),
             OrientationTask("chest", np.eye(3)), PostureTask(q0[7:])]
    ik = WholeBodyIK(model)
    c = ik.solve_to_convergence(q0, tasks, dt=0.05, tolerance=2e-4)
    assert c.converged, c.errors
    model.forward(c.q)
    assert np.allclose(model.frame_placement("r_sole").translation, feet["r"].translation, atol=2e-4)
    assert np.allclose(model.frame_placement("l_sole").translation, target_l.translation, atol=2e-4)
    assert np.allclose(model.com(c.q), com_goal, atol=2e-4)
    assert np.allclose(model.frame_placement("chest").rotation, np.eye(3), atol=1e-3)
    assert c.joint_margin >= 0.0


def test_velocity_and_position_limits_bind(model):
    """An unreachable CoM (1 m below and ahead) drives joints into their limits, never past them,
    and no step is faster than the velocity fraction of the URDF limits."""
    q = standing(model)
    feet = placements(model, q)
    ik = WholeBodyIK(model, velocity_fraction=0.9)
    tasks = [FrameTask("l_sole", feet["l"], hard=True), FrameTask("r_sole", feet["r"], hard=True),
             ComTask(model.com(q) + np.array([0.6, 0.0, -1.0]), weight=100.0)]
    dt = 0.01
    vmax = 0.9 * model.limits.velocity
    for _ in range(300):
        r = ik.solve(q, tasks, dt)
        assert r.ok
        assert np.all(np.abs(r.v[6:]) <= vmax + 1e-7)
        q = r.q
        assert np.all(q[7:] >= model.limits.lower - 1e-7) and np.all(q[7:] <= model.limits.upper + 1e-7)
    # at least one joint ended on a position limit (the goal is unreachable)
    assert ik.joint_margin(q) < 1e-6
    model.forward(q)
    assert np.allclose(model.frame_placement("l_sole").translation, feet["l"].translation, atol=1e-3)


def test_hard_foot_beats_soft_tasks(model):
    """A hard foot task holds even when a heavily weighted soft task pulls the other way."""
    q0 = standing(model)
    feet = placements(model, q0)
    ik = WholeBodyIK(model)
    tasks = [FrameTask("r_sole", feet["r"], hard=True),
             ComTask(model.com(q0) + np.array([0.0, 0.3, 0.0]), weight=1e4)]
    q = q0
    for _ in range(50):
        q = ik.solve(q, tasks, 0.002).q
    model.forward(q)
    assert np.linalg.norm(model.frame_placement("r_sole").translation - feet["r"].translation) < 1e-4


def test_fixed_base(model):
    q0 = standing(model)
    ik = WholeBodyIK(model, fixed_base=True)
    model.forward(q0)
    hand = pin.SE3(model.frame_placement("l_hand"))
    hand.translation = hand.translation + np.array([0.1, 0.0, 0.1])
    c = ik.solve_to_convergence(q0, [FrameTask("l_hand", hand, weight=(1, 1, 1, 0, 0, 0))], dt=0.05,
                                tolerance=1e-3)
    assert c.converged
    assert np.allclose(c.q[:7], q0[:7])


def test_bad_tasks_refused(model):
    ik = WholeBodyIK(model)
    q0 = standing(model)
    with pytest.raises(IKError):
        ik.solve(q0, [FrameTask("no_such_frame", pin.SE3.Identity())], 0.01)
    with pytest.raises(IKError):
        ik.solve(q0, [ComTask(np.zeros(3), weight=-1.0)], 0.01)
    with pytest.raises(IKError):
        ik.solve(q0, [PostureTask(np.zeros(3))], 0.01)
