"""The tick gate: stamped inputs in, "compute / retransmit / reset" decisions out (no rclpy).

Every per-tick node of the suite (estimator, controllers, monitors) receives
messages stamped with the bridge's tick time and must

* compute tick k once all its inputs of stamp k have arrived,
* answer a repeated stamp (the bridge retransmits a tick when nothing moved,
  e.g. during discovery) with its last output, without computing again,
* forget everything when time goes back (``sim/reset``),
* in free-run, when several ticks queued up, compute only the newest complete one.

``TickGate.offer`` stores one input and returns at once what to do about a
repeated or past stamp; ``TickGate.poll`` returns the newest complete tick to
compute (dropping older pending ones). A node calls ``poll`` after each input
(plain executor) or after each batch of inputs (hot loop).
"""
from __future__ import annotations

import dataclasses
import enum
from typing import Any, Iterable

MAX_PENDING_TICKS = 100  # incomplete ticks kept while waiting for their last input


class Action(enum.Enum):
    WAIT = "wait"                # stored; nothing to do yet
    RETRANSMIT = "retransmit"    # a stamp already computed: send the last output again
    RESET = "reset"              # time went back: the caller resets its state (the input is kept for the new run)


@dataclasses.dataclass
class Tick:
    """A complete tick: its stamp [ns] and one input per required kind."""

    stamp_ns: int
    inputs: dict[str, Any]


class TickGate:
    """Collects the inputs of each stamp until every required kind is there.

    Args:
        required: input kinds a tick needs (e.g. ``{"centroidal_state", "mux"}``).
        trigger: the kind whose repetition means "retransmitted tick" (default: the
            first of ``required`` in sorted order); repeats of other kinds are ignored.
    """

    def __init__(self, required: Iterable[str], trigger: str | None = None):
        self.required = frozenset(required)
        if not self.required:
            raise ValueError("a tick gate needs at least one required input")
        self.trigger = trigger or sorted(self.required)[0]
        if self.trigger not in self.required:
            raise ValueError(f"trigger {self.trigger!r} is not a required input")
        self.last_stamp = -1
        self.pending: dict[int, dict[str, Any]] = {}
        self.resets = 0
        self.dropped = 0

    def offer(self, kind: str, stamp_ns: int, value: Any) -> Action:
        """Store an input of ``kind`` stamped ``stamp_ns``; what the caller must do now."""
        if kind not in self.required:
            raise KeyError(f"{kind!r} is not an input of this gate ({sorted(self.required)})")
        if stamp_ns == self.last_stamp:
            return Action.RETRANSMIT if kind == self.trigger else Action.WAIT
        action = Action.WAIT
        if stamp_ns < self.last_stamp:
            # Each input topic is ordered (reliable, one publisher), so an older stamp than
            # the last computed tick can only mean a new timeline: sim/reset restarted time.
            self.pending.clear()
            self.last_stamp = -1
            self.resets += 1
            action = Action.RESET
        self.pending.setdefault(stamp_ns, {})[kind] = value
        if len(self.pending) > MAX_PENDING_TICKS:  # an input went quiet: do not grow forever
            for old in sorted(self.pending)[:-MAX_PENDING_TICKS]:
                del self.pending[old]
                self.dropped += 1
        return action

    def poll(self) -> Tick | None:
        """The newest complete tick (older pending ones are dropped), or None."""
        complete = [k for k, slot in self.pending.items() if self.required <= slot.keys()]
        if not complete:
            return None
        k = max(complete)
        inputs = self.pending.pop(k)
        for old in [x for x in self.pending if x < k]:
            del self.pending[old]
            self.dropped += 1
        self.last_stamp = k
        return Tick(k, inputs)

    def gathering(self, kind: str | None = None) -> bool:
        """Whether some tick has its input ``kind`` (default: the trigger) but not yet all the others."""
        kind = kind or self.trigger
        return any(kind in slot and not self.required <= slot.keys() for slot in self.pending.values())

    def reset(self) -> None:
        self.pending.clear()
        self.last_stamp = -1


__all__ = ["Action", "MAX_PENDING_TICKS", "Tick", "TickGate"]
