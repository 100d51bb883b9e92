"""Reading our bags, finalized or cut short by a ``kill -9``.

Everything here streams the file from the start (``mcap.stream_reader``) instead
of seeking to the summary at the end, because a bag whose recorder was killed has
no summary and no footer. Every chunk the recorder flushed is a complete record,
so the stream yields all of them and stops at the first incomplete record at the
tail (``ScanResult.truncated``). ``recover`` rewrites such a file as a finalized
copy that any MCAP reader (mcap_ros2, rosbags, Foxglove) opens.

Decoding uses the ``ros2msg`` schemas stored in the bag (mcap_ros2's dynamic
decoder), so it needs neither rclpy nor the interface packages; a message that
does not decode is counted and skipped, never fatal.
"""
from __future__ import annotations

import os
import pathlib
from dataclasses import dataclass, field
from typing import Any, Iterable, Iterator

import numpy as np
from mcap.records import Channel, Footer, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap_ros2.decoder import DecoderFactory

from humfall_ros.recording.cdr import leading_stamp_ns
from humfall_ros.recording.writer import BAG_FILE


def resolve_bag(path: str | os.PathLike) -> pathlib.Path:
    """A bag file, or a run folder holding one (``bag.mcap`` or a single ``*.mcap``)."""
    p = pathlib.Path(path)
    if p.is_dir():
        if (p / BAG_FILE).is_file():
            return p / BAG_FILE
        found = sorted(p.glob("*.mcap"))
        if len(found) == 1:
            return found[0]
        raise FileNotFoundError(f"{p}: expected one .mcap file in the folder, found {len(found)}")
    if not p.is_file():
        raise FileNotFoundError(f"{p}: no such bag")
    return p


@dataclass
class RawMessage:
    topic: str
    type: str
    log_time: int          # ns
    publish_time: int      # ns
    data: bytes
    channel_id: int


@dataclass
class ScanResult:
    """What a streaming pass learnt besides the messages (filled in while iterating)."""
    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    finalized: bool = False          # footer reached
    truncated: bool = False          # stream ended inside a record
    error: str | None = None


def iter_raw(path: str | os.PathLike, topics: Iterable[str] | None = None,
             scan: ScanResult | None = None) -> Iterator[RawMessage]:
    """Every message of the bag in file order, undecoded. Stops quietly at a cut-off tail.

    Pass a ``ScanResult`` to learn schemas, channels and whether the file was complete.
    """
    scan = scan if scan is not None else ScanResult()
    wanted = None if topics is None else {_norm(t) for t in topics}
    with open(resolve_bag(path), "rb") as f:
        records = StreamReader(f, skip_magic=False, emit_chunks=False).records
        while True:
            try:
                rec = next(records)
            except StopIteration:
                break
            except Exception as exc:  # noqa: BLE001 - EndOfFile, struct.error, decompress errors: a cut tail
                scan.truncated = True
                scan.error = f"{type(exc).__name__}: {exc}"
                break
            if isinstance(rec, Message):
                ch = scan.channels.get(rec.channel_id)
                if ch is None or (wanted is not None and ch.topic not in wanted):
                    continue
                sch = scan.schemas.get(ch.schema_id)
                yield RawMessage(ch.topic, sch.name if sch else "", rec.log_time, rec.publish_time,
                                 rec.data, rec.channel_id)
            elif isinstance(rec, Channel):
                scan.channels.setdefault(rec.id, rec)
            elif isinstance(rec, Schema):
                scan.schemas.setdefault(rec.id, rec)
            elif isinstance(rec, Metadata):
                scan.metadata[rec.name] = dict(rec.metadata)
            elif isinstance(rec, Footer):
                scan.finalized = True
    if not scan.finalized and not scan.truncated:
        # A stream that ends exactly at a record boundary but before the footer.
        scan.truncated = True


def _norm(topic: str) -> str:
    return topic if topic.startswith("/") else "/" + topic


@dataclass
class DecodeErrors:
    count: int = 0
    by_topic: dict[str, int] = field(default_factory=dict)
    last: str | None = None

    def add(self, topic: str, exc: Exception) -> None:
        self.count += 1
        self.by_topic[topic] = self.by_topic.get(topic, 0) + 1
        self.last = f"{topic}: {type(exc).__name__}: {exc}"


