"""Shared plumbing for the rclpy nodes: parameters from config/*.yaml with
descriptors, QoS profiles, and a main() wrapper with try/finally shutdown.

Parameter values live in ``config/<node>.yaml`` (ROS 2 params-file format:
``<node>: {ros__parameters: {...}}``); nodes declare each one here with a
description and, for numbers, a range. A ``--params-file`` given on the command
line overrides the file's values as usual.
"""
from __future__ import annotations

import contextlib
import os
import threading
import sys
import time
from types import SimpleNamespace
from typing import Any, Callable, NoReturn

from humfall_ros import params as params_mod
from humfall_ros.recording import cdr

import rclpy
import rclpy.executors
from rclpy.duration import Duration
from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from builtin_interfaces.msg import Time
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult

# Lockstep data: every message matters, keep a few in case of a burst.
QOS_RELIABLE = QoSProfile(depth=20, reliability=ReliabilityPolicy.RELIABLE,
                          durability=DurabilityPolicy.VOLATILE, history=HistoryPolicy.KEEP_LAST)
# Writers of per-tick data. A reliable KEEP_LAST writer overwrites a sample its readers have not acknowledged once
# its history is full, so the depth is the window (in ticks) in which a reader that stalled (the recorder, starved of
# CPU for tens of ms while the simulation runs at several times real time) can still get a lost sample re-sent.
# Depth 20 lost ticks from bags under load (session 28: 29 of 600 in a CI run); the lockstep readers are unaffected.
QOS_TICK_WRITER = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.VOLATILE, history=HistoryPolicy.KEEP_LAST)
# Events (fall_event, decisions, plans): late joiners get the last one.
QOS_LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL, history=HistoryPolicy.KEEP_LAST)
# /clock's writer is a per-tick writer too (rclpy's time source subscribes with its own QoS).
QOS_CLOCK = QOS_TICK_WRITER


def load_node_defaults(node_name: str) -> dict[str, Any]:
    """Default values of a node's parameters (``config/<node>.yaml``; see humfall_ros.params)."""
    return params_mod.defaults(node_name)


_ROS_TYPES = {"bool": Parameter.Type.BOOL, "int": Parameter.Type.INTEGER, "double": Parameter.Type.DOUBLE,
              "string": Parameter.Type.STRING, "bool_array": Parameter.Type.BOOL_ARRAY,
              "int_array": Parameter.Type.INTEGER_ARRAY, "double_array": Parameter.Type.DOUBLE_ARRAY,
              "string_array": Parameter.Type.STRING_ARRAY}


class Params:
    """Declares a node's parameters from their one declaration in ``config/<node>.yaml``.

    ``p.declare("physics_rate")`` declares it with the file's type, default,
    description and range and returns its value (a ``-p`` or ``--params-file``
    override wins, as usual); ``p.declare_all()`` declares every parameter of the
    file; ``p.values`` keeps what was declared; ``p.overridden`` names the ones
    set explicitly on the command line or by a params file.
    """

    def __init__(self, node: Node, config_name: str | None = None,
                 declarations: dict[str, params_mod.Declaration] | None = None):
        self.node = node
        self.config_name = config_name or node.get_name()
        # a node outside the package (e.g. a test-only controller) may bring its own declarations
        self.declarations = declarations if declarations is not None else params_mod.declarations(self.config_name)
        self.values: dict[str, Any] = {}
        overrides = getattr(node, "_parameter_overrides", None)  # rclpy keeps -p / params-file values here
        self._explicit = set(overrides) if isinstance(overrides, dict) else set()
        self.overridden: set[str] = set()
        # rclpy enforces a descriptor's number ranges but not a string's choices (additional_constraints is text):
        # a set that names a value outside the declared one_of is refused here, with the choices in the reason
        node.add_on_set_parameters_callback(self._check_choices)

    def _check_choices(self, parameters) -> SetParametersResult:
        for p in parameters:
            d = self.declarations.get(p.name)
            if d is not None and d.choices is not None and p.value not in d.choices:
                return SetParametersResult(successful=False,
                                           reason=f"{p.name}={p.value!r} is not one of {', '.join(d.choices)}")
        return SetParametersResult(successful=True)

    def declare(self, name: str) -> Any:
        d = self.declarations.get(name)
        if d is None:
            raise KeyError(f"parameter {name!r} of {self.node.get_name()} is not declared in "
                           f"config/{self.config_name}.yaml")
        desc = ParameterDescriptor(description=d.description, read_only=d.read_only, type=_ROS_TYPES[d.type])
        if d.bounds is not None:
            lo, hi = d.bounds
            if d.type.startswith("int"):
                desc.integer_range = [IntegerRange(from_value=int(lo), to_value=int(hi), step=0)]
            else:
                desc.floating_point_range = [FloatingPointRange(from_value=float(lo), to_value=float(hi), step=0.0)]
        if d.choices is not None:
            desc.additional_constraints = f"one of: {', '.join(d.choices)}"
        value = self.node.declare_parameter(name, d.default, desc).value
        if isinstance(value, (list, tuple)) or hasattr(value, "tolist"):
            value = list(value)
        self.values[name] = value
        if name in self._explicit:
            self.overridden.add(name)
        return value

    def declare_all(self) -> dict[str, Any]:
        for name in self.declarations:
            if name not in self.values:
                self.declare(name)
        return dict(self.values)


