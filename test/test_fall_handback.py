"""The hand-back after a captured push, in process (ClosedLoop): safe_fall -> locomotion, standing where the feet are.

standing_push 1.0x with ``stepping``: the protective step captures the push, the capture balance settles the
robot, the FTB recovers (the fall event is cleared), the safe-fall controller releases and locomotion stands
from the servo targets in the staggered stance (an IK posture on the measured feet). A walk command from that
stance is refused with its reason. A ClosedLoop monitor's latched None clears the input.
"""
import numpy as np
import pytest

from humfall_ros import scenario
from humfall_ros.sim import fall_runs as runs


@pytest.fixture(scope="module")
def handback():
    sc = scenario.load("standing_push", ["duration=5.6", "controller=stepping"])
    return runs.handback_run(sc, "stepping", walk_at=5.2)


def test_captured_push_is_handed_back_to_locomotion(handback):
    r = handback
    assert r["touchdown_time_s"] is not None and r["recovered_time_s"] is not None
    assert r["touchdown_time_s"] < r["recovered_time_s"] <= r["handback_time_s"]
    assert r["handback_ticks"] == 1 and r["active_end"] == "locomotion"      # once, and it stays with locomotion
    assert r["handbacks"][0]["phase"] == "landed"
    assert not r["fell"] and r["min_target_distance_m"] >= 0.05
    # bumpless: locomotion's first command is where the servos were (targets), and the CoM barely moves after
    assert r["target_jump_at_handback_rad"] < 1e-3
    assert r["com_move_after_handback_m"] < 0.01
    # still standing, still, upright, CoM over the middle of the two soles (ground truth)
    assert r["com_speed_last_0.5s_max_m_s"] < 0.01 and r["trunk_tilt_end_deg"] < 2.0
    assert r["com_over_soles_mid_end_m"] < 0.01
    assert r["com_end"][2] > 0.7


def test_locomotion_keeps_the_staggered_stance_and_refuses_a_walk_from_it(handback):
    r = handback
    a, b = r["soles_at_handback"], r["soles_end"]
    for sd in ("l", "r"):   # the feet are not dragged to the standard stance
        assert np.hypot(a[sd][0] - b[sd][0], a[sd][1] - b[sd][1]) < 0.005
    assert abs(a["r"][0] - a["l"][0]) > 0.15                                   # staggered: the step's stance
    msgs = r["loco_messages"]
    assert any(m.startswith("resume: standing where the feet are") for m in msgs)
    assert any("walk command refused: the feet stand" in m for m in msgs)
    assert not any(m.startswith("walk started") for m in msgs)


def test_latched_none_clears_a_loop_input():
    from humfall_ros.sim.closed_loop import ClosedLoop

    class Mon:
        name = "mon"
        latched: dict = {}

        def reset(self):
            self.k = 0

        def step(self, obs):
            self.k += 1
            self.latched = {"flag": "set"} if self.k == 2 else ({"flag": None} if self.k == 4 else {})
            return self.k

    class Ctl:
        source = "locomotion"

        def reset(self):
            self.seen = []

        def step(self, obs):
            self.seen.append(obs.inputs.get("flag"))
            return None

    ctl = Ctl()
    loop = ClosedLoop(scenario.load("standing_push"), [ctl], [Mon()])
    try:
        for _ in range(6):
            loop.step()
    finally:
        loop.close()
    assert ctl.seen == [None, "set", "set", None, None, None]


def test_standing_resumes_from_the_targets_into_the_resume_target_once():
    from humfall_ros.control.contract import CentroidalObservation, Observation
    from humfall_ros.control.standing import StandingController
    from humfall_ros.model.humanoid import load_model

    m = load_model()
    calls = []
    stance = m.joint_vector(m.standing_posture) + 0.02

    def target(obs):
        calls.append(obs.time)
        return stance, np.array([0.03, 0.0])

    c = StandingController(m, m.standing_posture, 0.3, 0.05, 0.12, resume_time=0.1, resume_target=target,
                           resume_from_targets=True)
    st = CentroidalObservation(np.array([0.03, 0.0, 0.74]), np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3),
                               np.zeros((0, 2)), np.zeros(3), 0.0, 0.0, 570.0, True, True, False)
    measured, servo = m.joint_vector(m.standing_posture) - 0.01, m.joint_vector(m.standing_posture) + 0.01

    def obs(t, active):
        return Observation(round(t * 1e9), measured, np.zeros(m.njoints), st, active, {}, joint_targets=servo)

    out = c.step(obs(0.0, "safe_fall"))          # another source drives: follow the servos' targets
    assert np.allclose(out.positions, np.clip(servo, m.limits.lower, m.limits.upper)) and not calls
    first = c.step(obs(0.002, "locomotion"))      # drives again: the target is asked for once, the blend starts
    assert calls == [0.002] and np.max(np.abs(first.positions - servo)) < 1e-6
    for k in range(2, 80):
        out = c.step(obs(0.002 * k, "locomotion"))
    assert calls == [0.002]
    assert np.allclose(out.positions, np.clip(stance, m.limits.lower, m.limits.upper))   # kept after the blend
    assert np.allclose(c.balance.reference, [0.03, 0.0])