def read_messages(path: str | os.PathLike, topics: Iterable[str] | None = None,
                  errors: DecodeErrors | None = None,
                  scan: ScanResult | None = None) -> Iterator[tuple[RawMessage, Any]]:
    """Decoded messages ``(raw, msg)``; undecodable ones are counted in ``errors`` and skipped.

    ``msg`` is a plain object with the ROS field names (``msg.com.x``).
    """
    errors = errors if errors is not None else DecodeErrors()
    scan = scan if scan is not None else ScanResult()
    factory = DecoderFactory()
    decoders: dict[int, Any] = {}
    for raw in iter_raw(path, topics, scan):
        dec = decoders.get(raw.channel_id)
        if dec is None:
            ch = scan.channels[raw.channel_id]
            try:
                dec = factory.decoder_for(ch.message_encoding, scan.schemas.get(ch.schema_id))
            except Exception as exc:  # noqa: BLE001 - a schema mcap_ros2 cannot parse
                errors.add(raw.topic, exc)
                dec = None
            decoders[raw.channel_id] = dec or _undecodable
        try:
            msg = dec(raw.data)
        except Exception as exc:  # noqa: BLE001 - bad CDR, wrong type on the wire
            errors.add(raw.topic, exc)
            continue
        yield raw, msg


def _undecodable(_data: bytes) -> Any:
    raise ValueError("no ros2msg/cdr decoder for this channel")


STAMP_FIELD_TYPES = ("std_msgs/Header", "builtin_interfaces/Time")


def leads_with_stamp(schema_text: str) -> bool:
    """Does a ros2msg schema's first field begin with a time stamp (a ``std_msgs/Header`` or a
    ``builtin_interfaces/Time``, as ``rosgraph_msgs/Clock``)? Constants and comments are skipped."""
    for line in schema_text.splitlines():
        line = line.split("#", 1)[0].strip()
        if line.startswith("="):
            return False   # the dependencies' definitions begin: the main type has no field
        if not line:
            continue
        field_type, rest = (line.split(None, 1) + [""])[:2]
        if "=" in rest:
            continue       # a constant
        return field_type in STAMP_FIELD_TYPES
    return False


def _set_stamps(stamps: Iterable[int]) -> np.ndarray:
    """The stamps as ns, without the 0 of a header nobody filled in (not a time)."""
    t = np.fromiter(stamps, dtype=np.int64)
    return t[t > 0]


def missing_stamps(stamps: Iterable[int], min_stamps: int = 10,
                   regular_fraction: float = 0.9) -> tuple[int | None, float | None]:
    """Holes in a periodic stamped topic: (stamps missing, period in s) from the distinct stamps.

    The period is the median step between consecutive distinct stamps; a topic counts as periodic when at least
    ``regular_fraction`` of its steps are that period (within 1 %), else (events, or fewer than ``min_stamps``
    stamps) (None, None). Stamps of 0 (unset headers) are left out. A step of k periods is k - 1 missing stamps
    (a message the recorder never got, or a tick its publisher skipped)."""
    t = np.unique(_set_stamps(stamps))
    if len(t) < min_stamps:
        return None, None
    d = np.diff(t)
    period = float(np.median(d))
    if period <= 0 or np.mean(np.abs(d - period) <= 0.01 * period) < regular_fraction:
        return None, None
    k = np.rint(d / period)
    return int(np.sum(k[k > 1] - 1)), period * 1e-9


def stamp_rate_hz(stamps: Iterable[int]) -> float | None:
    """Messages per second of the messages' own stamps (unset stamps of 0 left out): (count - 1) / stamp span.
    A log-time rate reads high for a recorder that fell behind and drained later (its log times are the /clock it
    had then); the stamps say when the messages were made."""
    t = _set_stamps(stamps)
    if len(t) < 2:
        return None
    span = float(t.max() - t.min()) * 1e-9
    return (len(t) - 1) / span if span > 0 else None


