"""The humanoid's model on pinocchio: the single source of robot facts.

Masses, joint limits, feet, sole corners and hands all come from the URDF
through this module; controllers ask it instead of hard-coding numbers.

Configuration convention (pinocchio free-flyer): ``q = [x, y, z, qx, qy, qz, qw,
joints...]`` and ``v = [v_base (base frame), omega_base (base frame),
joint velocities...]``, joints in ``joint_names`` order.
"""
from __future__ import annotations

import copy
import dataclasses
import functools
import math

import numpy as np
import pinocchio as pin

from humfall_ros import paths
from humfall_ros.dynamics.pendulum import GRAVITY

SIDES = ("l", "r")
# One leg's joints from the hip to the ankle, without the side prefix ("l_" / "r_"): the URDF's names
LEG_JOINTS = ("hip_yaw", "hip_roll", "hip_pitch", "knee", "ankle_pitch", "ankle_roll")
# The nominal standing posture (joints not named are 0): bent knees put the CoM over the
# ankles and keep the knees away from the singular straight leg.
STANDING_POSTURE = {
    "l_hip_pitch": -0.35, "l_knee": 0.70, "l_ankle_pitch": -0.35,
    "r_hip_pitch": -0.35, "r_knee": 0.70, "r_ankle_pitch": -0.35,
    "l_shoulder_pitch": 0.1, "r_shoulder_pitch": 0.1,
    "l_shoulder_roll": 0.15, "r_shoulder_roll": -0.15,
    "l_elbow": -0.5, "r_elbow": -0.5,
}
TRUNK_LINK = "chest"  # the upper-body link: pushed in the scenarios, its tilt is the trunk tilt
CORNER_NAMES = ("toe_left", "toe_right", "heel_right", "heel_left")  # counter-clockwise seen from above


@dataclasses.dataclass(frozen=True)
class JointLimits:
    lower: np.ndarray
    upper: np.ndarray
    velocity: np.ndarray
    effort: np.ndarray


