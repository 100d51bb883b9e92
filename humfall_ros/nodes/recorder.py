"""recorder: records every topic on the ROS graph into an MCAP bag.

Topics
    subscribes to every topic that has a publisher, raw (CDR bytes, never
    deserialised), including topics that appear later (the graph is polled every
    ``discovery_period`` s). Nothing is published.

Files (in ``output_dir``, default ``runs/<YYYYmmdd-HHMMSS>-<scenario>``)
    ``bag.mcap``               ros2msg schemas + cdr channels (see humfall_ros.recording)
    ``recording_stats.json``   per-topic type/count/first/last time; rewritten every
                               flush and finally on close (``finalized: true``)

QoS
    Each subscription adapts to the publishers seen when the topic is first
    recorded: reliable unless a publisher is best-effort (a reliable reader
    cannot match a best-effort writer); transient-local when every publisher is
    transient-local, so a latched message sent before we subscribed (``fall_event``)
    is still delivered; a deep history (``queue_depth``) because in lockstep runs
    every message matters and a burst must queue rather than drop. Topics that only
    have subscribers so far are left until a publisher shows up, so their QoS is
    decided from real publishers.

Times (decision; also stored in the bag's ``humfall_recorder`` metadata record)
    ``log_time`` is the receive time on the recorder's clock. With
    ``clock: sim`` (default) that is the sim time of the last ``/clock`` message
    the recorder itself took (within a few ticks of the message's own stamp; the
    node clock is only updated between drains and strayed by tens of ms): a bag's time axis
    is then the simulation's, the same as the message header stamps, and rates in
    ``humfall bag info`` are per simulated second whether the run was lockstep or
    free-run. Messages received before the first ``/clock`` message get log time 0,
    which is what they are in sim terms (before the simulation started); this is
    also what ``ros2 bag record --use-sim-time`` does. ``clock: wall`` stamps with
    the system clock, for graphs without a simulator.
    ``publish_time`` is the publisher's send time as the middleware reports it
    (``source_timestamp``, system clock), as rosbag2 on Jazzy does; it keeps
    wall-clock latency visible even in sim-time bags.

Durability
    A steady-clock timer (so it runs even if sim time stalls) flushes the open chunk
    every ``flush_period`` s: a ``kill -9`` loses at most that much, and the file
    stays readable with ``humfall_ros.recording.reader`` (streaming) or after
    ``recover``. SIGINT/SIGTERM close the file with summary and footer.
    Nothing that arrives can stop the node: an unknown type or a schema that
    cannot be built skips that topic (logged, listed in the stats); a failed write
    is counted and logged.
"""
from __future__ import annotations

import datetime
import importlib
import pathlib
import re
import time
from typing import Any

from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from humfall_ros.nodes.common import HotLoop, Params, run_node
from humfall_ros.recording.cdr import leading_stamp_ns
from humfall_ros.recording.schema import SchemaError, split_type_name
from humfall_ros.recording.writer import BAG_FILE, STATS_FILE, BagWriter

NODE_NAME = "recorder"


def default_output_dir(scenario: str, now: datetime.datetime | None = None) -> pathlib.Path:
    """``runs/<YYYYmmdd-HHMMSS>-<scenario>`` relative to the working directory."""
    stamp = (now or datetime.datetime.now()).strftime("%Y%m%d-%H%M%S")
    safe = re.sub(r"[^A-Za-z0-9_.-]+", "_", scenario) or "run"
    return pathlib.Path("runs") / f"{stamp}-{safe}"


def load_message_class(type_name: str) -> type:
    """The generated Python class of ``pkg/msg/Type`` (raw subscriptions still need it)."""
    pkg, name = split_type_name(type_name)
    return getattr(importlib.import_module(f"{pkg}.msg"), name)


def _policy_name(value: Any) -> str:
    return getattr(value, "name", str(value)).lower()


def subscription_qos(publisher_qos: list[QoSProfile], depth: int) -> QoSProfile:
    """The QoS that matches every publisher and loses nothing (see module docstring)."""
    best_effort = any(q.reliability == ReliabilityPolicy.BEST_EFFORT for q in publisher_qos)
    latched = bool(publisher_qos) and all(
        q.durability == DurabilityPolicy.TRANSIENT_LOCAL for q in publisher_qos)
    return QoSProfile(
        depth=depth, history=HistoryPolicy.KEEP_LAST,
        reliability=ReliabilityPolicy.BEST_EFFORT if best_effort else ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)


