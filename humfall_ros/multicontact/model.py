"""Planar (sagittal) robot model for the multi-contact planner (paper 2, Sec. III-C.1).

The model is derived from the robot URDF with pinocchio: a planar root (x, z,
pitch) as a composite PX-PZ-RY joint, the in-plane joints kept (hip pitch, knee,
ankle pitch per leg, shoulder pitch and elbow per arm) and every other joint
locked at zero with ``buildReducedModel``. That gives n = 13 coordinates and
m = 10 actuated joints, as in the paper's Table I.

pinocchio has no casadi bindings in the wheel, so the chain parameters (joint
placements, masses, CoM levers, pitch inertias, frame offsets) are read from the
reduced pinocchio model and the planar kinematics and dynamics of eq. 1 are
written symbolically in casadi SX here. The unit tests compare them against
pinocchio's ``crba``/``rnea``/frame Jacobians at random configurations.

Contacts (Sec. III-A): four extremities LF, RF (flat feet, toe and heel points
from the sole-corner frames) and LH, RH (hand frames). Environment: ground z = 0
and optionally a vertical wall, the plane x = wall_distance, facing -x.
"""
from __future__ import annotations

import dataclasses
import functools
import math

import casadi as ca
import numpy as np
import pinocchio as pin

from humfall_ros import paths

GRAVITY = 9.81

# In-plane joints kept in the planar model (everything else locked at 0).
PLANAR_JOINTS = (
    "l_hip_pitch", "l_knee", "l_ankle_pitch",
    "r_hip_pitch", "r_knee", "r_ankle_pitch",
    "l_shoulder_pitch", "l_elbow",
    "r_shoulder_pitch", "r_elbow",
)
ROOT_NAMES = ("root_x", "root_z", "root_pitch")
EXTREMITIES = ("LF", "RF", "LH", "RH")
FEET = ("LF", "RF")
HANDS = ("LH", "RH")
# Sole-corner frames: in the sagittal plane the left/right corners coincide;
# the point used is their mean.
_FOOT_FRAMES = {
    "LF": (("l_sole_toe_left", "l_sole_toe_right"), ("l_sole_heel_left", "l_sole_heel_right")),
    "RF": (("r_sole_toe_left", "r_sole_toe_right"), ("r_sole_heel_left", "r_sole_heel_right")),
}
_HAND_FRAMES = {"LH": "l_hand", "RH": "r_hand"}
# Points of the non-contact links kept away from ground and wall (Sec. III-C.2):
# joint origins and the head frame.
_BODY_JOINTS = ("l_knee", "r_knee", "l_elbow", "r_elbow", "l_ankle_pitch", "r_ankle_pitch",
                "l_hip_pitch", "l_shoulder_pitch")
_BODY_FRAMES = ("head",)
# Mirror map between left and right coordinates (planar model is symmetric).
_MIRROR = {"LF": "RF", "RF": "LF", "LH": "RH", "RH": "LH"}


def _planar_root() -> pin.JointModelComposite:
    root = pin.JointModelComposite(pin.JointModelPX())
    root.addJoint(pin.JointModelPZ())
    root.addJoint(pin.JointModelRY())
    return root


def _pitch_of(rot: np.ndarray) -> float:
    """Angle of a rotation about y; refuses out-of-plane rotations."""
    if abs(rot[1, 1] - 1.0) > 1e-9:
        raise ValueError("joint placement rotates out of the sagittal plane")
    return math.atan2(rot[0, 2], rot[0, 0])


@dataclasses.dataclass
class Body:
    joint: int          # pinocchio joint id in the reduced model
    parent: int         # parent joint id (0: world)
    offset: tuple       # (x, z) of the joint origin in the parent joint frame
    offset_pitch: float  # pitch of the joint placement
    q_index: int        # index into q of this joint (revolute) or -1 (root)
    mass: float
    com: tuple          # (x, z) in the joint frame
    inertia_yy: float   # about the CoM