class HumanoidModel:
    """Kinematics and dynamics of the floating-base humanoid (pinocchio)."""

    def __init__(self, urdf_path: str | None = None):
        self.urdf_path = str(urdf_path or paths.urdf_path())
        self.model = pin.buildModelFromUrdf(self.urdf_path, pin.JointModelFreeFlyer())
        self.data = self.model.createData()
        self.joint_names: list[str] = list(self.model.names[2:])
        self.njoints = len(self.joint_names)
        self.total_mass = float(pin.computeTotalMass(self.model))
        self.weight = self.total_mass * GRAVITY
        m = self.model
        self.limits = JointLimits(
            lower=np.array(m.lowerPositionLimit[7:]), upper=np.array(m.upperPositionLimit[7:]),
            velocity=np.array(m.velocityLimit[6:]), effort=np.array(m.effortLimit[6:]))
        self.frame_ids = {f.name: i for i, f in enumerate(m.frames)}
        self.link_names = [f.name for f in m.frames if f.type == pin.FrameType.BODY]
        self.sole_frame = {s: f"{s}_sole" for s in SIDES}
        self.foot_link = {s: f"{s}_foot" for s in SIDES}
        self.hand_frame = {s: f"{s}_hand" for s in SIDES}
        self.imu_frame = "imu_link"
        self.trunk_link = TRUNK_LINK
        self.standing_posture = dict(STANDING_POSTURE)
        self.corner_frames = {s: [f"{s}_sole_{c}" for c in CORNER_NAMES] for s in SIDES}
        # sole rectangle in the foot (ankle) frame, from the corner frames
        q0 = self.neutral()
        pin.framesForwardKinematics(m, self.data, q0)
        self.sole_corners_local = {}
        for s in SIDES:
            foot = self.data.oMf[self.frame_ids[self.foot_link[s]]]
            self.sole_corners_local[s] = np.array(
                [(foot.inverse() * self.data.oMf[self.frame_ids[c]]).translation for c in self.corner_frames[s]])
        c = self.sole_corners_local["l"]
        self.foot_length = float(c[:, 0].max() - c[:, 0].min())
        self.foot_width = float(c[:, 1].max() - c[:, 1].min())
        self.ankle_height = float(-c[:, 2].mean())

    def with_own_data(self) -> HumanoidModel:
        """This model (URDF, frames, limits: shared) with pinocchio data of its own, so that kinematics computed on
        it do not overwrite this one's (a controller's IK, a sensed configuration)."""
        own = copy.copy(self)
        own.data = self.model.createData()
        return own

    # ------------------------------------------------------------------ basics
    @functools.cached_property
    def urdf_joints(self) -> list[tuple[str, str, str, bool]]:
        """(joint, parent link, child link, is_fixed) for every URDF joint: the TF tree."""
        import xml.etree.ElementTree as ET

        root = ET.parse(self.urdf_path).getroot()
        return [(j.get("name"), j.find("parent").get("link"), j.find("child").get("link"), j.get("type") == "fixed")
                for j in root.findall("joint")]

    @functools.cached_property
    def push_point(self) -> np.ndarray:
        """The trunk link's centre of mass in its own frame [m] (URDF inertial origin): where pushes act."""
        import xml.etree.ElementTree as ET

        link = ET.parse(self.urdf_path).getroot().find(f"link[@name='{self.trunk_link}']")
        origin = link.find("inertial/origin") if link is not None else None
        if origin is None:
            return np.zeros(3)
        return np.array([float(x) for x in origin.get("xyz", "0 0 0").split()])

    @property
    def root_link(self) -> str:
        return self.model.frames[2].name  # after universe and the free-flyer joint frame

    def link_transforms(self, fixed: bool) -> list[tuple[str, str, np.ndarray, np.ndarray]]:
        """(parent, child, translation, quaternion xyzw) per URDF joint of that kind, after forward()."""
        out = []
        for _, parent, child, is_fixed in self.urdf_joints:
            if is_fixed != fixed:
                continue
            T = self.data.oMf[self.frame_ids[parent]].actInv(self.data.oMf[self.frame_ids[child]])
            out.append((parent, child, T.translation.copy(), pin.Quaternion(T.rotation).coeffs().copy()))
        return out

    def neutral(self) -> np.ndarray:
        return pin.neutral(self.model)

    def joint_index(self, name: str) -> int:
        return self.joint_names.index(name)

    def leg_joint_indices(self, side: str) -> list[int]:
        """Model-order indices of one leg's joints (``side`` "l" or "r"), hip to ankle (``LEG_JOINTS``)."""
        return [self.joint_index(f"{side}_{j}") for j in LEG_JOINTS]

    def joint_vector(self, mapping: dict[str, float], default: float = 0.0) -> np.ndarray:
        """Joint-space vector in model order from a name->value mapping."""
        unknown = set(mapping) - set(self.joint_names)
        if unknown:
            raise KeyError(f"unknown joints: {sorted(unknown)}")
        return np.array([mapping.get(n, default) for n in self.joint_names], dtype=float)

    def configuration(self, base_position, base_quat_xyzw, joints) -> np.ndarray:
        q = np.empty(self.model.nq)
        q[:3] = base_position
        q[3:7] = np.asarray(base_quat_xyzw, dtype=float) / np.linalg.norm(base_quat_xyzw)
        q[7:] = joints
        return q

    def velocity(self, base_linear_world, base_angular_world, base_quat_xyzw, joint_velocities) -> np.ndarray:
        """Free-flyer velocity from world-frame base twist (pinocchio wants it in the base frame)."""
        R = quat_matrix(base_quat_xyzw)
        v = np.empty(self.model.nv)
        v[:3] = R.T @ np.asarray(base_linear_world, dtype=float)
        v[3:6] = R.T @ np.asarray(base_angular_world, dtype=float)
        v[6:] = joint_velocities
        return v

    # ------------------------------------------------------------- kinematics
    def forward(self, q, v=None) -> None:
        """Update kinematics (and CoM) for q (and v)."""
        if v is None:
            pin.forwardKinematics(self.model, self.data, q)
        else:
            pin.forwardKinematics(self.model, self.data, q, v)
        pin.updateFramePlacements(self.model, self.data)
        pin.centerOfMass(self.model, self.data, q, v if v is not None else np.zeros(self.model.nv), False)

    def com(self, q) -> np.ndarray:
        return pin.centerOfMass(self.model, self.data, q).copy()

    def com_jacobian(self, q) -> np.ndarray:
        """d com / d v (3 x nv)."""
        return pin.jacobianCenterOfMass(self.model, self.data, q).copy()

    def frame_position(self, name: str) -> np.ndarray:
        """World position of a frame after forward()."""
        return self.data.oMf[self.frame_ids[name]].translation.copy()

    def frame_placement(self, name: str) -> pin.SE3:
        return self.data.oMf[self.frame_ids[name]]

    def frame_jacobian(self, q, name: str) -> np.ndarray:
        """6 x nv Jacobian of a frame, LOCAL_WORLD_ALIGNED (linear first)."""
        return pin.computeFrameJacobian(self.model, self.data, q, self.frame_ids[name],
                                        pin.ReferenceFrame.LOCAL_WORLD_ALIGNED).copy()

    def swing_com_gain(self, q, side: str) -> np.ndarray:
        """How far the whole-body CoM moves horizontally per horizontal move of ``side``'s sole, the leg's joints alone
        moving (the rest of the body, its orientation and the sole's held), at ``q`` (2 x 2) [m/m].

        ``J_com[:2, leg] @ J_sole[:, leg]^-1[:, :2]`` (LOCAL_WORLD_ALIGNED; the leg's six joints make its sole
        Jacobian square). Paper 1's pendulum (eq. 1-2) moves a rigid body: the swing leg's own mass, carried to the
        landing, is what it leaves out (standing: 0.09 I)."""
        pin.computeJointJacobians(self.model, self.data, q)
        pin.updateFramePlacements(self.model, self.data)
        cols = [6 + i for i in self.leg_joint_indices(side)]
        J_com = pin.jacobianCenterOfMass(self.model, self.data, q, False)[:2, cols]
        J_sole = pin.getFrameJacobian(self.model, self.data, self.frame_ids[self.sole_frame[side]],
                                      pin.ReferenceFrame.LOCAL_WORLD_ALIGNED)[:, cols]
        return J_com @ np.linalg.pinv(J_sole, rcond=1e-6)[:, :2]

    def sole_corners(self, side: str) -> np.ndarray:
        """World positions (4 x 3, counter-clockwise) of a foot's sole corners after forward()."""
        return np.array([self.frame_position(f) for f in self.corner_frames[side]])

    # -------------------------------------------------------------- centroidal
    def centroidal(self, q, v) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(com, com velocity, angular momentum about the com) via pinocchio's CCRBA."""
        pin.ccrba(self.model, self.data, q, v)
        h = self.data.hg
        com = self.data.com[0].copy()
        return com, h.linear / self.total_mass, h.angular.copy()

    def crb_inertia(self, q) -> np.ndarray:
        """Composite-rigid-body (centroidal) rotational inertia about the CoM, world axes (3 x 3).

        This is the locked inertia paper 1 shapes in §IV (eq. 11-14).
        """
        pin.ccrba(self.model, self.data, q, np.zeros(self.model.nv))
        return self.data.Ig.inertia.copy()

    # --------------------------------------------------------------- contacts
    def foot_wrench_to_world(self, side: str, force_local, torque_local) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Wrench measured at a foot's ankle frame (foot-frame axes) as (origin, force, torque) in world."""
        M = self.frame_placement(self.foot_link[side])
        R = M.rotation
        return M.translation.copy(), R @ np.asarray(force_local, float), R @ np.asarray(torque_local, float)


