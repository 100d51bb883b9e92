"""Swing tilt compensation: the swing foot stays on its IK placement under the stance ankle offsets."""
from __future__ import annotations

import dataclasses
import types

import numpy as np
import pinocchio as pin
import pytest

from humfall_ros.model.humanoid import load_model
from humfall_ros.walking.config import LocomotionConfig
from humfall_ros.walking.controller import LocomotionController


@pytest.fixture(scope="module")
def ctl():
    m = load_model()
    return LocomotionController(m, dataclasses.replace(LocomotionConfig(), swing_tilt_compensation=True))


def rebased_other_sole(ctl, q_ik, q_cmd, base, other):
    """The other sole of the commanded joints with the base sole held at its IK placement (the flat ground)."""
    m = ctl.m
    m.forward(q_ik)
    M_b = m.frame_placement(m.sole_frame[base]).copy()
    q = q_ik.copy()
    q[7:] = q_cmd
    m.forward(q)
    T = M_b * m.frame_placement(m.sole_frame[base]).inverse()
    return T * m.frame_placement(m.sole_frame[other])


def test_swing_foot_kept_on_its_placement(ctl):
    m = ctl.m
    q = ctl.reference_configuration(ctl.standing_posture, 0.0, (0.0, 0.0))
    q[7 + m.joint_index("r_knee")] += 0.3          # a lifted, bent swing leg
    q[7 + m.joint_index("r_hip_pitch")] -= 0.2
    m.forward(q)
    target = m.frame_placement(m.sole_frame["r"]).copy()
    q_cmd = q[7:].copy()
    q_cmd[m.joint_index("l_ankle_pitch")] += 0.003   # the stabiliser's stance ankle offsets [rad]
    q_cmd[m.joint_index("l_ankle_roll")] -= 0.002
    q_cmd[m.joint_index("r_ankle_pitch")] += 0.001   # and a residual one on the swing ankle
    sample = types.SimpleNamespace(phase_fraction=0.5)
    ctl.command = dataclasses.replace(ctl.command, speed=0.3)
    before = rebased_other_sole(ctl, q, q_cmd, "l", "r")
    assert np.linalg.norm(pin.log6(before.inverse() * target).vector) > 3e-4   # the tilt moves the swing foot
    out = ctl._swing_tilt_compensation(q, q_cmd, sample, "l")
    after = rebased_other_sole(ctl, q, out, "l", "r")
    assert np.linalg.norm(after.translation - target.translation) < 2e-6
    assert np.linalg.norm(pin.log3(after.rotation.T @ target.rotation)) < 2e-5
    changed = np.flatnonzero(np.abs(out - q_cmd) > 0)
    assert {m.joint_names[i] for i in changed} <= {f"r_{j}" for j in ("hip_yaw", "hip_roll", "hip_pitch", "knee",
                                                                      "ankle_pitch", "ankle_roll")}


def test_ramp_and_double_support_fade(ctl):
    m = ctl.m
    q = ctl.reference_configuration(ctl.standing_posture, 0.0, (0.0, 0.0))
    q_cmd = q[7:].copy()
    q_cmd[m.joint_index("l_ankle_pitch")] += 0.003
    ctl.command = dataclasses.replace(ctl.command, speed=0.3)
    T_ss = ctl.cfg.single_support_for(0.3)
    early = ctl._swing_tilt_compensation(q, q_cmd, types.SimpleNamespace(phase_fraction=0.0), "l")
    assert np.array_equal(early, q_cmd)                        # lift-off: the correction ramps in from 0
    half = ctl._swing_tilt_compensation(q, q_cmd, types.SimpleNamespace(
        phase_fraction=0.5 * ctl.cfg.swing_tilt_ramp / T_ss), "l")
    full = ctl._swing_tilt_compensation(q, q_cmd, types.SimpleNamespace(phase_fraction=0.5), "l")
    np.testing.assert_allclose(half - q_cmd, 0.5 * (full - q_cmd), atol=1e-12)
    ctl._last_stance = "l"                                     # the double support after that swing
    ds_end = ctl._swing_tilt_compensation(q, q_cmd, types.SimpleNamespace(phase_fraction=1.0), None)
    assert np.array_equal(ds_end, q_cmd)
    ds_mid = ctl._swing_tilt_compensation(q, q_cmd, types.SimpleNamespace(phase_fraction=0.25), None)
    np.testing.assert_allclose(ds_mid - q_cmd, 0.75 * (full - q_cmd), atol=1e-12)
    ctl._last_stance = None
    assert np.array_equal(ctl._swing_tilt_compensation(q, q_cmd, types.SimpleNamespace(phase_fraction=0.3), None),
                          q_cmd)                               # the start double support: nothing to correct
