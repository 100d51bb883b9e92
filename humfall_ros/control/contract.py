"""The controller contract: what every joint-command source of the suite is.

A controller is a plain class (no rclpy, no simulator) with

* ``source``: its command source name on the mux (``joint_command/<source>``),
* ``reset()``: forget everything (a new run, or sim time went back),
* ``step(observation) -> JointTargets | None``: the command for one control tick;
  ``None`` is a **release** (the source yields the robot this tick).

The in-process loop (``humfall_ros.sim.closed_loop``) and the controller's node
call it the same way, with the same numbers (the node builds the
:class:`Observation` from the messages of the tick, the loop from the estimator's
output, through :func:`centroidal_from_estimate`, which keeps exactly the fields of
``humfall_interfaces/CentroidalState``), so a scenario gives the same joint states
in process and over ROS.

A source that has **taken over** (its first non-empty command after releasing)
keeps the robot until it releases: the mux never hands a falling robot back to a
lower source on a timeout. ``Observation.active_source`` says which source drove
the robot during the tick that ended at this observation, so a controller that
regains control can start from the measured posture (bumpless transfer).
"""
from __future__ import annotations

import dataclasses
from typing import Any, Protocol, runtime_checkable

import numpy as np


@dataclasses.dataclass
class CentroidalObservation:
    """The fields of ``humfall_interfaces/msg/CentroidalState`` (world frame, ground z = 0).

    Attributes:
        com: centre of mass G [m], (3,).
        com_velocity: dG/dt [m/s], (3,).
        cop: centre of pressure P [m], (3,), z = 0.
        capture_point: Q, paper 1 eq. 1-2 [m], (3,), z = 0.
        angular_momentum: centroidal angular momentum [kg m^2/s], (3,).
        support_polygon: convex hull of the sole corners in contact, counter-clockwise [m], (k, 2).
        feet_center: mid-point of the ankle frames [m], (3,).
        lean_angle: angle of P->G to the vertical [rad].
        lean_direction: heading of the P->G ground projection [rad].
        normal_force: total vertical ground reaction [N].
        left_contact, right_contact: foot loaded.
        cop_on_edge: P on the support polygon boundary.
        left_normal_force, right_normal_force: vertical ground reaction under each foot [N] (its own ankle
            wrench).
        left_cop, right_cop: each foot's own centre of pressure [m], (3,), z = 0 (below its ankle when unloaded).
        com_velocity_fused, capture_point_fused: the estimator's complementary-filter CoM velocity and its
            capture point [m/s], [m] (3,): robust to stance-foot slip, late behind an unmeasured push (walking and
            the e-stop read them; the fall trigger and the safe fall read ``com_velocity`` / ``capture_point``).
            None: the same as those.
    """

    com: np.ndarray
    com_velocity: np.ndarray
    cop: np.ndarray
    capture_point: np.ndarray
    angular_momentum: np.ndarray
    support_polygon: np.ndarray
    feet_center: np.ndarray
    lean_angle: float
    lean_direction: float
    normal_force: float
    left_contact: bool
    right_contact: bool
    cop_on_edge: bool
    left_normal_force: float = 0.0
    right_normal_force: float = 0.0
    left_cop: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(3))
    right_cop: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(3))
    com_velocity_fused: np.ndarray | None = None
    capture_point_fused: np.ndarray | None = None

    def __post_init__(self):
        if self.com_velocity_fused is None:
            self.com_velocity_fused = np.asarray(self.com_velocity, float).copy()
        if self.capture_point_fused is None:
            self.capture_point_fused = np.asarray(self.capture_point, float).copy()

    @property
    def contacts(self) -> dict[str, bool]:
        return {"l": self.left_contact, "r": self.right_contact}

    @property
    def foot_normal_forces(self) -> dict[str, float]:
        """side -> vertical ground reaction under that foot [N]."""
        return {"l": self.left_normal_force, "r": self.right_normal_force}

    @property
    def foot_cops(self) -> dict[str, np.ndarray]:
        """side -> that foot's own centre of pressure [m] (3,)."""
        return {"l": self.left_cop, "r": self.right_cop}


