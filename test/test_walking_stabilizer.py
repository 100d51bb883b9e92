"""Walking stabiliser loops and the sole sinkage feed-forward (walking/stabilizer.py, walking/compliance.py)."""
from __future__ import annotations

import xml.etree.ElementTree as ET

import numpy as np
import pytest

from humfall_ros.dynamics.pendulum import GRAVITY
from humfall_ros.model.humanoid import SIDES, load_model
from humfall_ros.walking.compliance import distribute_zmp, planned_loads, sole_contact, sole_sinkage
from humfall_ros.walking.stabilizer import WalkingStabilizer

DT = 0.002


@pytest.fixture(scope="module")
def model():
    return load_model()


def stabilizer(model, **kw):
    args = {"dcm_gain": 0.0, "com_feedback_max": 0.03, "cop_gain": 1.0, "cop_time_constant": 0.2,
            "ankle_max_offset": 0.05, "foot_height_gain": 0.05, "foot_height_time_constant": 0.05,
            "foot_height_max": 0.0005}
    args.update(kw)
    return WalkingStabilizer(model, DT, **args)


def test_planned_loads_split_the_weight_by_the_reference_zmp():
    centres = {"l": np.array([0.0, 0.09]), "r": np.array([0.2, -0.09])}
    w = 500.0
    assert planned_loads(centres["l"], centres, None, w) == pytest.approx({"l": w, "r": 0.0})
    assert planned_loads(0.5 * (centres["l"] + centres["r"]), centres, None, w) == pytest.approx({"l": w / 2,
                                                                                                  "r": w / 2})
    # a point off the segment is projected onto it; beyond the front sole all is on the front sole
    off = 0.5 * (centres["l"] + centres["r"]) + 0.05 * np.array([0.18, 0.2])     # across the segment's middle
    assert planned_loads(off, centres, None, w) == pytest.approx({"l": w / 2, "r": w / 2})
    assert planned_loads([0.5, -0.4], centres, None, w) == pytest.approx({"l": 0.0, "r": w})
    # single support: the stance sole carries all, wherever the ZMP reference is
    assert planned_loads([0.3, 0.3], centres, "r", w) == {"l": 0.0, "r": w}
    for zmp in ([0.03, 0.05], [0.1, 0.0], [0.17, -0.06]):
        f = planned_loads(zmp, centres, None, w)
        assert f["l"] + f["r"] == pytest.approx(w) and min(f.values()) >= 0


def test_sole_contact_is_the_urdf_contact_at_each_corner(model):
    k, c = sole_contact(model)
    link = ET.parse(model.urdf_path).getroot().find(f"link[@name='{model.foot_link['l']}']")
    n = len(model.sole_corners_local["l"])
    assert k == pytest.approx(n * float(link.find("contact/stiffness").get("value")))
    assert c == pytest.approx(n * float(link.find("contact/damping").get("value")))
    # standing on one sole, it sinks by a fraction of a millimetre
    assert 0.05e-3 < model.total_mass * GRAVITY / k < 0.5e-3


def test_sinkage_includes_the_damper_lead():
    k, c = 4e6, 4e4
    static = sole_sinkage({"l": 300.0, "r": 200.0}, {"l": 300.0, "r": 200.0}, DT, k, c)
    assert static == pytest.approx({"l": 300.0 / k, "r": 200.0 / k})
    # loading at 5 kN/s: the spring-damper needs k d + c dd/dt = f, so the sinkage is less than f / k
    ramp = sole_sinkage({"l": 300.0, "r": 200.0}, {"l": 290.0, "r": 210.0}, DT, k, c)
    assert ramp["r"] == pytest.approx((200.0 - (c / k) * 10.0 / DT) / k)
    assert ramp["l"] > static["l"] and ramp["r"] < static["r"]
    assert sole_sinkage({"l": 0.0, "r": 0.0}, {"l": 0.0, "r": 50.0}, DT, k, c)["r"] == 0.0   # never above ground
    assert sole_sinkage({"l": 300.0, "r": 0.0}, {"l": 300.0, "r": 0.0}, DT, 0.0, 0.0) == {"l": 0.0, "r": 0.0}


def _update(st, cop, ref_zmp, stance, transfer_to=None, swing_loaded=False):
    centres = {"l": np.array([0.0, 0.09]), "r": np.array([0.2, -0.09])}
    feet = 0.5 * (centres["l"] + centres["r"])
    z = np.zeros(2)
    return st.update(z, np.asarray(cop, float), feet, z, np.asarray(ref_zmp, float), feet, stance, 0.0, centres,
                     transfer_to, swing_loaded)


