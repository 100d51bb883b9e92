"""Does the 3-D robot stop after a touchdown that leaves its capture point d inside the front toe? (session 38)

Both open issues fail after a touchdown: issue 14's executed steps and paper 1's captures above 1.35x land with the
capture point near the front toe, and the robot does not stop. This maps where it does, from a scripted state:

* the left sole ``L`` ahead of the right, both flat (the shared IK: right sole hard, left sole, the CoM half way
  between the soles and 3 cm below standing, the trunk upright);
* the CoM moving along x (world) at the speed that puts the capture point xi = x + v / omega (paper 1 eq. 1-2)
  ``d`` inside the left toe, the base translating without rotation and the legs' joint velocities chosen so that
  both soles are still (``SimWorld.set_state``). Before session 39 the base's velocity was given along its own x
  axis (yawed 2-20 deg by the IK) and to PyBullet as if in the world frame: the soles started sliding at 0.08-0.58
  m/s (0.3-0.6 m steps, d 6 cm), and the map of sessions 38-39 measured that;
* then the ankle balance of ``control/standing.py`` (the safe-fall controller's capture balance, its gains from
  ``config/safe_fall_controller.yaml`` unless given) about the scripted posture, the CoM held over the feet's
  middle, for ``--duration`` s on ground truth.

A case stops when nothing but the feet touched and the CoM is slower than 0.1 m/s at the end.

The depth ``d`` is along x, to the front toe's line. What decides is the capture point's margin inside the two soles'
hull (``xi_margin_m``, reported per case): the soles are 0.18 m apart sideways, so the hull's side towards the rear
foot runs diagonally from the rear toe to the front sole's inner toe corner, and a capture point d inside the toe
line is much less deep inside the hull (0.3 m step, d = 6 cm: 2.7 cm), the more so the longer the step.

    python benchmarks/bench_capture_balance.py [--steps 0.3,0.45,0.6] [--depths 0.15,0.1,0.06,0.03,0]
                                               [--kp 0.3 --kd 0.1 --max-offset 0.12] [--duration 2]
                                               [--hip-flex 0.3 [--hip-rise 0.15 --hip-hold 0.6 --hip-release 1]]

``--hip-flex``: the hip strategy on top (``control.standing.hip_flexion_profile``; both hips flexed from the
touchdown; the safe-fall controller's ``balance_hip_*``).

Prints one JSON object: per case the CoM speed at the start, whether it stopped, and per step length the
smallest depth that stopped.
"""
from __future__ import annotations

import argparse
import json
import math
import pathlib
import sys

import numpy as np
import pinocchio as pin

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from humfall_ros import params  # noqa: E402
from humfall_ros.control.standing import StandingBalance, hip_flexion_profile  # noqa: E402
from humfall_ros.dynamics.pendulum import GRAVITY  # noqa: E402
from humfall_ros.model.humanoid import point_in_polygon_margin, support_polygon  # noqa: E402
from humfall_ros.model.ik import ComTask, FrameTask, OrientationTask, PostureTask, WholeBodyIK  # noqa: E402
from humfall_ros.sim.world import SimWorld  # noqa: E402

STOPPED_SPEED = 0.1   # m/s: the CoM slower than this at the end


def scripted_state(world: SimWorld, step: float, depth: float, com_drop: float = 0.03):
    """(q, qd, v_com, toe_x, com_x, ik converged, the soles' middle, the capture point's margin inside the soles'
    hull [m]) of the scripted touchdown state (module docstring)."""
    m = world.model
    q0, _ = world.pinocchio_state()
    pin.framesForwardKinematics(m.model, m.data, q0)
    right = m.data.oMf[m.frame_ids[m.sole_frame["r"]]].copy()
    left0 = m.data.oMf[m.frame_ids[m.sole_frame["l"]]]
    left = pin.SE3(left0.rotation, left0.translation + np.array([step, 0.0, 0.0]))
    z = pin.centerOfMass(m.model, m.data, q0)[2]
    com_target = np.array([right.translation[0] + 0.5 * step, 0.5 * (right.translation[1] + left.translation[1]),
                           z - com_drop])
    tasks = [FrameTask(m.sole_frame["r"], right, hard=True), FrameTask(m.sole_frame["l"], left, weight=1000.0),
             ComTask(com_target, weight=100.0), OrientationTask(m.imu_frame, np.eye(3), weight=10.0),
             PostureTask(q0[7:].copy())]
    res = WholeBodyIK(m).solve_to_convergence(q0, tasks, dt=0.05, max_iterations=400, tolerance=1e-3)
    q = res.q
    pin.framesForwardKinematics(m.model, m.data, q)
    com = pin.centerOfMass(m.model, m.data, q)
    toe_x = float(m.data.oMf[m.frame_ids[m.sole_frame["l"]]].translation[0] + 0.5 * m.foot_length)
    v_com = math.sqrt(GRAVITY / com[2]) * (toe_x - depth - com[0])
    hull = support_polygon(np.vstack([m.sole_corners(sd)[:, :2] for sd in ("l", "r")]))
    xi_margin = point_in_polygon_margin([toe_x - depth, com[1]], hull)
    # the base translating (no rotation), each leg's joints keeping its sole still; the base's velocity (pinocchio:
    # in the base frame, which the IK leaves yawed and pitched) chosen so the CoM moves along world x only
    pin.computeJointJacobians(m.model, m.data, q)
    pin.updateFramePlacements(m.model, m.data)
    soles = [(pin.getFrameJacobian(m.model, m.data, m.frame_ids[m.sole_frame[side]], pin.LOCAL_WORLD_ALIGNED),
              [6 + i for i in m.leg_joint_indices(side)]) for side in ("l", "r")]
    basis = []
    for k in range(3):
        qd = np.zeros(m.model.nv)
        qd[k] = 1.0
        for J, cols in soles:
            qd[cols] = np.linalg.solve(J[:, cols], -J[:, :6] @ qd[:6])
        pin.centerOfMass(m.model, m.data, q, qd)
        basis.append((qd, m.data.vcom[0].copy()))
    u = np.linalg.solve(np.column_stack([b[1] for b in basis]), [v_com, 0.0, 0.0])
    qd = sum(uk * b[0] for uk, b in zip(u, basis))
    return (q, qd, v_com, toe_x, float(com[0]), bool(res.converged), 0.5 * (right.translation + left.translation),
            float(xi_margin))