def centroidal_from_estimate(e) -> CentroidalObservation:
    """The message's view of a ``CentroidalEstimate`` (what a node would receive).

    Support polygon points lose nothing (the message carries float64 x, y and z = 0).
    """
    poly = np.asarray(e.support_polygon, float).reshape(-1, 2)
    return CentroidalObservation(
        com=np.asarray(e.com, float).copy(), com_velocity=np.asarray(e.com_velocity, float).copy(),
        cop=np.asarray(e.cop, float).copy(), capture_point=np.asarray(e.capture_point, float).copy(),
        angular_momentum=np.asarray(e.angular_momentum, float).copy(), support_polygon=poly.copy(),
        feet_center=np.asarray(e.feet_center, float).copy(), lean_angle=float(e.lean_angle),
        lean_direction=float(e.lean_direction), normal_force=float(e.normal_force),
        left_contact=bool(e.contacts["l"]), right_contact=bool(e.contacts["r"]),
        cop_on_edge=bool(e.cop_on_edge),
        left_normal_force=float(e.foot_normal_force["l"]), right_normal_force=float(e.foot_normal_force["r"]),
        left_cop=np.asarray(e.foot_cop["l"], float).copy(), right_cop=np.asarray(e.foot_cop["r"], float).copy(),
        com_velocity_fused=np.asarray(e.com_velocity_fused, float).copy(),
        capture_point_fused=np.asarray(e.capture_point_fused, float).copy())


@dataclasses.dataclass
class Observation:
    """Everything a controller may use at one control tick.

    Attributes:
        stamp_ns: the tick's sim time [ns] (the lockstep identity of the tick).
        joint_position: measured joint positions [rad], model order (``HumanoidModel.joint_names``).
        joint_velocity: measured joint velocities [rad/s], model order.
        state: the estimator's centroidal state of this tick.
        active_source: the mux's source during the tick that ended here ("" or "none": none).
        joint_targets: the joint position targets the servos tracked during that tick [rad],
            model order (None if unknown): a source taking over starts from them (bumpless).
        inputs: further per-tick inputs by name (e.g. ``"ftb/status"``, ``"walking/state"``)
            and latched ones (``"fall_event"``, ``"obstacles"``, ``"estop"``), as plain
            dataclasses of the functional core; a node fills them from its messages.
    """

    stamp_ns: int
    joint_position: np.ndarray
    joint_velocity: np.ndarray
    state: CentroidalObservation
    active_source: str = ""
    inputs: dict[str, Any] = dataclasses.field(default_factory=dict)
    joint_targets: np.ndarray | None = None

    @property
    def time(self) -> float:
        """Sim time [s]."""
        return self.stamp_ns * 1e-9


@dataclasses.dataclass(frozen=True)
class Obstacle:
    """A box in the world (the ``obstacles`` topic): centre [m], full extents [m], yaw [rad]."""

    name: str
    position: tuple[float, float, float]
    size: tuple[float, float, float]
    yaw: float = 0.0
    is_target: bool = False


@dataclasses.dataclass
class JointTargets:
    """A joint command in model order: position targets [rad], optional velocity targets [rad/s]."""

    positions: np.ndarray
    velocities: np.ndarray | None = None


@runtime_checkable
class Controller(Protocol):
    """A joint-command source (see the module docstring)."""

    source: str

    def reset(self) -> None: ...

    def step(self, observation: Observation) -> JointTargets | None: ...


def stamp_ns_of(t: float) -> int:
    """Sim time [s] -> the integer nanoseconds stamps carry (the bridge's rounding)."""
    return int(round(t * 1e9))


__all__ = ["CentroidalObservation", "Controller", "JointTargets", "Observation", "Obstacle", "centroidal_from_estimate",
           "stamp_ns_of"]