def stamp_key(stamp) -> int:
    """A header stamp as integer nanoseconds: the tick identity in lockstep."""
    return stamp.sec * 1_000_000_000 + stamp.nanosec


def ros_stamp(stamp) -> Time:
    """A stamp (a message's, or a decoded one's from ``HotLoop.subscribe(decoded=True)``) as a new
    ``builtin_interfaces/Time`` to put into an outgoing message."""
    return Time(sec=int(stamp.sec), nanosec=int(stamp.nanosec))


def shutting_down() -> bool:
    """True once SIGINT/SIGTERM has shut the context down.

    A take or publish that was under way at that moment raises a plain RuntimeError
    or RCLError (not ExternalShutdownException): that is a clean stop, not a crash.
    """
    return not rclpy.ok()


@contextlib.contextmanager
def profiled(node: Node):
    """With ``HUMFALL_PROFILE_DIR`` set (a developer's switch, off by default), the node's spin runs under
    cProfile and its statistics go to ``DIR/<node name>.prof`` when it stops (``python -m pstats`` reads them).

    The clock is the spinning thread's CPU time, not the wall: on a loaded machine a publish wakes its
    readers, which preempt the publisher, and a wall-clock profile books their run time to ``publish``."""
    out = os.environ.get("HUMFALL_PROFILE_DIR")
    if not out:
        yield
        return
    import cProfile

    prof = cProfile.Profile(time.thread_time)
    prof.enable()
    try:
        yield
    finally:
        prof.disable()
        os.makedirs(out, exist_ok=True)
        prof.dump_stats(os.path.join(out, f"{node.get_name()}.prof"))


def run_node(factory: Callable[[], Node], args=None, use_sim_time: bool = True,
             executor_factory: Callable[[], Any] | None = None) -> int:
    """Standard main(): init, spin, clean shutdown on SIGINT/SIGTERM, try/finally."""
    os.environ.setdefault("ROS_LOG_DIR", os.path.join(os.path.expanduser("~"), ".ros", "log"))
    rclpy.init(args=args if args is not None else sys.argv)
    node = None
    try:
        node = factory()
        if use_sim_time and not node.has_parameter("use_sim_time"):
            node.declare_parameter("use_sim_time", True)
        if use_sim_time:
            node.set_parameters([Parameter("use_sim_time", Parameter.Type.BOOL, True)])
        executor = executor_factory() if executor_factory else rclpy.executors.SingleThreadedExecutor()
        executor.add_node(node)
        with profiled(node):
            hot = getattr(node, "hot_loop", None)
            if isinstance(hot, HotLoop):
                hot.spin(executor)
            else:
                # not executor.spin(): a multi-threaded executor blocked in its wait was never woken by the
                # shutdown a signal makes (measured: the planner ignored SIGTERM and SIGINT once idle)
                while rclpy.ok():
                    executor.spin_once(timeout_sec=0.1)
    except (KeyboardInterrupt, rclpy.executors.ExternalShutdownException):
        pass
    except Exception:  # noqa: BLE001
        if not shutting_down():
            raise
    finally:
        if node is not None:
            close_node(node)
        rclpy.try_shutdown()
    return _exit_past_worker_threads(0)