def base_rotation_from_imu(model: HumanoidModel, data, imu_quat_xyzw) -> np.ndarray:
    """World rotation of the floating base from the IMU's world orientation (x, y, z, w), given ``data`` after a
    frames forward kinematics pass with the base at identity: the IMU's rotation composed with the inverse of its
    rotation in the base (through the waist joints) - the estimator's construction."""
    return quat_matrix(imu_quat_xyzw) @ data.oMf[model.frame_ids[model.imu_frame]].rotation.T


def base_angular_velocity_from_imu(model: HumanoidModel, data, imu_quat_xyzw, imu_gyro) -> np.ndarray:
    """World angular velocity of the floating base from the IMU (orientation x, y, z, w; gyro in the IMU frame), given
    ``data`` after a forward kinematics pass with the base at identity and at rest and the joints moving
    (``pin.forwardKinematics(m, data, q_rel, v_rel)`` and the frames' placements): the IMU sits on the chest, above
    the waist joints, so its gyro reads the base's angular velocity plus the waist joints' (the IMU frame's angular
    velocity in that pass) - the estimator's construction."""
    fid = model.frame_ids[model.imu_frame]
    imu_rel = pin.getFrameVelocity(model.model, data, fid, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED).angular
    return (quat_matrix(imu_quat_xyzw) @ np.asarray(imu_gyro, float)
            - base_rotation_from_imu(model, data, imu_quat_xyzw) @ imu_rel)


def imu_quaternion(imu) -> np.ndarray | None:
    """The world orientation (x, y, z, w) of an IMU reading, or None for a missing or unusable one.

    ``imu``: ``Observation.inputs["imu"]`` as the loops fill it, ``(orientation, gyro)``; also an object or dict
    with an ``orientation``, or the orientation array itself. Unusable: not four finite numbers, or a norm
    of 0.5 or less (not normalised here)."""
    if imu is None:
        return None
    if isinstance(imu, (tuple, list)):
        q = imu[0]
    elif isinstance(imu, np.ndarray):
        q = imu
    else:
        q = imu.get("orientation") if isinstance(imu, dict) else getattr(imu, "orientation", None)
    try:
        q = np.asarray(q, float).reshape(-1)
    except (TypeError, ValueError):
        return None
    return q if q.shape == (4,) and np.all(np.isfinite(q)) and np.linalg.norm(q) > 0.5 else None