def run_case(step: float, depth: float, kp: float, kd: float, max_offset: float, duration: float,
             hip: tuple = (0.0, 0.15, 0.6, 1.0)) -> dict:
    world = SimWorld()
    try:
        m = world.model
        q, qd, v_com, toe_x, com_x, ik_ok, feet_mid, xi_margin = scripted_state(world, step, depth)
        world.set_state(q, qd)
        balance = StandingBalance(m, dict(zip(m.joint_names, q[7:])), kp=kp, kd=kd, max_offset=max_offset)
        balance.reference = np.zeros(2)   # the CoM over the feet's middle
        nominal = balance.nominal.copy()
        hips = [m.joint_index(f"{sd}_hip_pitch") for sd in ("l", "r")]
        touched = False
        for k in range(int(round(duration * world.control_rate))):
            balance.nominal = nominal.copy()
            balance.nominal[hips] -= hip_flexion_profile(k / world.control_rate, *hip)
            qq, vv = world.pinocchio_state()
            pin.centerOfMass(m.model, m.data, qq, vv)
            world.set_joint_targets(balance.command(m.data.com[0], m.data.vcom[0], feet_center=feet_mid))
            world.step_control()
            touched |= world.non_foot_contact()
        qq, vv = world.pinocchio_state()
        pin.centerOfMass(m.model, m.data, qq, vv)
        speed = float(np.linalg.norm(m.data.vcom[0]))
        return {"step_m": step, "depth_m": depth, "xi_margin_m": round(xi_margin, 4),
                "ik_converged": ik_ok, "com_x_m": round(com_x, 3),
                "toe_x_m": round(toe_x, 3), "com_speed_start_mps": round(v_com, 3),
                "touched_besides_feet": bool(touched), "com_speed_end_mps": round(speed, 3),
                "stopped": bool(not touched and speed < STOPPED_SPEED)}
    finally:
        world.close()


def main() -> int:
    d = params.defaults("safe_fall_controller")
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--steps", default="0.3,0.45,0.6", help="step lengths L (m), comma-separated")
    ap.add_argument("--depths", default="0.15,0.1,0.06,0.03,0", help="capture point inside the toe (m)")
    ap.add_argument("--kp", type=float, default=d["balance_kp"])
    ap.add_argument("--kd", type=float, default=d["balance_kd"])
    ap.add_argument("--max-offset", type=float, default=d["balance_max_offset"])
    ap.add_argument("--duration", type=float, default=2.0)
    ap.add_argument("--hip-flex", type=float, default=d["balance_hip_flex_rad"], help="hip strategy [rad] (0: off)")
    ap.add_argument("--hip-rise", type=float, default=d["balance_hip_rise_s"])
    ap.add_argument("--hip-hold", type=float, default=d["balance_hip_hold_s"])
    ap.add_argument("--hip-release", type=float, default=d["balance_hip_release_s"])
    a = ap.parse_args()
    hip = (a.hip_flex, a.hip_rise, a.hip_hold, a.hip_release)
    steps = [float(x) for x in a.steps.split(",")]
    depths = sorted((float(x) for x in a.depths.split(",")), reverse=True)
    cases = [run_case(s, dep, a.kp, a.kd, a.max_offset, a.duration, hip) for s in steps for dep in depths]
    smallest, smallest_margin = {}, {}
    for s in steps:
        ok = [c for c in cases if c["step_m"] == s and c["stopped"]]
        smallest[str(s)] = min(c["depth_m"] for c in ok) if ok else None
        smallest_margin[str(s)] = min(c["xi_margin_m"] for c in ok) if ok else None
    print(json.dumps({"gains": {"kp": a.kp, "kd": a.kd, "max_offset": a.max_offset},
                      "hip_strategy": dict(zip(("flex_rad", "rise_s", "hold_s", "release_s"), hip)),
                      "duration_s": a.duration,
                      "cases": cases, "smallest_depth_that_stopped_m": smallest,
                      "smallest_xi_margin_that_stopped_m": smallest_margin}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
