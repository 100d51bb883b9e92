"""The PyBullet world: ground, robot, obstacles, pushes and sensors. No rclpy.

One ``SimWorld`` owns one PyBullet client in DIRECT mode. Physics runs at
``physics_rate``; ``step_control()`` advances one control tick
(``physics_rate / control_rate`` physics steps) with the current joint targets.
Recreate the world (``reset()``) for repeatable runs: PyBullet is
deterministic given the same commands from a fresh world.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pybullet as pb

from humfall_ros import params as params_mod
from humfall_ros.control.contract import Obstacle
from humfall_ros.dynamics.pendulum import GRAVITY
from humfall_ros.model.humanoid import SIDES, HumanoidModel, load_model, quat_matrix
from humfall_ros.model.humanoid import STANDING_POSTURE as _STANDING_POSTURE
from humfall_ros.sim.push import MAX_PUSH_FORCE, validate_push  # noqa: F401 - MAX_PUSH_FORCE re-exported



def tick_contacts(substep_contacts: list) -> tuple:
    """One tick's contact points from each physics substep's ``getContactPoints``: all points, their
    normal and lateral friction forces (entries 9, 10, 12) divided by the substep count, the rest as
    PyBullet reports them (bodies, links, positions, normal and friction directions, distance)."""
    n = len(substep_contacts)
    if n == 1:
        return tuple(substep_contacts[0])
    return tuple(cp[:9] + (cp[9] / n, cp[10] / n, cp[11], cp[12] / n, cp[13])
                 for pts in substep_contacts for cp in pts)


# an obstacle box of the world: the controllers' contract.Obstacle (one definition)
Box = Obstacle


@dataclasses.dataclass
class Push:
    force: np.ndarray           # world frame, N
    point: np.ndarray           # in the link frame (URDF frame), m
    link: str
    start: float                # sim time, s
    duration: float

    def active(self, t: float) -> bool:
        return self.start <= t < self.start + self.duration - 1e-12


STANDING_POSTURE = _STANDING_POSTURE  # the model's (kept importable from here)


class SimWorld:
    def __init__(self, physics_rate: float = 1000.0, control_rate: float = 500.0,
                 friction: float = 0.9, servo_time_constant: float | None = None, velocity_gain: float = 1.0,
                 model: HumanoidModel | None = None, initial_posture: dict | None = None,
                 enforce_velocity_limits: bool = True, contact_breaking_threshold: float | None = None):
        if physics_rate % control_rate:
            raise ValueError("physics_rate must be an integer multiple of control_rate")
        self.physics_rate = float(physics_rate)
        self.control_rate = float(control_rate)
        self.substeps = int(round(physics_rate / control_rate))
        self.dt = 1.0 / physics_rate
        self.friction = friction
        # Bullet's persistent contact points are dropped when their two witness points drift apart
        # sideways by more than this [m] (Bullet's own default 0.02 drops loaded sole corners; None: the
        # declared default of config/sim_bridge.yaml)
        if contact_breaking_threshold is None:
            contact_breaking_threshold = params_mod.defaults("sim_bridge")["contact_breaking_threshold"]
        self.contact_breaking_threshold = float(contact_breaking_threshold)
        # The joint servos are PyBullet's motor constraints: each physics step they ask for the velocity
        # target plus positionGain x the position error per step, within the URDF effort. So positionGain
        # = dt / servo_time_constant (None: config/sim_bridge.yaml's). A fast loop (0.3, 3.3 ms: the default
        # until session 21) rings on the stiff sole contact at every load change (docs/walking.md "Session 21").
        if servo_time_constant is None:
            servo_time_constant = params_mod.defaults("sim_bridge")["servo_time_constant"]
        self.servo_time_constant = float(servo_time_constant)
        if not self.servo_time_constant >= self.dt:
            raise ValueError(f"servo_time_constant {servo_time_constant} s must be at least a physics step "
                             f"({self.dt} s): PyBullet's positionGain = dt / servo_time_constant is at most 1")
        self.position_gain = self.dt / self.servo_time_constant
        self.velocity_gain = velocity_gain
        self.enforce_velocity_limits = enforce_velocity_limits
        self.model = model or load_model()
        self.initial_posture = dict(STANDING_POSTURE if initial_posture is None else initial_posture)
        self.client = pb.connect(pb.DIRECT)
        self.obstacles: list[Box] = []
        self._obstacle_ids: dict[str, int] = {}
        self.pushes: list[Push] = []
        self.reset()

    # ------------------------------------------------------------------ setup
    def reset(self, obstacles: list[Box] | None = None) -> None:
        c = self.client
        pb.resetSimulation(physicsClientId=c)
        pb.setPhysicsEngineParameter(fixedTimeStep=self.dt, numSolverIterations=50,
                                     deterministicOverlappingPairs=1,
                                     contactBreakingThreshold=self.contact_breaking_threshold, physicsClientId=c)
        pb.setGravity(0, 0, -GRAVITY, physicsClientId=c)
        plane = pb.createCollisionShape(pb.GEOM_PLANE, physicsClientId=c)
        self.ground = pb.createMultiBody(0, plane, physicsClientId=c)
        pb.changeDynamics(self.ground, -1, lateralFriction=self.friction, physicsClientId=c)
        self.robot = pb.loadURDF(self.model.urdf_path, [0, 0, 1.0],
                                 flags=pb.URDF_USE_INERTIA_FROM_FILE, physicsClientId=c)
        self._index_joints()
        for link in range(-1, pb.getNumJoints(self.robot, physicsClientId=c)):
            pb.changeDynamics(self.robot, link, linearDamping=0.0, angularDamping=0.0, physicsClientId=c)
            # a separate call: PyBullet ignores lateralFriction given together with the damping
            # arguments (measured: the robot kept its default 0.5). Bullet multiplies the two
            # bodies' coefficients, so the robot gets 1 and the ground (and obstacles) `friction`.
            pb.changeDynamics(self.robot, link, lateralFriction=1.0, physicsClientId=c)
        # Real actuators cannot drive faster than their speed: each servo gets its URDF velocity limit
        # (which paper 1's stepping zone, eq. 8, is computed from) as the motor's maxVelocity. Not the
        # solver's maxJointVelocity: that clamps the joint's velocity after the solve without the
        # reaction on the rest of the body, so it does not conserve momentum (measured in a 40 J fall:
        # 70-100 N s gained in one tick, 1,000-1,500 J of kinetic energy against 192 J planned).
        self._motor_max_velocity = [float(v) for v in self.model.limits.velocity] \
            if self.enforce_velocity_limits else None
        q_joints = self.model.joint_vector(self.initial_posture)
        base_z = self.standing_base_height(q_joints)
        pb.resetBasePositionAndOrientation(self.robot, [0, 0, base_z], [0, 0, 0, 1], physicsClientId=c)
        for name, value in zip(self.model.joint_names, q_joints):
            pb.resetJointState(self.robot, self.joint_ids[name], value, 0.0, physicsClientId=c)
        # default velocity motors off: control goes through set_joint_targets
        self.targets = q_joints.copy()
        self.target_velocities = np.zeros(self.model.njoints)
        self._apply_targets()
        # settle onto the ground before time starts, so t=0 is a loaded stance
        for _ in range(int(self.physics_rate * 0.1)):
            pb.stepSimulation(physicsClientId=c)
        self.time = 0.0
        self.step_count = 0
        self.pushes = []
        self._prev_imu_velocity = None
        # readings of the current physics step (contacts, joints, base, IMU), asked for
        # several times a tick by the bridge, the metrics and retransmissions
        self._readings: dict = {}
        self.set_obstacles(self.obstacles if obstacles is None else obstacles)

    def set_state(self, q, v) -> None:
        """Put the robot in the pinocchio state (q, v) (the model's free-flyer convention: base position, quaternion
        xyzw, joints; base twist in the base frame, joint rates), the servo targets on it (positions and rates),
        time and pushes unchanged. For scripted states (``benchmarks/bench_capture_balance.py``): the readings of
        the step before are dropped, and the IMU's next acceleration is taken from this state on."""
        q = np.asarray(q, float).reshape(-1)
        v = np.asarray(v, float).reshape(-1)
        m = self.model
        if q.shape != (m.model.nq,) or v.shape != (m.model.nv,) or not (np.all(np.isfinite(q))
                                                                      and np.all(np.isfinite(v))):
            raise ValueError(f"a state needs finite q ({m.model.nq},) and v ({m.model.nv},)")
        c = self.client
        quat = q[3:7] / np.linalg.norm(q[3:7])
        R = quat_matrix(quat)
        # the waist's inertial origin is its URDF origin, so pybullet's base frame is pinocchio's root frame
        pb.resetBasePositionAndOrientation(self.robot, q[:3].tolist(), quat.tolist(), physicsClientId=c)
        pb.resetBaseVelocity(self.robot, (R @ v[:3]).tolist(), (R @ v[3:6]).tolist(), physicsClientId=c)
        for i, name in enumerate(m.joint_names):
            pb.resetJointState(self.robot, self.joint_ids[name], float(q[7 + i]), float(v[6 + i]),
                               physicsClientId=c)
        self.set_joint_targets(q[7:], v[6:])
        self._readings = {}
        self._prev_imu_velocity = None

    def standing_base_height(self, q_joints) -> float:
        """Base height that puts the lowest sole corner on the ground (pinocchio FK)."""
        q = self.model.configuration([0, 0, 0], [0, 0, 0, 1], q_joints)
        self.model.forward(q)
        lowest = min(self.model.sole_corners(s)[:, 2].min() for s in SIDES)
        return -lowest + 1e-4

    def _index_joints(self) -> None:
        c = self.client
        self.joint_ids: dict[str, int] = {}
        self.link_ids: dict[str, int] = {pb.getBodyInfo(self.robot, physicsClientId=c)[0].decode(): -1}
        for j in range(pb.getNumJoints(self.robot, physicsClientId=c)):
            info = pb.getJointInfo(self.robot, j, physicsClientId=c)
            self.link_ids[info[12].decode()] = j
            if info[2] == pb.JOINT_REVOLUTE:
                self.joint_ids[info[1].decode()] = j
        missing = set(self.model.joint_names) - set(self.joint_ids)
        if missing:
            raise RuntimeError(f"pybullet and pinocchio disagree on joints: {sorted(missing)}")
        self._jidx = [self.joint_ids[n] for n in self.model.joint_names]
        self._efforts = self.model.limits.effort.copy()
        self.foot_links = {s: self.link_ids[self.model.foot_link[s]] for s in SIDES}
        self.imu_link = self.link_ids[self.model.imu_frame]

    def set_obstacles(self, obstacles: list[Box]) -> None:
        c = self.client
        for bid in self._obstacle_ids.values():
            pb.removeBody(bid, physicsClientId=c)
        self._obstacle_ids = {}
        self.obstacles = list(obstacles)
        for box in self.obstacles:
            half = [s / 2 for s in box.size]
            shape = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=half, physicsClientId=c)
            orn = pb.getQuaternionFromEuler([0, 0, box.yaw])
            self._obstacle_ids[box.name] = pb.createMultiBody(0, shape, basePosition=box.position,
                                                              baseOrientation=orn, physicsClientId=c)
            pb.changeDynamics(self._obstacle_ids[box.name], -1, lateralFriction=self.friction, physicsClientId=c)

    # ---------------------------------------------------------------- control
    def set_joint_targets(self, positions, velocities=None) -> None:
        """Position targets (model joint order), clipped to the joint limits."""
        lim = self.model.limits
        self.targets = np.clip(np.asarray(positions, float), lim.lower, lim.upper)
        self.target_velocities = np.zeros(self.model.njoints) if velocities is None else \
            np.clip(np.asarray(velocities, float), -lim.velocity, lim.velocity)
        self._apply_targets()

    def _apply_targets(self) -> None:
        if self._motor_max_velocity is not None:
            # one call per joint: setJointMotorControlArray has no maxVelocity (and the multi-DoF
            # array call ignores it for revolute joints: measured); ~40 us more per tick
            ctl, pc, robot, client = pb.setJointMotorControl2, pb.POSITION_CONTROL, self.robot, self.client
            kp, kd = self.position_gain, self.velocity_gain
            for jid, q, v, f, vmax in zip(self._jidx, self.targets.tolist(), self.target_velocities.tolist(),
                                          self._efforts.tolist(), self._motor_max_velocity):
                ctl(robot, jid, pc, targetPosition=q, targetVelocity=v, force=f, positionGain=kp,
                    velocityGain=kd, maxVelocity=vmax, physicsClientId=client)
            return
        n = len(self._jidx)
        pb.setJointMotorControlArray(
            self.robot, self._jidx, pb.POSITION_CONTROL, targetPositions=self.targets.tolist(),
            targetVelocities=self.target_velocities.tolist(), forces=self._efforts.tolist(),
            positionGains=[self.position_gain] * n, velocityGains=[self.velocity_gain] * n,
            physicsClientId=self.client)

    def add_push(self, force, point=(0.0, 0.0, 0.0), duration: float = 0.1, link: str = "chest",
                 start: float | None = None) -> None:
        reason = validate_push(force, point, duration)
        if reason:
            raise ValueError(reason)
        if link not in self.link_ids:
            raise ValueError(f"unknown link {link!r}")
        self.pushes.append(Push(np.asarray(force, float), np.asarray(point, float), link,
                                self.time if start is None else start, float(duration)))

    def step_control(self) -> None:
        c = self.client
        substep_contacts = []
        for _ in range(self.substeps):
            for p in self.pushes:
                if p.active(self.time):
                    lid = self.link_ids[p.link]
                    pos, orn = self._link_frame(lid)
                    world_point = np.asarray(pos) + quat_matrix(orn) @ p.point
                    pb.applyExternalForce(self.robot, lid, p.force.tolist(), world_point.tolist(),
                                          pb.WORLD_FRAME, physicsClientId=c)
            pb.stepSimulation(physicsClientId=c)
            self._readings = {}
            self.step_count += 1
            self.time = self.step_count * self.dt
            substep_contacts.append(pb.getContactPoints(self.robot, self.ground, physicsClientId=c))
        self.pushes = [p for p in self.pushes if self.time < p.start + p.duration]
        self._readings["contacts"] = tick_contacts(substep_contacts)

    # ---------------------------------------------------------------- sensors
    def ground_contacts(self) -> tuple:
        """Robot-ground contact points of the last control tick, in PyBullet's ``getContactPoints`` layout.

        The points of every physics substep of the tick, their forces (normal, both lateral frictions)
        divided by the substep count: sums over them are the tick's mean contact force and moment, i.e.
        the contact impulse over the tick divided by its duration. The last substep alone is not a
        reading of the tick: the rubber-sole contact chatters at the physics rate (measured walking at
        1 km/h: the horizontal force alternates by a median 340 N from one 1 kHz substep to the next),
        so reading every second substep aliased into a steady bias (-170 N in x, the single-support CoP
        4-5 cm forward) although each substep's force obeys Newton with that substep's momentum rate
        (residual < 1 N; the tick mean: 0.02 N). Before the first tick (after ``reset``): the current
        step's points.
        """
        r = self._readings.get("contacts")
        if r is None:
            r = self._readings["contacts"] = pb.getContactPoints(self.robot, self.ground, physicsClientId=self.client)
        return r

    def _link_frame(self, lid: int):
        c = self.client
        if lid == -1:
            return pb.getBasePositionAndOrientation(self.robot, physicsClientId=c)
        s = pb.getLinkState(self.robot, lid, physicsClientId=c)
        return s[4], s[5]

    def joint_states(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(positions, velocities, applied torques) in model order; cached per physics step."""
        r = self._readings.get("joints")
        if r is None:
            st = pb.getJointStates(self.robot, self._jidx, physicsClientId=self.client)
            r = self._readings["joints"] = (np.array([s[0] for s in st]), np.array([s[1] for s in st]),
                                            np.array([s[3] for s in st]))
        return r

    def imu(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(orientation xyzw, angular velocity in IMU frame, proper acceleration in IMU frame).

        Computed once per control tick (the acceleration is a finite difference over
        the tick), so asking again, e.g. to retransmit a tick, gives the same reading.
        """
        if "imu" in self._readings:
            return self._readings["imu"]
        s = pb.getLinkState(self.robot, self.imu_link, computeLinkVelocity=1, physicsClientId=self.client)
        orn = np.array(s[5])
        R = quat_matrix(orn)
        v = np.array(s[6])
        w = np.array(s[7])
        ctrl_dt = 1.0 / self.control_rate
        acc = np.zeros(3) if self._prev_imu_velocity is None else (v - self._prev_imu_velocity) / ctrl_dt
        self._prev_imu_velocity = v
        proper = acc + np.array([0, 0, GRAVITY])
        reading = self._readings["imu"] = (orn, R.T @ w, R.T @ proper)
        return reading

    def foot_wrench(self, side: str) -> tuple[np.ndarray, np.ndarray]:
        """Ground reaction on a foot as (force, torque) at the ankle frame, foot-frame axes.

        Built from the tick's contact points (``ground_contacts``: the mean over the tick's physics
        substeps, as a sampled F/T sensor with an anti-alias filter reads; what it measures minus the
        foot's own inertia, which is small and would only add noise here). The moment is about the
        ankle's position at the end of the tick.
        """
        lid = self.foot_links[side]
        pos, orn = self._link_frame(lid)
        R = quat_matrix(orn)
        fx = fy = fz = tx = ty = tz = 0.0
        px, py, pz = pos
        for cp in self.ground_contacts():  # plain floats: numpy is slow on 3-vectors
            if cp[3] != lid:
                continue
            n, d1, d2 = cp[7], cp[11], cp[13]
            f0 = cp[9] * n[0] + cp[10] * d1[0] + cp[12] * d2[0]
            f1 = cp[9] * n[1] + cp[10] * d1[1] + cp[12] * d2[1]
            f2 = cp[9] * n[2] + cp[10] * d1[2] + cp[12] * d2[2]
            r0, r1, r2 = cp[6][0] - px, cp[6][1] - py, cp[6][2] - pz
            fx, fy, fz = fx + f0, fy + f1, fz + f2
            tx, ty, tz = tx + r1 * f2 - r2 * f1, ty + r2 * f0 - r0 * f2, tz + r0 * f1 - r1 * f0
        return R.T @ np.array([fx, fy, fz]), R.T @ np.array([tx, ty, tz])

    def ground_truth_cop(self):
        """CoP of all robot-ground contacts over the last tick (world; normal-force weighted over the tick's
        substeps, see ``ground_contacts``), or None when airborne."""
        f_tot = np.zeros(3)
        m = np.zeros(2)
        for cp in self.ground_contacts():
            fz = cp[9] * cp[7][2]
            f_tot[2] += fz
            m += fz * np.asarray(cp[6][:2])
        if f_tot[2] < 1.0:
            return None
        return np.array([m[0] / f_tot[2], m[1] / f_tot[2], 0.0])

    def non_foot_contact(self) -> bool:
        """True when any robot link but the feet touches the ground or an obstacle."""
        feet = set(self.foot_links.values())
        if any(cp[3] not in feet for cp in self.ground_contacts()):
            return True
        return any(pb.getContactPoints(self.robot, other, physicsClientId=self.client)
                   for other in self._obstacle_ids.values())

    def trunk_tilt(self) -> float:
        """Angle (rad) between the chest's z axis and the vertical."""
        _, orn = self._link_frame(self.link_ids[self.model.trunk_link])
        return math.acos(float(np.clip(quat_matrix(orn)[2, 2], -1.0, 1.0)))

    def base_state(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Ground truth: waist frame position, orientation xyzw, linear and angular velocity (world)."""
        r = self._readings.get("base")
        if r is None:  # cached per physics step: the bridge and the metrics both ask each tick
            pos, orn = pb.getBasePositionAndOrientation(self.robot, physicsClientId=self.client)
            lin, ang = pb.getBaseVelocity(self.robot, physicsClientId=self.client)
            # pybullet's base frame is the inertial frame; the waist's inertial origin is its URDF origin
            r = self._readings["base"] = (np.array(pos), np.array(orn), np.array(lin), np.array(ang))
        return r

    def pinocchio_state(self) -> tuple[np.ndarray, np.ndarray]:
        """Ground-truth (q, v) in the model's convention."""
        pos, orn, lin, ang = self.base_state()
        qj, vj, _ = self.joint_states()
        return self.model.configuration(pos, orn, qj), self.model.velocity(lin, ang, orn, vj)

    def pinocchio_configuration(self) -> np.ndarray:
        """Ground-truth q in the model's convention (no velocity: cheaper, for per-tick metrics); cached per
        physics step like the readings it is made of (the metrics and the feet ask each tick). A copy."""
        q = self._readings.get("q")
        if q is None:
            pos, orn, _, _ = self.base_state()
            q = self._readings["q"] = self.model.configuration(pos, orn, self.joint_states()[0])
        return q.copy()

    def robot_link_positions(self) -> np.ndarray:
        """URDF-frame positions of all robot links (n x 3), for fall geometry."""
        pts = [self._link_frame(-1)[0]]
        for lid in range(pb.getNumJoints(self.robot, physicsClientId=self.client)):
            pts.append(self._link_frame(lid)[0])
        return np.array(pts)

    def distance_to(self, name: str, max_distance: float = 10.0) -> float:
        """Closest distance (m) between the robot and an obstacle; 0 when touching."""
        bid = self._obstacle_ids[name]
        pts = pb.getClosestPoints(self.robot, bid, max_distance, physicsClientId=self.client)
        if not pts:
            return max_distance
        return max(0.0, min(p[8] for p in pts))

    def close(self) -> None:
        if self.client is not None and pb.isConnected(self.client):
            pb.disconnect(self.client)
        self.client = None