def bag_info(path: str | os.PathLike) -> dict[str, Any]:
    """Per-topic counts, types, times and rates; works on finalized and cut-off bags.

    Times are the bag's log times (see the recorder: sim time when ``/clock`` runs). For topics whose messages
    begin with a stamp and come at a regular period (the per-tick topics), ``missing_stamps`` counts the holes
    between the first and the last stamp, with ``stamp_period_s``; None elsewhere. ``stamp_rate_hz`` is the rate by
    the messages' stamps for every topic whose type leads with one (``rate_hz``: by log time).
    """
    bag = resolve_bag(path)
    scan = ScanResult()
    per: dict[int, dict[str, Any]] = {}
    for raw in iter_raw(bag, scan=scan):
        t = per.get(raw.channel_id)
        if t is None:
            # the channel and its schema precede its first message: read stamps only where the type leads with one
            ch = scan.channels.get(raw.channel_id)
            sch = scan.schemas.get(ch.schema_id) if ch is not None else None
            stamped = (sch is not None and sch.encoding == "ros2msg"
                       and leads_with_stamp(sch.data.decode(errors="replace")))
            t = per[raw.channel_id] = {"count": 0, "first_ns": raw.log_time, "last_ns": raw.log_time,
                                       "stamps": [] if stamped else None}
        t["count"] += 1
        t["first_ns"] = min(t["first_ns"], raw.log_time)
        t["last_ns"] = max(t["last_ns"], raw.log_time)
        if t["stamps"] is not None:
            st = leading_stamp_ns(raw.data)
            if st is not None:
                t["stamps"].append(st)
    topics: dict[str, dict[str, Any]] = {}
    stamps: dict[str, list[int]] = {}
    for cid, ch in scan.channels.items():
        sch = scan.schemas.get(ch.schema_id)
        t = per.get(cid, {"count": 0, "first_ns": None, "last_ns": None, "stamps": None})
        entry = topics.setdefault(ch.topic, {"topic": ch.topic, "type": sch.name if sch else "",
                                             "count": 0, "first_ns": None, "last_ns": None})
        entry["count"] += t["count"]
        if t["stamps"] is not None:
            stamps.setdefault(ch.topic, []).extend(t["stamps"])
        for k, fn in (("first_ns", min), ("last_ns", max)):
            if t[k] is not None:
                entry[k] = t[k] if entry[k] is None else fn(entry[k], t[k])
    for e in topics.values():
        span = (e["last_ns"] - e["first_ns"]) * 1e-9 if e["count"] else 0.0
        e["duration_s"] = span
        e["rate_hz"] = (e["count"] - 1) / span if e["count"] > 1 and span > 0 else None
        st = stamps.get(e["topic"], [])
        e["stamp_rate_hz"] = stamp_rate_hz(st)
        e["missing_stamps"], e["stamp_period_s"] = missing_stamps(st)
    starts = [e["first_ns"] for e in topics.values() if e["first_ns"] is not None]
    ends = [e["last_ns"] for e in topics.values() if e["last_ns"] is not None]
    start, end = (min(starts), max(ends)) if starts else (None, None)
    return {
        "path": str(bag),
        "size_bytes": bag.stat().st_size,
        "finalized": scan.finalized,
        "truncated": scan.truncated,
        "tail_error": scan.error,
        "message_count": sum(e["count"] for e in topics.values()),
        "start_ns": start,
        "end_ns": end,
        "duration_s": (end - start) * 1e-9 if starts else 0.0,
        "metadata": scan.metadata,
        "topics": sorted(topics.values(), key=lambda e: e["topic"]),
    }


def recover(path: str | os.PathLike, out: str | os.PathLike | None = None) -> pathlib.Path:
    """Rewrite a (possibly cut-off) bag as a finalized copy; returns the new path.

    Default output: ``<name>.recovered.mcap`` next to the input. The input is not touched.
    """
    from humfall_ros.recording.writer import BagWriter  # local: writer imports nothing from here

    src = resolve_bag(path)
    dst = pathlib.Path(out) if out else src.with_name(src.stem + ".recovered.mcap")
    scan = ScanResult()
    writer = BagWriter(dst)
    ids: dict[int, int] = {}
    try:
        for raw in iter_raw(src, scan=scan):
            cid = ids.get(raw.channel_id)
            if cid is None:
                ch = scan.channels[raw.channel_id]
                sch = scan.schemas.get(ch.schema_id)
                cid = ids[raw.channel_id] = writer.add_topic(
                    ch.topic, sch.name if sch else "", schema_text=sch.data.decode() if sch else "",
                    channel_metadata=dict(ch.metadata))
            writer.write(cid, raw.data, raw.log_time, raw.publish_time)
        for name, data in scan.metadata.items():
            writer.add_metadata(name, data)
    finally:
        writer.close()
    return dst
