"""The e-stop's Major/Minor frame (paper 3, Fig. 3) and the feet it is built from. No rclpy, no simulator.

The Major axis (``y``) points from the centre of the right sole to the centre of the left
sole; the Minor axis (``x``) is its horizontal normal with ``x, y, z`` right-handed. The origin
lies on the Major axis (so the Minor-axis ZMP reference, the feet's centre line, is ``x = 0``)
at the orthogonal projection of the reference ZMP at the stop's start, so ``pbar_y(0) = 0``
(§IV-C: the origin is the desired ZMP at the beginning of the double-support phase).
"""
from __future__ import annotations

import dataclasses

import numpy as np

from humfall_ros.model.humanoid import SIDES, HumanoidModel, support_polygon


@dataclasses.dataclass(frozen=True)
class FootPose:
    """A foot's ankle frame (the model's ``foot_link``) in the world.

    Attributes:
        position: ankle frame origin [m], (3,).
        rotation: world rotation of the foot frame, (3, 3).
    """

    position: np.ndarray
    rotation: np.ndarray

    @staticmethod
    def flat(x: float, y: float, yaw: float, ankle_height: float) -> FootPose:
        """A foot flat on the ground z = 0 with heading ``yaw`` [rad]."""
        c, s = np.cos(yaw), np.sin(yaw)
        R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        return FootPose(np.array([x, y, ankle_height]), R)

    def sole_corners(self, model: HumanoidModel, side: str) -> np.ndarray:
        """World sole corners (4, 3), counter-clockwise, from the model's sole rectangle."""
        return self.position + model.sole_corners_local[side] @ self.rotation.T

    def sole_center(self, model: HumanoidModel, side: str) -> np.ndarray:
        """World centre of the sole rectangle [m], (3,)."""
        return self.sole_corners(model, side).mean(axis=0)


def double_support_polygon(model: HumanoidModel, feet: dict[str, FootPose]) -> np.ndarray:
    """Convex hull (k, 2), counter-clockwise, of both soles' corners [m]."""
    return support_polygon(np.vstack([feet[s].sole_corners(model, s)[:, :2] for s in SIDES]))


@dataclasses.dataclass(frozen=True)
class StopFrame:
    """The Major/Minor frame on the ground (Fig. 3).

    Attributes:
        origin: world xy of the origin [m], (2,).
        major: unit world xy of the Major axis y (right sole centre -> left sole centre), (2,).
        minor: unit world xy of the Minor axis x, (2,) (``minor x major`` = +z).
        rotation: columns minor (x) and major (y) in world xy, (2, 2) (derived).
    """

    origin: np.ndarray
    major: np.ndarray
    minor: np.ndarray
    rotation: np.ndarray = dataclasses.field(init=False, repr=False, compare=False)

    def __post_init__(self):
        object.__setattr__(self, "rotation", np.column_stack([self.minor, self.major]))

    @staticmethod
    def from_feet(left_center, right_center, zmp) -> StopFrame:
        """Frame from the sole centres and the reference ZMP [m] (world; only x, y are read)."""
        lc = np.asarray(left_center, float)[:2]
        rc = np.asarray(right_center, float)[:2]
        d = lc - rc
        n = float(np.hypot(d[0], d[1]))
        if n < 1e-6:
            raise ValueError("the sole centres coincide: no Major axis")
        major = d / n
        minor = np.array([major[1], -major[0]])
        z = np.asarray(zmp, float)[:2]
        origin = rc + major * float((z - rc) @ major)
        return StopFrame(origin, major, minor)

    def to_local(self, p) -> np.ndarray:
        """World xy (..., 2) -> (minor x, major y) [m]."""
        return (np.asarray(p, float)[..., :2] - self.origin) @ self.rotation

    def vector_to_local(self, v) -> np.ndarray:
        """A world xy vector (..., 2) (velocity, acceleration) -> (minor, major) components."""
        return np.asarray(v, float)[..., :2] @ self.rotation

    def to_world(self, local) -> np.ndarray:
        """(minor x, major y) (..., 2) -> world xy [m]."""
        return np.asarray(local, float) @ self.rotation.T + self.origin

    def vector_to_world(self, local) -> np.ndarray:
        return np.asarray(local, float) @ self.rotation.T

    def moved(self, motion: PlanarMotion) -> StopFrame:
        """This frame carried by a rigid planar motion (e.g. from the pattern's feet onto the measured ones)."""
        major = motion.rotation @ self.major
        return StopFrame(motion.apply(self.origin), major, np.array([major[1], -major[0]]))


@dataclasses.dataclass(frozen=True)
class PlanarMotion:
    """A rigid motion of the ground plane: ``p -> rotation @ p + translation`` [m].

    Attributes:
        rotation: (2, 2); translation: [m] (2,).
    """

    rotation: np.ndarray
    translation: np.ndarray

    @property
    def yaw(self) -> float:
        """Its rotation angle [rad]."""
        return float(np.arctan2(self.rotation[1, 0], self.rotation[0, 0]))

    def apply(self, p) -> np.ndarray:
        """World xy (..., 2) moved [m]."""
        return np.asarray(p, float)[..., :2] @ self.rotation.T + self.translation

    @staticmethod
    def between_feet(left_from, right_from, left_to, right_to) -> PlanarMotion:
        """The rigid motion taking two sole centres onto two others (exact when their distances agree; otherwise
        the mid-points coincide and the left-right directions align) [m], xy read."""
        a0, b0 = np.asarray(left_from, float)[:2], np.asarray(right_from, float)[:2]
        a1, b1 = np.asarray(left_to, float)[:2], np.asarray(right_to, float)[:2]
        d0, d1 = a0 - b0, a1 - b1
        yaw = float(np.arctan2(d1[1], d1[0]) - np.arctan2(d0[1], d0[0]))
        c, s = np.cos(yaw), np.sin(yaw)
        R = np.array([[c, -s], [s, c]])
        return PlanarMotion(R, 0.5 * (a1 + b1) - R @ (0.5 * (a0 + b0)))


__all__ = ["FootPose", "PlanarMotion", "StopFrame", "double_support_polygon"]
