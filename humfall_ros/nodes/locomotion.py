"""locomotion: the balance controller. Standing now (walking comes with its issue).

Answers every centroidal_state tick with a joint command stamped like it, so
the bridge can run in lockstep.
"""
from __future__ import annotations

from humfall_interfaces.msg import CentroidalState
from rclpy.node import Node
from sensor_msgs.msg import JointState

from humfall_ros.control.standing import StandingBalance
from humfall_ros.model.humanoid import load_model
from humfall_ros.nodes.common import NO_PUB_EVENTS, QOS_RELIABLE, HotLoop, Params, run_node, stamp_key
from humfall_ros.sim.world import STANDING_POSTURE



class Locomotion(Node):
    def __init__(self):
        super().__init__("locomotion")
        P = Params(self)
        kp = P.declare("ankle_kp")
        kd = P.declare("ankle_kd")
        max_off = P.declare("ankle_max_offset")
        self.model = load_model()
        self.balance = StandingBalance(self.model, STANDING_POSTURE, kp, kd, max_off)
        self.pub = self.create_publisher(JointState, "joint_command/locomotion", QOS_RELIABLE,
                                         event_callbacks=NO_PUB_EVENTS)
        self.hot_loop = HotLoop(self)
        self.hot_loop.subscribe(CentroidalState, "centroidal_state", self._on_state)
        self.last_key = -1
        self.last_cmd: JointState | None = None

    def _on_state(self, msg: CentroidalState) -> None:
        k = stamp_key(msg.header.stamp)
        if k == self.last_key:
            if self.last_cmd is not None:
                self.pub.publish(self.last_cmd)  # retransmitted tick
            return
        if k < self.last_key:  # time went back (sim/reset): hold the new stance
            self.get_logger().info(f"sim time went back to {k * 1e-9:.3f} s: balance reset")
            self.balance.reset()
        self.last_key = k
        try:
            q = self.balance.command([msg.com.x, msg.com.y, msg.com.z],
                                     [msg.com_velocity.x, msg.com_velocity.y, msg.com_velocity.z],
                                     [[p.x, p.y] for p in msg.support_polygon],
                                     [msg.feet_center.x, msg.feet_center.y])
            cmd = JointState(name=self.model.joint_names, position=q.tolist())
        except Exception as e:  # noqa: BLE001 - never die on a bad state; release this tick
            self.get_logger().error(f"standing command failed: {e}", throttle_duration_sec=1.0)
            cmd = JointState()
        cmd.header.stamp = msg.header.stamp
        self.pub.publish(cmd)
        self.last_cmd = cmd


def main(args=None) -> int:
    return run_node(Locomotion, args)


if __name__ == "__main__":
    raise SystemExit(main())
