"""Sensor readings with optional, seeded noise (humfall_ros.sim.sensors)."""
import dataclasses

import numpy as np
import pytest

from humfall_ros.sim.sensors import SensorNoise, Sensors
from humfall_ros.sim.world import SimWorld


@pytest.fixture(scope="module")
def world():
    w = SimWorld(1000, 500)
    yield w
    w.close()


def test_exact_sensors_are_the_simulator_readings(world):
    r = Sensors(world).read()
    q, v, tau = world.joint_states()
    assert np.array_equal(r.joint_position, q) and np.array_equal(r.joint_velocity, v)
    f, t = world.foot_wrench("l")
    assert np.array_equal(r.wrenches["l"][0], f) and np.array_equal(r.wrenches["l"][1], t)


def test_noise_has_the_asked_spread_and_is_repeatable_by_seed(world):
    noise = SensorNoise(joint_position=0.01, gyro=0.02, force=3.0, imu_orientation=0.01, seed=7)
    exact = Sensors(world).read()
    samples = []
    for seed in (7, 7, 8):
        s = Sensors(world, dataclasses.replace(noise, seed=seed))
        draws = []
        for _ in range(200):
            s._readings = None  # a new sample of the same physical state
            draws.append(s.read())
        samples.append(draws)
    dq = np.array([d.joint_position - exact.joint_position for d in samples[0]])
    assert np.std(dq) == pytest.approx(0.01, rel=0.1) and abs(np.mean(dq)) < 0.002
    dg = np.array([d.gyro - exact.gyro for d in samples[0]])
    assert np.std(dg) == pytest.approx(0.02, rel=0.15)
    df = np.array([d.wrenches["r"][0] - exact.wrenches["r"][0] for d in samples[0]])
    assert np.std(df) == pytest.approx(3.0, rel=0.15)
    # the attitude is a unit quaternion rotated by ~0.01 rad
    angles = [2 * np.arccos(min(1.0, abs(float(np.dot(d.imu_orientation, exact.imu_orientation)))))
              for d in samples[0]]
    assert all(abs(np.linalg.norm(d.imu_orientation) - 1) < 1e-12 for d in samples[0])
    assert 0.005 < np.median(angles) < 0.03
    # untouched sensors stay exact; the same seed gives the same noise, another seed other noise
    assert np.array_equal(samples[0][0].joint_velocity, exact.joint_velocity)
    assert np.array_equal(samples[0][5].joint_position, samples[1][5].joint_position)
    assert not np.array_equal(samples[0][5].joint_position, samples[2][5].joint_position)


def test_a_tick_read_twice_is_the_same_sample_and_a_new_tick_a_new_one(world):
    s = Sensors(world, SensorNoise(joint_position=0.01, seed=1))
    a, b = s.read(), s.read()
    assert a is b  # a retransmitted tick must not be a new sample
    world.step_control()
    assert not np.array_equal(s.read().joint_position, a.joint_position)


@pytest.mark.parametrize("bad", [-0.1, float("nan"), float("inf")])
def test_bad_noise_settings_are_refused(bad):
    with pytest.raises(ValueError, match="gyro"):
        SensorNoise(gyro=bad)