def wait_acknowledged(node: Node, timeout_s: float) -> list[str]:
    """Wait (at most ``timeout_s`` in all) until every reliable reader has acknowledged every sample the node's
    publishers sent; the topics still unacknowledged. A node that ends a run on its own (the bridge) calls it before
    it exits: a writer that goes away takes the samples a stalled reader (the recorder) has not yet had with it."""
    end = time.monotonic() + timeout_s
    late = []
    for pub in list(node.publishers):
        left = end - time.monotonic()
        try:
            acked = left > 0 and pub.wait_for_all_acked(Duration(seconds=left))
        except Exception:  # noqa: BLE001 - a publisher destroyed or a context shut down meanwhile
            acked = False
        if not acked:
            late.append(pub.topic_name)
    return late


def close_node(node: Node) -> None:
    """The node's own ``close()`` (files, worlds), then destroy it."""
    close = getattr(node, "close", None)
    if callable(close):
        close()
    node.destroy_node()


def _exit_past_worker_threads(code: int) -> int:
    """Return ``code``, or end the process now if worker threads are still busy.

    A thread inside a long C++ call (an IPOPT solve, a casadi structure build) cannot be
    interrupted; letting the interpreter finalise around it aborts the process ("pure
    virtual method called", exit 134) or keeps it alive past SIGTERM. The node has
    closed its files and shut rclpy down by now, so leaving at once loses nothing.
    """
    busy = [t for t in threading.enumerate() if t is not threading.main_thread() and t.is_alive()
            and not t.name.startswith(("pydevd", "Dummy"))]
    if busy:
        leave_now(code)
    return code


def leave_now(code: int) -> NoReturn:
    """End the process with ``code`` without the interpreter's finalisation (streams flushed first).

    For a node whose rclpy is shut down and files closed: nothing is lost, and tearing down what a
    C++ library still holds (a busy worker thread, casadi's NLP structures) is skipped.
    """
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


# Our per-tick topics need no QoS event callbacks; each one would be another
# entity in every wait set rclpy rebuilds per spin.
NO_SUB_EVENTS = SubscriptionEventCallbacks(use_default_callbacks=False)
NO_PUB_EVENTS = PublisherEventCallbacks(use_default_callbacks=False)


class KeptWaitSet:
    """A wait set on a fixed list of subscriptions, kept between waits (rclpy's executor builds a new one on every
    spin): the subscriptions' and the context's handles are held until :meth:`close`. Raises AttributeError,
    TypeError or ImportError when rclpy's internals are not what this expects (callers then use an executor)."""

    def __init__(self, subscriptions, context):
        from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy

        self.subs = list(subscriptions)
        self._held = contextlib.ExitStack()
        try:
            for sub in self.subs:
                self._held.enter_context(sub.handle)
            self._held.enter_context(context.handle)
            self._wait_set = _rclpy.WaitSet(len(self.subs), 0, 0, 0, 0, 0, context.handle)
            self._pointers = [sub.handle.pointer for sub in self.subs]
        except BaseException:
            self._held.close()
            raise

    def wait(self, timeout_ns: int) -> list[bool]:
        """Wait up to ``timeout_ns`` for a message; per subscription (in order), whether one is ready."""
        ws = self._wait_set
        ws.clear_entities()
        for sub in self.subs:
            ws.add_subscription(sub.handle)
        ws.wait(timeout_ns)
        ready = ws.get_ready_entities("subscription")
        return [p in ready for p in self._pointers]

    def close(self) -> None:
        self._held.close()