def qos_dict(q: QoSProfile) -> dict[str, Any]:
    return {"history": _policy_name(q.history), "depth": q.depth,
            "reliability": _policy_name(q.reliability), "durability": _policy_name(q.durability),
            "liveliness": _policy_name(q.liveliness)}


class Recorder(Node):
    def __init__(self):
        super().__init__(NODE_NAME)
        p = Params(self)
        self.scenario = p.declare("scenario")
        out = p.declare("output_dir")
        self.clock_mode = p.declare("clock")
        self.flush_period = p.declare("flush_period")
        self.discovery_period = p.declare("discovery_period")
        self.depth = p.declare("queue_depth")
        self.drain_max = p.declare("drain_max")
        self.batch_period = p.declare("batch_period")
        exclude = p.declare("exclude_regex")
        clocks = p.declarations["clock"].choices     # config/recorder.yaml's one_of
        if self.clock_mode not in clocks:
            raise ValueError(f"recorder: clock must be one of {', '.join(clocks)}, not {self.clock_mode!r}")
        self._exclude = re.compile(exclude) if exclude else None
        # use_sim_time follows `clock`, so the node clock is the log-time clock.
        self.set_parameters([Parameter("use_sim_time", Parameter.Type.BOOL, self.clock_mode == "sim")])

        self.output_dir = pathlib.Path(out) if out else default_output_dir(self.scenario)
        self.bag_path = self.output_dir / BAG_FILE
        self.writer = BagWriter(self.bag_path, metadata={
            "log_time_clock": self.clock_mode, "publish_time_clock": "wall (publisher source_timestamp)",
            "scenario": self.scenario, "started": datetime.datetime.now().isoformat(timespec="seconds"),
        })
        self._subs: dict[str, Any] = {}
        self._clock_cid: int | None = None      # channel of /clock, whose messages set the log time
        self._sim_now_ns: int | None = None
        self._failed: dict[str, str] = {}       # topic -> reason (retried never; see _discover)
        self._warned_types: set[str] = set()
        self._last_error_log = 0.0
        self._closed = False
        # the recorded topics are waited on alone (HotLoop): rclpy's executor rebuilt a wait set of
        # every entity of the node per wait; timers, discovery and parameters are served every 50 ms
        self.hot_loop = HotLoop(self, pace=self.batch_period)
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        # Both timers on the steady clock: they must run even when sim time stands still.
        self.create_timer(self.flush_period, self._flush, clock=steady)
        self.create_timer(self.discovery_period, self._discover, clock=steady)
        self.get_logger().info(f"recording to {self.bag_path} (log time: {self.clock_mode} clock)")
        self._discover()

    # -- discovery ------------------------------------------------------------
    def _discover(self) -> None:
        try:
            topics = self.get_topic_names_and_types()
        except Exception as exc:  # noqa: BLE001 - e.g. during shutdown
            self._error(f"graph query failed: {exc}")
            return
        for topic, types in topics:
            if topic in self._subs or topic in self._failed:
                continue
            if self._exclude is not None and self._exclude.search(topic):
                continue
            try:
                pubs = self.get_publishers_info_by_topic(topic)
            except Exception as exc:  # noqa: BLE001
                self._error(f"{topic}: publisher query failed: {exc}")
                continue
            if not pubs:
                continue  # only subscribers so far: decide QoS when a publisher exists
            self._subscribe(topic, types, [pi.qos_profile for pi in pubs])

    def _subscribe(self, topic: str, types: list[str], pub_qos: list[QoSProfile]) -> None:
        type_name = types[0]
        if len(types) > 1:
            self.get_logger().warning(f"{topic} has several types {types}; recording {type_name}")
        try:
            cls = load_message_class(type_name)
        except Exception as exc:  # noqa: BLE001 - unknown package/type in this environment
            self._skip(topic, f"type {type_name} not importable: {exc}")
            return
        qos = subscription_qos(pub_qos, self.depth)
        try:
            cid = self.writer.add_topic(topic, type_name, [qos_dict(q) for q in pub_qos])
        except SchemaError as exc:
            self._skip(topic, f"no message definition for {type_name}: {exc}")
            return
        self.writer.channels[cid].qos = qos_dict(qos)

        if topic == "/clock":
            self._clock_cid = cid

        def on_message(data: bytes, info: dict, cid: int = cid, topic: str = topic) -> None:
            self._record(cid, data, info)
            self._drain(topic, cid)

        try:
            self._subs[topic] = self.hot_loop.subscribe(cls, topic, on_message, qos, raw=True, with_info=True)
        except Exception as exc:  # noqa: BLE001 - bad topic name, rmw error
            self._skip(topic, f"cannot subscribe: {exc}")
            return
        self.get_logger().info(
            f"recording {topic} [{type_name}] {_policy_name(qos.reliability)}/{_policy_name(qos.durability)}")

    def _skip(self, topic: str, reason: str) -> None:
        self._failed[topic] = reason
        self.writer.skipped[topic] = reason
        self.get_logger().error(f"not recording {topic}: {reason}")

    # -- recording --------------------------------------------------------------
    def _record(self, cid: int, data: bytes, info: dict) -> None:
        if self._closed:
            return
        try:
            if self.clock_mode == "sim":
                if cid == self._clock_cid:
                    now = leading_stamp_ns(data)   # rosgraph_msgs/Clock
                    if now is not None:
                        self._sim_now_ns = now
                # the last /clock this recorder took, not the node clock: that one is only
                # updated between drains and could run ahead of or behind the messages
                log_time = self._sim_now_ns if self._sim_now_ns is not None else self.get_clock().now().nanoseconds
            else:
                log_time = int(info.get("received_timestamp") or time.time_ns())
            publish_time = int(info.get("source_timestamp") or log_time)
            self.writer.write(cid, bytes(data), log_time, publish_time)
        except Exception as exc:  # noqa: BLE001 - never lose the node (and the bag) over one message
            self.writer.write_errors += 1
            self._error(f"write failed on channel {cid}: {exc}")

    def _drain(self, topic: str, cid: int) -> None:
        """Take what else is queued on this subscription now.

        The rclpy executor takes one message per subscription per wait, and rebuilding
        the wait set costs far more than recording a message (~0.3 ms vs ~0.03 ms
        here). Draining the reader queue in the callback makes a backlog cost one wait,
        so the recorder catches up instead of falling further behind. Uses the
        subscription handle's take_message, as the executor itself does.
        """
        sub = self._subs.get(topic)
        if sub is None or self.drain_max <= 0:
            return
        try:
            for _ in range(self.drain_max):
                with sub.handle:
                    taken = sub.handle.take_message(sub.msg_type, True)
                if taken is None:
                    return
                self._record(cid, taken[0], taken[1])
        except Exception as exc:  # noqa: BLE001 - rclpy internals changed: fall back to one per wait
            self.drain_max = 0
            self._error(f"draining disabled: {exc}")

    def _flush(self) -> None:
        if self._closed:
            return
        try:
            self.writer.flush()
            self.writer.write_stats(extra=self._stats_extra())
        except Exception as exc:  # noqa: BLE001 - disk full etc.: keep recording into memory
            self.writer.write_errors += 1
            self._error(f"flush failed: {exc}")

    def _stats_extra(self) -> dict[str, Any]:
        return {"log_time_clock": self.clock_mode, "scenario": self.scenario}

    def _error(self, text: str) -> None:
        # Throttled: a flood of errors must not become a flood of /rosout messages we record.
        now = time.monotonic()
        if now - self._last_error_log > 1.0:
            self._last_error_log = now
            self.get_logger().error(text)

    def close(self) -> None:
        """Finalize the bag and the stats file (run_node calls this on shutdown)."""
        if self._closed:
            return
        self._closed = True
        try:
            self.writer.close()
        finally:
            p = self.writer.write_stats(self.output_dir / STATS_FILE, extra=self._stats_extra())
            total = sum(s.count for s in self.writer.channels.values())
            print(f"[recorder] closed {self.bag_path}: {total} messages on "
                  f"{len(self.writer.channels)} topics; stats in {p}", flush=True)


def main(args=None) -> int:
    # use_sim_time is set by the node from its `clock` parameter, not forced by run_node.
    return run_node(Recorder, args=args, use_sim_time=False)


if __name__ == "__main__":
    raise SystemExit(main())