def quat_matrix(q_xyzw) -> np.ndarray:
    """Rotation matrix of a quaternion (x, y, z, w), normalised first.

    Plain floats: the simulator and estimator call this several times per tick,
    and numpy's norm/array on 4 numbers cost ~20 us a call against ~3 us here.
    """
    x, y, z, w = (float(c) for c in q_xyzw)
    n = math.sqrt(x * x + y * y + z * z + w * w)
    x, y, z, w = x / n, y / n, z / n, w / n
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])



def cross3(a, b) -> np.ndarray:
    """a x b for 3-vectors; np.cross costs ~60 us a call (axis handling), this ~2 us."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def cop_from_wrenches(wrenches, ground_height: float = 0.0, min_normal: float = 1.0):
    """Centre of pressure on the ground plane from world-frame wrenches.

    ``wrenches``: iterable of (origin, force, torque) with torque about origin.
    The CoP is the point p on the plane z = h about which the net moment has no
    horizontal component: tau_x = p_y f_z - h f_y, tau_y = h f_x - p_x f_z.
    Returns (cop (3,), total normal force), cop is None if unloaded.
    """
    f_tot = np.zeros(3)
    tau_tot = np.zeros(3)  # about the world origin
    for o, f, t in wrenches:
        o = np.asarray(o, float)
        f = np.asarray(f, float)
        f_tot += f
        tau_tot += np.asarray(t, float) + cross3(o, f)
    fz = f_tot[2]
    if fz < min_normal:
        return None, float(fz)
    h = ground_height
    # tau = p x f + tau_z_free with p = (px, py, h):
    # tau_x = py fz - h fy ; tau_y = h fx - px fz
    px = (h * f_tot[0] - tau_tot[1]) / fz
    py = (tau_tot[0] + h * f_tot[1]) / fz
    return np.array([px, py, h]), float(fz)


def support_polygon(points) -> np.ndarray:
    """Convex hull (counter-clockwise, 2-D) of ground contact points.

    Andrew's monotone chain: the support polygon has at most 8 points (the sole
    corners) and is needed every control tick; scipy's Qhull costs ~1 ms a call
    here for that, this ~20 us. test_model checks it against scipy.spatial.ConvexHull.
    Degenerate sets (one point, a segment) come back as their extreme points.
    """
    pts = sorted({(float(p[0]), float(p[1])) for p in points})
    if len(pts) <= 2:
        return np.array(pts, dtype=float).reshape(-1, 2)

    def cross(o, a, b):
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    lower: list = []
    for p in pts:
        while len(lower) >= 2 and cross(lower[-2], lower[-1], p) <= 1e-12:
            lower.pop()
        lower.append(p)
    upper: list = []
    for p in reversed(pts):
        while len(upper) >= 2 and cross(upper[-2], upper[-1], p) <= 1e-12:
            upper.pop()
        upper.append(p)
    hull = lower[:-1] + upper[:-1]
    return np.array(hull, dtype=float)


def point_in_polygon_margin(point, polygon) -> float:
    """Signed distance of a 2-D point to a convex counter-clockwise polygon (>0 inside)."""
    p = np.asarray(point, float)[:2]
    poly = np.asarray(polygon, float)
    if len(poly) < 3:
        if len(poly) == 0:
            return -math.inf
        if len(poly) == 1:
            return -float(np.linalg.norm(p - poly[0]))
        a, b = poly[0], poly[1]
        t = np.clip(np.dot(p - a, b - a) / max(np.dot(b - a, b - a), 1e-12), 0, 1)
        return -float(np.linalg.norm(p - (a + t * (b - a))))
    margin = math.inf
    n = len(poly)
    for i in range(n):
        a, b = poly[i], poly[(i + 1) % n]
        e = b - a
        length = math.hypot(e[0], e[1])
        if length < 1e-12:
            continue
        # inward normal of a CCW edge is (-e_y, e_x)
        d = ((p[0] - a[0]) * -e[1] + (p[1] - a[1]) * e[0]) / length
        margin = min(margin, d)
    return float(margin)


@functools.lru_cache(maxsize=None)
def load_model(urdf_path: str | None = None) -> HumanoidModel:
    """A shared model instance per URDF (building it parses the URDF)."""
    return HumanoidModel(urdf_path)