def test_foot_height_difference_moves_the_load_onto_the_lagging_side(model):
    st = stabilizer(model)
    ref = np.array([0.1, 0.0])
    for _ in range(20):      # the measured CoP lags 3 cm behind the reference, towards the rear (left) sole
        out = _update(st, ref - 0.03 * np.array([0.2, -0.18]) / np.hypot(0.2, 0.18), ref, None, transfer_to="r")
    # the front (right) sole target goes down, the rear one up, by the same amount
    assert out.foot_z["r"] < -1e-6 and out.foot_z["l"] == pytest.approx(-out.foot_z["r"])
    # du/dt = k e - u / T: u = k e T (1 - exp(-t / T)) after t
    assert out.foot_z["l"] - out.foot_z["r"] == pytest.approx(0.05 * 0.03 * 0.05 * (1 - np.exp(-20 * DT / 0.05)),
                                                              rel=0.05)
    ahead = stabilizer(model)
    for _ in range(20):
        out2 = _update(ahead, ref + 0.03 * np.array([0.2, -0.18]) / np.hypot(0.2, 0.18), ref, None, transfer_to="r")
    assert out2.foot_z["r"] > 1e-6
    # no error across the feet axis, no action
    quiet = stabilizer(model)
    assert _update(quiet, ref + np.array([0.18, 0.2]) * 0.1, ref, None, transfer_to="r").foot_z["r"] \
        == pytest.approx(0.0, abs=1e-12)
    # single support: it leaks back to zero
    for _ in range(500):
        out = _update(st, ref, ref, "r")
    assert abs(out.foot_z["r"]) < 1e-3 * 0.05 * 0.03 * 20 * DT


def test_stance_ankle_damping_holds_off_while_the_swing_foot_is_loaded(model):
    st = stabilizer(model, foot_height_gain=0.0)
    for _ in range(10):
        out = _update(st, [0.23, -0.09], [0.2, -0.09], "r")        # CoP 3 cm ahead on the stance sole
    assert out.ankle["r"][0] < -1e-4                             # toes up to bring it back
    held = stabilizer(model, foot_height_gain=0.0)
    for _ in range(10):
        out = _update(held, [0.1, 0.0], [0.2, -0.09], "r", swing_loaded=True)   # early touchdown of the left
    assert np.all(out.ankle["r"] == 0.0) and np.all(out.ankle["l"] == 0.0)


CENTRES = {"l": np.array([0.0, 0.09]), "r": np.array([0.2, -0.09])}


def test_distribute_zmp_sums_to_the_total_and_splits_by_the_zmp_between_the_soles():
    total = 560.0
    a, b = CENTRES["l"], CENTRES["r"]
    for alpha in (0.0, 0.1, 0.5, 0.75, 1.0):
        for off in (0.0, 0.02, -0.015):               # also beside the feet axis
            zmp = a + alpha * (b - a) + off * np.array([0.18, 0.2]) / np.hypot(0.18, 0.2)
            sh = distribute_zmp(zmp, CENTRES, None, total)
            assert sh["l"].force + sh["r"].force == pytest.approx(total)
            assert sh["r"].force == pytest.approx(alpha * total)      # the ratio follows the ZMP
            # the soles' own CoPs, weighted by their forces, are the ZMP
            p = (sh["l"].force * sh["l"].cop + sh["r"].force * sh["r"].cop) / total
            assert p == pytest.approx(zmp, abs=1e-12)
            assert np.linalg.norm(sh["r"].cop - b) == pytest.approx(abs(off), abs=1e-12)
    # beyond the front sole: all on it, its CoP on the ZMP
    sh = distribute_zmp(b + np.array([0.03, 0.0]), CENTRES, None, total)
    assert sh["r"].force == pytest.approx(total) and sh["l"].force == 0.0
    assert sh["r"].cop == pytest.approx(b + np.array([0.03, 0.0]))
    # single support: the stance sole carries all, its CoP on the reference
    sh = distribute_zmp([0.21, -0.08], CENTRES, "r", total)
    assert sh["r"].force == total and sh["l"].force == 0.0 and sh["r"].cop == pytest.approx([0.21, -0.08])
    # planned_loads is the distribution's forces
    assert planned_loads([0.05, 0.03], CENTRES, None, total) == pytest.approx(
        {s: v.force for s, v in distribute_zmp([0.05, 0.03], CENTRES, None, total).items()})