def decodable(msg_type) -> bool:
    """Whether :mod:`humfall_ros.recording.cdr` decodes ``msg_type`` (else rclpy's messages are used)."""
    try:
        cdr.decoder(msg_type)
    except cdr.UnsupportedType:
        return False
    return True


def xyz(v) -> SimpleNamespace:
    """A Point's (or Vector3's) fields as a namespace, for :func:`publish_encoded`, from a 2- or 3-vector
    (z = 0 for a 2-vector)."""
    return SimpleNamespace(x=float(v[0]), y=float(v[1]), z=float(v[2]) if len(v) > 2 else 0.0)


def encode(pub, msg) -> bytes:
    """``msg`` (a message of ``pub``'s type, or a :func:`cdr.blank` namespace filled like one) as the CDR bytes
    ``pub`` publishes raw (:mod:`humfall_ros.recording.cdr`)."""
    return msg if isinstance(msg, bytes) else cdr.encoder(pub.msg_type)(msg)


def publish_encoded(pub, msg) -> bytes:
    """Publish ``msg`` encoded by :func:`encode`; returns the bytes (publish them again as they are).

    For the per-tick topics: rclpy's publish of a message object converts it through the generated
    classes first (CentroidalState 77 us, WalkingState 97 us a publish on this machine; encoded here and
    published raw, about a third of that)."""
    data = encode(pub, msg)
    pub.publish(data)
    return data


# How long a node's first per-tick answer waits for its known readers to match (wall s; then it goes out anyway,
# e.g. to a reader with an incompatible QoS that never matches).
FIRST_ANSWER_HOLD_S = 2.0


class FirstAnswerHold:
    """Holds a lockstep node's first answer until every reader its graph knows of is matched.

    The graph can list a reader (the recorder, which subscribes to a topic once it sees its writer) some
    milliseconds before the writer has matched it; a volatile writer's sample published in that window never
    reaches it, and the bag would start one tick late (a CI run: no tick-0 command). The bridge resends a tick
    it has no answer to every ``retransmit_period``; the held answer goes out on one of those resends, once the
    readers are matched or after ``hold_s``. Once released, it never holds again (one bool a tick)."""

    def __init__(self, node: Node, hold_s: float = FIRST_ANSWER_HOLD_S):
        self.node = node
        self.hold_s = hold_s
        self.released = False
        self.since: float | None = None

    def ready(self, pubs) -> bool:
        """True once every publisher in ``pubs`` has matched all the readers the graph lists for its topic (or
        the hold is over); from then on always True."""
        if self.released:
            return True
        now = time.monotonic()
        if self.since is None:
            self.since = now
        unmatched = [p.topic_name for p in pubs
                     if p.get_subscription_count() < self.node.count_subscribers(p.topic_name)]
        if unmatched and now - self.since <= self.hold_s:
            return False
        if unmatched:
            self.node.get_logger().warning(f"first answer sent after {self.hold_s} s with readers of {unmatched} "
                                           "still unmatched")
        self.released = True
        return True


def decoding(node: Node, msg_type, topic: str, callback: Callable) -> Callable[[bytes], None]:
    """A raw subscription's callback: decode the bytes, hand the result to ``callback``; data that does not
    decode is logged and dropped (a bad message never kills the node)."""
    decode = cdr.decoder(msg_type)

    def on_bytes(data: bytes) -> None:
        try:
            msg = decode(data)
        except Exception as e:  # noqa: BLE001 - struct.error, ValueError: a malformed message
            node.get_logger().error(f"{topic}: undecodable message dropped ({e})", throttle_duration_sec=1.0)
            return
        callback(msg)

    return on_bytes


