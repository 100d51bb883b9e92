"""state_estimator's tick bookkeeping (its TickGate), in-process: newest complete tick only, bounded backlog,
retransmitted ticks answered again, a reset when time goes back."""
import pytest
import rclpy
from builtin_interfaces.msg import Time
from geometry_msgs.msg import WrenchStamped
from humfall_interfaces.msg import CentroidalState
from sensor_msgs.msg import Imu, JointState

from humfall_ros.nodes.common import stamp_key
from humfall_ros.control.tick_gate import MAX_PENDING_TICKS
from humfall_ros.nodes.state_estimator import StateEstimator
from humfall_ros.recording import cdr
from humfall_ros.sim.sensors import Sensors
from humfall_ros.sim.world import SimWorld


@pytest.fixture
def estimator(in_ros_domain):
    rclpy.init()
    node = StateEstimator()
    published = []
    decode = cdr.decoder(CentroidalState)
    node.pub.publish = lambda data: published.append(decode(data))  # what it would send (bytes), without a graph
    node.hot_loop.batching = True        # as when its hot loop spins it
    try:
        yield node, published
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


def tick_messages(world: SimWorld, sensors: Sensors, names: list[str]) -> dict:
    """One tick's sensor messages, as the bridge sends them."""
    r = sensors.read()
    ns = int(round(world.time * 1e9))
    stamp = Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
    js = JointState(name=names, position=r.joint_position.tolist(), velocity=r.joint_velocity.tolist())
    imu = Imu()
    o = imu.orientation
    o.x, o.y, o.z, o.w = r.imu_orientation.tolist()
    out = {"js": js, "imu": imu}
    for side in ("l", "r"):
        w = WrenchStamped()
        w.wrench.force.x, w.wrench.force.y, w.wrench.force.z = r.wrenches[side][0].tolist()
        out[side] = w
    for m in out.values():
        m.header.stamp = stamp
    return out


def simulated_ticks(n: int, names: list[str]) -> list[dict]:
    """The sensor messages of the first ``n`` ticks of a standing robot."""
    world = SimWorld(1000, 500)
    sensors = Sensors(world)
    ticks = []
    for _ in range(n):
        ticks.append(tick_messages(world, sensors, names))
        world.step_control()
    world.close()
    return ticks


def test_a_backlog_is_answered_with_the_newest_complete_tick_only(estimator):
    node, published = estimator
    ticks = simulated_ticks(3, node.model.joint_names)
    for t in ticks[:2]:  # two complete ticks queued up, and half of a third
        for kind, msg in t.items():
            node._add(kind, msg)
    node._add("js", ticks[2]["js"])
    node._on_batch()
    assert len(published) == 1
    assert stamp_key(published[0].header.stamp) == stamp_key(ticks[1]["js"].header.stamp)
    assert published[0].left_contact and published[0].right_contact and 0.6 < published[0].com.z < 0.9
    assert list(node.gate.pending) == [stamp_key(ticks[2]["js"].header.stamp)]  # the incomplete newer one waits


def test_ticks_that_never_complete_do_not_pile_up(estimator):
    node, published = estimator
    for i in range(MAX_PENDING_TICKS + 50):  # an IMU that went quiet: joint states only
        js = JointState(name=node.model.joint_names)
        js.header.stamp = Time(sec=0, nanosec=(i + 1) * 2_000_000)
        node._add("js", js)
        node._on_batch()
    assert not published and len(node.gate.pending) == MAX_PENDING_TICKS


def test_a_retransmitted_tick_is_answered_again_and_time_going_back_resets(estimator):
    node, _ = estimator
    stamps = []  # what went out, read at publish time (the node refills one message)
    decode = cdr.decoder(CentroidalState)
    node.pub.publish = lambda data: stamps.append((stamp_key(decode(data).header.stamp), decode(data).com.x))
    ticks = simulated_ticks(2, node.model.joint_names)
    for t in ticks:
        for kind, msg in t.items():
            node._add(kind, msg)
        node._on_batch()
    k0, k1 = (stamp_key(t["js"].header.stamp) for t in ticks)
    assert [s for s, _ in stamps] == [k0, k1]
    node._add("js", ticks[1]["js"])   # the bridge resends tick 2: the same answer again, no new estimate
    node._add("imu", ticks[1]["imu"])  # a repeated non-trigger input is ignored
    assert stamps[2] == stamps[1] and len(stamps) == 3
    for kind, msg in ticks[0].items():  # time went back (sim/reset): a new run from tick 1
        node._add(kind, msg)
    node._on_batch()
    assert node.gate.resets == 1 and len(stamps) == 4 and stamps[3][0] == k0