class PlanarModel:
    """Sagittal model of the robot: pinocchio reference + casadi expressions.

    Attributes use the paper's symbols: ``n`` coordinates, ``m`` actuators,
    ``B`` the input matrix of eq. 1.
    """

    def __init__(self, urdf: str | None = None):
        self.urdf = str(urdf or paths.urdf_path())
        full = pin.buildModelFromUrdf(self.urdf, _planar_root())
        lock = [full.getJointId(nm) for nm in full.names[2:] if nm not in PLANAR_JOINTS]
        self.pin_model = pin.buildReducedModel(full, lock, pin.neutral(full))
        self.pin_data = self.pin_model.createData()
        pm = self.pin_model
        if pm.nq != 3 + len(PLANAR_JOINTS) or pm.nv != pm.nq:
            raise ValueError(f"unexpected planar model size nq={pm.nq}")
        self.n = pm.nv
        self.m = self.n - 3
        self.joint_names = [pm.names[j] for j in range(2, pm.njoints)]
        self.coordinate_names = list(ROOT_NAMES) + self.joint_names
        self.q_index = {nm: 3 + i for i, nm in enumerate(self.joint_names)}
        # Input matrix B (eq. 1): joints actuated, root not.
        self.B = np.zeros((self.n, self.m))
        self.B[3:, :] = np.eye(self.m)
        # Limits from the URDF (eq. 6).
        self.q_min = np.array(pm.lowerPositionLimit[3:])
        self.q_max = np.array(pm.upperPositionLimit[3:])
        self.v_max = np.array(pm.velocityLimit[3:])
        self.u_max = np.array(pm.effortLimit[3:])
        self.bodies = self._extract_bodies()
        self.total_mass = float(sum(b.mass for b in self.bodies))
        self.points = self._extract_points()
        self.mirror_perm = self._mirror_permutation()
        self._build_casadi()

    # ----------------------------------------------------------- extraction
    def _extract_bodies(self) -> list[Body]:
        pm = self.pin_model
        bodies = []
        for j in range(1, pm.njoints):
            pl = pm.jointPlacements[j]
            inert = pm.inertias[j]
            if j == 1:
                if not np.allclose(pl.homogeneous, np.eye(4)):
                    raise ValueError("root placement must be identity")
                qi = -1
            else:
                if pm.joints[j].shortname() != "JointModelRY":
                    raise ValueError(f"joint {pm.names[j]} is not a pitch joint")
                qi = pm.joints[j].idx_q
            bodies.append(Body(
                joint=j, parent=pm.parents[j],
                offset=(float(pl.translation[0]), float(pl.translation[2])),
                offset_pitch=_pitch_of(pl.rotation), q_index=qi,
                mass=float(inert.mass),
                com=(float(inert.lever[0]), float(inert.lever[2])),
                inertia_yy=float(inert.inertia[1, 1]),
            ))
        return bodies

    def _frame_point(self, name: str) -> tuple[int, tuple]:
        pm = self.pin_model
        fid = pm.getFrameId(name)
        if fid >= pm.nframes:
            raise KeyError(f"frame {name} not in the URDF")
        f = pm.frames[fid]
        t = f.placement.translation
        return f.parentJoint, (float(t[0]), float(t[2]))

    def _extract_points(self) -> dict[str, tuple[int, tuple]]:
        """Named points (joint id, local x-z offset) used for contacts and clearance."""
        pts = {}
        for ext, (toes, heels) in _FOOT_FRAMES.items():
            for tag, names in (("toe", toes), ("heel", heels)):
                js, offs = zip(*(self._frame_point(nm) for nm in names))
                if len(set(js)) != 1:
                    raise ValueError("sole corners on different links")
                pts[f"{ext}_{tag}"] = (js[0], tuple(np.mean(offs, axis=0)))
        for ext, nm in _HAND_FRAMES.items():
            pts[ext] = self._frame_point(nm)
        pm = self.pin_model
        for nm in _BODY_JOINTS:
            pts[nm] = (pm.getJointId(nm), (0.0, 0.0))
        for nm in _BODY_FRAMES:
            pts[nm] = self._frame_point(nm)
        return pts

    def _mirror_permutation(self) -> np.ndarray:
        perm = np.arange(self.n)
        for nm, i in self.q_index.items():
            other = ("r_" + nm[2:]) if nm.startswith("l_") else ("l_" + nm[2:])
            perm[i] = self.q_index[other]
        return perm

    # ------------------------------------------------------------- casadi
    def _poses(self, q):
        """World planar pose (x, z, pitch) of every joint frame (id -> tuple)."""
        poses = {0: (0.0, 0.0, 0.0)}
        for b in self.bodies:
            if b.q_index < 0:
                poses[b.joint] = (q[0], q[1], q[2])
                continue
            px, pz, pth = poses[b.parent]
            c, s = ca.cos(pth), ca.sin(pth)
            ox, oz = b.offset
            x = px + c * ox + s * oz
            z = pz - s * ox + c * oz
            poses[b.joint] = (x, z, pth + b.offset_pitch + q[b.q_index])
        return poses

    @staticmethod
    def _apply(pose, off):
        x, z, th = pose
        c, s = ca.cos(th), ca.sin(th)
        return ca.vertcat(x + c * off[0] + s * off[1], z - s * off[0] + c * off[1])

    def _build_casadi(self):
        n = self.n
        q = ca.SX.sym("q", n)
        v = ca.SX.sym("v", n)
        a = ca.SX.sym("a", n)
        poses = self._poses(q)
        # Inverse dynamics by projected Newton-Euler: sum over bodies of
        # J_c^T m (a_c + g) + J_th^T I alpha; equals D a + C v + G of eq. 1.
        tau = ca.SX.zeros(n)
        D = ca.SX.zeros(n, n)
        com_num = ca.SX.zeros(2)
        potential = 0
        for b in self.bodies:
            pc = self._apply(poses[b.joint], b.com)
            th = poses[b.joint][2]
            Jc = ca.jacobian(pc, q)
            Jth = ca.jacobian(th, q)
            vc = Jc @ v
            ac = Jc @ a + ca.jacobian(vc, q) @ v
            alpha = Jth @ a  # planar pitch Jacobian is constant
            tau += Jc.T @ (b.mass * (ac + ca.vertcat(0, GRAVITY))) + Jth.T * (b.inertia_yy * alpha)
            D += b.mass * (Jc.T @ Jc) + b.inertia_yy * (Jth.T @ Jth)
            com_num += b.mass * pc
            potential += b.mass * GRAVITY * pc[1]
        com = com_num / self.total_mass
        self.f_id = ca.Function("inverse_dynamics", [q, v, a], [tau])
        self.f_D = ca.Function("D", [q], [D])
        self.f_bias = ca.Function("bias", [q, v], [ca.substitute(tau, a, ca.SX.zeros(n))])
        self.f_com = ca.Function("com", [q], [com])
        ke = 0.5 * ca.dot(v, D @ v)
        self.f_ke = ca.Function("ke", [q, v], [ke])
        names = list(self.points)
        pts = [self._apply(poses[self.points[nm][0]], self.points[nm][1]) for nm in names]
        P = ca.horzcat(*pts)  # 2 x npoints
        self.point_names = names
        self.f_points = ca.Function("points", [q], [P])
        self.f_point = {nm: ca.Function(f"p_{nm}", [q], [pts[i]]) for i, nm in enumerate(names)}
        self.f_point_jac = {nm: ca.Function(f"J_{nm}", [q], [ca.jacobian(pts[i], q)])
                            for i, nm in enumerate(names)}
        # Jdot v of each point (acceleration-level contact rows: J a + Jdot v).
        self.f_point_dJv = {}
        for i, nm in enumerate(names):
            Jv = ca.jacobian(pts[i], q) @ v
            self.f_point_dJv[nm] = ca.Function(f"dJv_{nm}", [q, v], [ca.jacobian(Jv, q) @ v])
        self.f_pitch = {b.joint: ca.Function(f"th_{b.joint}", [q], [poses[b.joint][2]]) for b in self.bodies}
        # Symbolic handles for NLP construction (SX graphs reused by callers).
        self._sx_q = q

    # ----------------------------------------------------------- numerics
    def D(self, q) -> np.ndarray:
        return np.array(self.f_D(q))

    def bias(self, q, v) -> np.ndarray:
        """C(q, v) v + G(q) of eq. 1."""
        return np.array(self.f_bias(q, v)).ravel()

    def kinetic_energy(self, q, v) -> float:
        return float(self.f_ke(q, v))

    def com(self, q) -> np.ndarray:
        return np.array(self.f_com(q)).ravel()

    def com_velocity(self, q, v, eps: float = 1e-6) -> np.ndarray:
        """(x, z) velocity of the centre of mass: its Jacobian times v, by a central difference along v."""
        q = np.asarray(q, float)
        v = np.asarray(v, float)
        return (self.com(q + eps * v) - self.com(q - eps * v)) / (2 * eps)

    def point(self, name: str, q) -> np.ndarray:
        return np.array(self.f_point[name](q)).ravel()

    def point_jacobian(self, name: str, q) -> np.ndarray:
        return np.array(self.f_point_jac[name](q))

    def all_points(self, q) -> dict[str, np.ndarray]:
        P = np.array(self.f_points(q))
        return {nm: P[:, i] for i, nm in enumerate(self.point_names)}

    def mirror(self, x: np.ndarray) -> np.ndarray:
        """Swap left and right coordinates of a configuration or velocity."""
        return np.asarray(x)[self.mirror_perm]

    def is_symmetric(self, q, v, tol: float = 1e-9) -> bool:
        return bool(np.allclose(self.mirror(q), q, atol=tol) and np.allclose(self.mirror(v), v, atol=tol))

    def skeleton(self, q) -> list[tuple[np.ndarray, np.ndarray]]:
        """Line segments (parent joint -> joint, joint -> extremity) for stick figures."""
        poses = self._poses(ca.DM(q))
        pos = {j: np.array([float(p[0]), float(p[1])]) for j, p in poses.items()}
        segs = []
        for b in self.bodies:
            if b.parent > 0:
                segs.append((pos[b.parent], pos[b.joint]))
        for nm, (j, off) in self.points.items():
            if nm in ("LH", "RH") or nm.endswith(("_toe", "_heel")) or nm == "head":
                segs.append((pos[j], self.point(nm, q)))
        for ext in FEET:
            segs.append((self.point(f"{ext}_toe", q), self.point(f"{ext}_heel", q)))
        return segs

    # ------------------------------------------------------- pinocchio side
    def pin_crba(self, q) -> np.ndarray:
        M = pin.crba(self.pin_model, self.pin_data, self.to_pin_q(q))
        return np.triu(M) + np.triu(M, 1).T

    def pin_rnea(self, q, v, a) -> np.ndarray:
        return np.array(pin.rnea(self.pin_model, self.pin_data, self.to_pin_q(q), np.asarray(v, float),
                                 np.asarray(a, float)))

    def to_pin_q(self, q) -> np.ndarray:
        # The composite PX-PZ-RY root is parameterised by (x, z, pitch) directly.
        return np.asarray(q, float).copy()


@functools.lru_cache(maxsize=2)
def load_model(urdf: str | None = None) -> PlanarModel:
    """One planar model per URDF per process (building the casadi graphs costs ~0.5 s)."""
    return PlanarModel(urdf)


def mirror_extremity(name: str) -> str:
    return _MIRROR[name]