class HotLoop:
    """Spin a node whose work comes in per-tick messages, without rclpy's executor cost.

    rclpy's executor rebuilds a wait set of every entity of the node (parameter
    services, /clock, QoS events...) on each spin and takes one message per
    wait: ~0.3 ms a spin here, several times per control tick. A hot loop waits
    only on the per-tick subscriptions, takes everything queued on them at once
    (subscription handle's take_message, as the executor does internally) and
    services the rest of the node (parameters, services, /clock, timers) through
    the executor every ``service_period`` seconds. If rclpy's internals are not
    what this expects, it falls back to plain ``executor.spin()``.
    """

    def __init__(self, node: Node, service_period: float = 0.05, on_batch: Callable[[], None] | None = None,
                 pace: float = 0.0, gathering: Callable[[], bool] | None = None):
        self.node = node
        # trigger-first waiting (subscribe(trigger=True)): while ``gathering()`` is False the loop sleeps on the
        # trigger subscriptions only (the tick gate's trigger, whose message comes last in a tick) and then takes
        # whatever the others hold; while it is True (a trigger arrived before the rest of its tick) on all.
        # Waking on each of a controller's four per-tick topics cost three wake-ups a tick that found nothing
        # to do yet (~65 us of Python each, plus the context switches)
        self.gathering = gathering
        self.trigger_subs: set = set()
        self.service_period = service_period
        # s to sleep before each wait, so that the messages of a tick gather and one wait takes them
        # all (the recorder: a dozen topics per tick; latency does not matter to it)
        self.pace = pace
        # called after each batch of taken messages: a node that fell behind (free-run on a
        # busy machine) can then answer only the newest tick instead of every stale one
        self.on_batch = on_batch
        self.batching = False  # True while spin() runs its own loop (and so calls on_batch)
        self.subs: list[tuple[Any, type, Callable, bool]] = []
        self.composition = Composition.current
        if self.composition is not None:
            self.composition.loops.append(self)

    def subscribe(self, msg_type, topic: str, callback: Callable, qos=None, raw: bool = False,
                  with_info: bool = False, decoded: bool = False, trigger: bool = False):
        """A per-tick subscription: ``callback(msg)``, or ``callback(msg, info)`` with ``with_info``
        (the executor passes the same two to a two-argument callback); ``raw`` takes serialized bytes.

        ``decoded``: take the bytes and decode them with :mod:`humfall_ros.recording.cdr` (5-10x cheaper
        than rclpy building the message): ``callback`` gets a read-only SimpleNamespace tree with the
        message's field names, not a message (never publish it or assign its parts into a message).

        ``trigger``: the loop may sleep on this subscription alone (see ``gathering``)."""
        if decoded and (raw or with_info):
            raise ValueError("decoded excludes raw and with_info")
        decoded = decoded and decodable(msg_type)
        if self.composition is not None and not (raw or with_info):  # composed: one subscription per topic
            return self.composition.subscribe(self.node, msg_type, topic, callback, qos, decoded)
        if decoded:
            callback, raw = decoding(self.node, msg_type, topic, callback), True
        sub = self.node.create_subscription(msg_type, topic, callback, qos or QOS_RELIABLE,
                                            event_callbacks=NO_SUB_EVENTS, raw=raw)
        self.subs.append((sub, msg_type, callback, with_info))
        if trigger:
            self.trigger_subs.add(sub)
        return sub

    def spin(self, executor) -> None:
        ctx = self.node.context
        next_service = 0.0
        self.batching = True
        timeout_ns = int(self.service_period * 1e9)
        # the wait set is kept while the subscriptions stay the same, and only the subscriptions it reports
        # ready are taken from. Polling every subscription until all were empty took ~27 takes per tick for
        # 4 messages, ~0.9 ms a tick of the locomotion node (profiled).
        kept: KeptWaitSet | None = None
        kept_trigger: KeptWaitSet | None = None
        subs: tuple = ()
        try:
            while ctx.ok():
                if self.pace > 0:
                    time.sleep(self.pace)
                if len(self.subs) != len(subs):  # a callback may add one (the recorder's discovery)
                    for k in (kept, kept_trigger):
                        if k is not None:
                            k.close()
                    subs = tuple(self.subs)
                    kept = KeptWaitSet([sub for sub, *_ in subs], ctx) if subs else None
                    triggers = [sub for sub, *_ in subs if sub in self.trigger_subs]
                    kept_trigger = KeptWaitSet(triggers, ctx) if triggers and self.gathering is not None else None
                taken = 0
                if kept is None:  # rcl refuses to wait on an empty wait set
                    time.sleep(self.service_period)
                else:
                    if kept_trigger is not None and not self.gathering():
                        # a trigger's tick: take everything the tick's other topics (and the latched ones) hold
                        ready_all = any(kept_trigger.wait(timeout_ns))
                        ready = [ready_all] * len(subs)
                    else:
                        ready = kept.wait(timeout_ns)
                    for (sub, msg_type, callback, with_info), flag in zip(subs, ready):
                        if not flag:
                            continue
                        # drain it: a node that fell behind answers only the newest tick (on_batch)
                        while (msg := sub.handle.take_message(msg_type, sub.raw)) is not None:
                            taken += 1
                            if with_info:
                                callback(msg[0], msg[1])
                            else:
                                callback(msg[0])
                now = time.monotonic()
                if now >= next_service:
                    executor.spin_once(timeout_sec=0.0)  # may run a hot callback too
                    next_service = now + self.service_period
                    taken += 1
                if taken and self.on_batch is not None:
                    self.on_batch()
        except (AttributeError, TypeError, ImportError) as e:  # rclpy internals changed (KeptWaitSet)
            self.node.get_logger().warning(f"hot loop disabled ({e}); spinning the executor")
            self.batching = False
            executor.spin()
        finally:
            for k in (kept, kept_trigger):
                if k is not None:
                    k.close()


