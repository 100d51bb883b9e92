"""The robot's sensors as a controller sees them: the simulator's readings plus optional noise. No rclpy.

The simulator's joint encoders, IMU and ankle force/torque readings are exact;
real ones are not, and an estimator that is only ever fed exact readings says
little about itself. ``SensorNoise`` adds zero-mean Gaussian noise (standard
deviations per sensor, all 0 by default) from a seeded generator, so a noisy
run is as repeatable as an exact one. ``Sensors.read()`` gives one tick's
readings and gives the same values when asked again in that tick (the bridge
retransmits a tick during start-up, and a retransmission must not be a new sample).
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from humfall_ros.model.humanoid import SIDES


@dataclasses.dataclass(frozen=True)
class SensorNoise:
    """Standard deviations of additive Gaussian noise per sensor (0: exact)."""
    joint_position: float = 0.0    # rad, encoders
    joint_velocity: float = 0.0    # rad/s
    imu_orientation: float = 0.0   # rad, a random small rotation of the IMU's attitude estimate
    gyro: float = 0.0              # rad/s, per axis
    accelerometer: float = 0.0     # m/s^2, per axis
    force: float = 0.0             # N, per axis of each ankle F/T sensor
    torque: float = 0.0            # N m, per axis
    seed: int = 0

    def __post_init__(self):
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if f.name != "seed" and not (math.isfinite(v) and v >= 0.0):
                raise ValueError(f"sensor noise {f.name} must be a finite standard deviation >= 0, got {v}")

    @property
    def exact(self) -> bool:
        return all(getattr(self, f.name) == 0.0 for f in dataclasses.fields(self) if f.name != "seed")


@dataclasses.dataclass
class Readings:
    joint_position: np.ndarray
    joint_velocity: np.ndarray
    joint_effort: np.ndarray
    imu_orientation: np.ndarray    # x, y, z, w
    gyro: np.ndarray               # IMU frame
    accelerometer: np.ndarray      # IMU frame, proper acceleration
    wrenches: dict                 # side -> (force, torque) at the ankle, foot axes


def _small_rotation(quat_xyzw: np.ndarray, rotvec: np.ndarray) -> np.ndarray:
    """quat * exp(rotvec) (body-frame perturbation), as x, y, z, w."""
    angle = float(np.linalg.norm(rotvec))
    if angle < 1e-12:
        return quat_xyzw
    ax = rotvec / angle
    s, c = math.sin(angle / 2), math.cos(angle / 2)
    x1, y1, z1, w1 = quat_xyzw
    x2, y2, z2, w2 = ax[0] * s, ax[1] * s, ax[2] * s, c
    q = np.array([w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                  w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
                  w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
                  w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2])
    return q / np.linalg.norm(q)


class Sensors:
    """One tick's sensor readings of a SimWorld, with ``noise``; call ``reset()`` with the world's."""

    def __init__(self, world, noise: SensorNoise | None = None):
        self.world = world
        self.noise = noise or SensorNoise()
        self.reset()

    def reset(self) -> None:
        self.rng = np.random.default_rng(self.noise.seed)
        self._tick = None
        self._readings: Readings | None = None

    def read(self) -> Readings:
        w = self.world
        if self._readings is not None and self._tick == w.step_count:
            return self._readings
        q, v, tau = w.joint_states()
        orn, gyro, acc = w.imu()
        wrenches = {s: w.foot_wrench(s) for s in SIDES}
        r = Readings(q, v, tau, orn, gyro, acc, wrenches)
        if not self.noise.exact:
            r = self._noisy(r)
        self._tick, self._readings = w.step_count, r
        return r

    def _noisy(self, r: Readings) -> Readings:
        n, g = self.noise, self.rng
        nj = len(r.joint_position)
        # always draw every sample, so one sensor's setting does not shift the others' sequence
        d = g.standard_normal(2 * nj + 9 + 6 * len(SIDES))
        dq, dv, rest = d[:nj], d[nj:2 * nj], d[2 * nj:]
        wrenches = {}
        for i, s in enumerate(SIDES):
            f, t = r.wrenches[s]
            k = 9 + 6 * i
            wrenches[s] = (f + n.force * rest[k:k + 3], t + n.torque * rest[k + 3:k + 6])
        return Readings(r.joint_position + n.joint_position * dq, r.joint_velocity + n.joint_velocity * dv,
                        r.joint_effort, _small_rotation(r.imu_orientation, n.imu_orientation * rest[0:3]),
                        r.gyro + n.gyro * rest[3:6], r.accelerometer + n.accelerometer * rest[6:9], wrenches)


# A plausible humanoid's sensors (orders of magnitude, for experiments and the
# estimator figures): high-resolution encoders, velocities from differentiated
# encoders, a MEMS IMU with an attitude filter, 6-axis ankle F/T sensors.
TYPICAL_NOISE = SensorNoise(joint_position=1e-4, joint_velocity=0.01, imu_orientation=0.002, gyro=0.003,
                            accelerometer=0.05, force=2.0, torque=0.2)