def _update_forces(st, forces, cops, ref_zmp, stance=None, contacts=None):
    feet = 0.5 * (CENTRES["l"] + CENTRES["r"])
    z = np.zeros(2)
    total = sum(forces.values())
    cop = sum(forces[s] * np.asarray(cops[s], float) for s in forces) / total
    return st.update(z, cop, feet, z, np.asarray(ref_zmp, float), feet, stance, 0.0, CENTRES, "r", False,
                     foot_forces=forces, foot_cops=cops, contacts=contacts or {"l": True, "r": True})


@pytest.mark.parametrize("rear, front", [("l", "r"), ("r", "l")])
def test_foot_force_difference_raises_the_overloaded_rear_foot(model, rear, front):
    k, T = 3e-5, 0.05
    st = stabilizer(model, foot_height_gain=0.0, foot_force_gain=k, foot_height_time_constant=T, cop_gain=0.0)
    ref = CENTRES[rear] + 0.9 * (CENTRES[front] - CENTRES[rear])      # late in the transfer: rear 10 %, front 90 %
    forces = {rear: 150.0, front: 410.0}                               # the rear foot carries 150 N, not 56 N
    cops = {s: CENTRES[s] for s in SIDES}
    for _ in range(10):
        out = _update_forces(st, forces, cops, ref)
    assert out.foot_z[rear] > 1e-6 and out.foot_z[front] == pytest.approx(-out.foot_z[rear])   # rear up, front down
    # d(dz)/dt = k e - dz / T with e = the rear's excess counted twice (f_l - f_r against its reference)
    e = 2 * (150.0 - 56.0)
    assert out.foot_z[rear] - out.foot_z[front] == pytest.approx(k * e * T * (1 - np.exp(-10 * DT / T)), rel=0.05)
    # the split on its reference: no action; the CoP-based loop 4 is replaced (its gain 0.05 would act here)
    quiet = stabilizer(model, foot_force_gain=k, cop_gain=0.0)
    ahead = {s: CENTRES[s] + np.array([0.05, 0.0]) for s in SIDES}     # the total CoP 5 cm off the reference
    out = _update_forces(quiet, {rear: 56.0, front: 504.0}, ahead, ref)
    assert out.foot_z[rear] == pytest.approx(0.0, abs=1e-12)
    # a foot the estimator sees out of contact: the loop leaks, no force feedback
    for _ in range(200):
        out = _update_forces(st, forces, cops, ref, contacts={rear: False, front: True})
    assert abs(out.foot_z[rear]) < 1e-3 * k * e * T


def test_per_foot_cop_damping_turns_each_loaded_ankle_towards_its_own_reference(model):
    st = stabilizer(model, foot_height_gain=0.0, foot_cop_gain=1.0, foot_cop_min_force=100.0)
    ref = 0.5 * (CENTRES["l"] + CENTRES["r"])
    # the front (right) sole's own CoP 3 cm ahead of and 1 cm outside (-y) its centre; the left 50 N, on its toe
    cops = {"l": CENTRES["l"] + np.array([0.1, 0.0]), "r": CENTRES["r"] + np.array([0.03, -0.01])}
    for _ in range(10):
        out = _update_forces(st, {"l": 50.0, "r": 510.0}, cops, ref)
    assert out.ankle["r"][0] < -1e-5          # pitch: toes up, its CoP back
    assert out.ankle["r"][1] < -1e-6          # roll < 0 lowers its +y edge: the CoP towards +y
    assert np.all(out.ankle["l"] == 0.0)      # below foot_cop_min_force: untouched
    # the rate scales with the foot's load (the ankle torque error)
    half = stabilizer(model, foot_height_gain=0.0, foot_cop_gain=1.0, foot_cop_min_force=100.0)
    out_half = _update_forces(half, {"l": 50.0, "r": 255.0}, cops, ref)
    one = stabilizer(model, foot_height_gain=0.0, foot_cop_gain=1.0, foot_cop_min_force=100.0)
    out_one = _update_forces(one, {"l": 50.0, "r": 510.0}, cops, ref)
    assert out_half.ankle["r"][0] == pytest.approx(0.5 * out_one.ankle["r"][0], rel=1e-9)