class Composition:
    """Several per-tick nodes in one process and one wait set (``humfall up --compose``).

    Each node stays its own node, with its own parameters, publishers and topics; what
    they share is the process: one hot loop waits on every per-tick topic, and a topic
    that several of them read (joint_states, centroidal_state, mux/state) is subscribed
    once and its message handed to each (as ROS 2 composition delivers intra-process),
    instead of being taken and deserialised once per node. After each batch every
    node's ``on_batch`` runs, in construction order.

    Activate it (``Composition.current = c``) before constructing the nodes.
    """

    current: "Composition | None" = None

    def __init__(self):
        self.loops: list[HotLoop] = []
        self.fanout: dict[tuple[str, type], list[Callable]] = {}
        self.subs: list[tuple[Any, type, Callable, bool]] = []

    def subscribe(self, node: Node, msg_type, topic: str, callback: Callable, qos=None, decoded: bool = False):
        key = (node.resolve_topic_name(topic), msg_type, decoded)
        if key in self.fanout:
            self.fanout[key].append(callback)
            return None
        callbacks = self.fanout[key] = [callback]

        def fan(msg, callbacks=callbacks):
            for cb in callbacks:
                cb(msg)

        taken = decoding(node, msg_type, topic, fan) if decoded else fan  # decoded once, handed to each
        sub = node.create_subscription(msg_type, topic, taken, qos or QOS_RELIABLE, event_callbacks=NO_SUB_EVENTS,
                                       raw=decoded)
        self.subs.append((sub, msg_type, taken, False))
        return sub

    def spin(self, executor, service_period: float = 0.05) -> None:
        if not self.loops:
            executor.spin()
            return
        combined = HotLoop.__new__(HotLoop)
        combined.node = self.loops[0].node
        combined.service_period = service_period
        combined.pace = 0.0
        combined.subs = self.subs
        combined.composition = None
        combined.gathering, combined.trigger_subs = None, set()  # one wait on every member's topics
        members = list(self.loops)

        def on_batch():
            for loop in members:
                if loop.on_batch is not None:
                    loop.on_batch()

        combined.on_batch = on_batch
        for loop in members:
            loop.batching = True
        combined.batching = True
        HotLoop.spin(combined, executor)
