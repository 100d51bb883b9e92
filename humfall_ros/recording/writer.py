"""MCAP bag writer for raw (CDR-serialised) ROS 2 messages, with per-topic stats.

Plain Python (no rclpy) so the file logic is unit-testable:
``BagWriter.add_topic`` registers a ``ros2msg`` schema and a ``cdr`` channel
the way rosbag2 does (including the ``offered_qos_profiles`` channel metadata,
so ``ros2 bag play`` re-offers e.g. a latched topic as transient-local);
``write`` appends one serialised message; ``flush`` closes the chunk in progress
and pushes it to the OS. The recorder calls ``flush`` at least once a second,
which is what bounds the loss on a ``kill -9`` to the last flush period: every
flushed chunk is a complete record a streaming reader can decode even though
the file then has no summary or footer (see ``reader.recover``).

``close`` writes the summary section (schemas, channels, statistics, chunk
indexes) and footer, and the ``recording_stats.json`` next to the bag.
"""
from __future__ import annotations

import json
import os
import pathlib
import time
from dataclasses import asdict, dataclass, field
from typing import Any

from mcap.writer import CompressionType, Writer

from humfall_ros.recording.schema import MESSAGE_ENCODING, SCHEMA_ENCODING, build_schema

PROFILE = "ros2"
LIBRARY = "humfall_ros recorder"
STATS_FILE = "recording_stats.json"
BAG_FILE = "bag.mcap"
# Chunks close on size or on flush, whichever comes first. 1 MiB is the mcap default;
# at our rates the 1 s flush usually comes first.
CHUNK_SIZE = 1024 * 1024


@dataclass
class TopicStats:
    topic: str
    type: str
    count: int = 0
    first_log_time_ns: int | None = None
    last_log_time_ns: int | None = None
    qos: dict[str, Any] = field(default_factory=dict)

    def as_json(self) -> dict[str, Any]:
        d = asdict(self)
        for k in ("first", "last"):
            ns = d[f"{k}_log_time_ns"]
            d[f"{k}_time_s"] = None if ns is None else ns * 1e-9
        return d


def qos_yaml(profiles: list[dict[str, Any]]) -> str:
    """rosbag2's ``offered_qos_profiles`` channel metadata (YAML list, one per publisher).

    Deadline, lifespan and lease duration are written as rosbag2 writes "infinite".
    """
    infinite = "\n    sec: 2147483647\n    nsec: 4294967295"
    out = []
    for p in profiles:
        out.append(
            f"- history: {p.get('history', 'keep_last')}\n"
            f"  depth: {int(p.get('depth', 0))}\n"
            f"  reliability: {p.get('reliability', 'reliable')}\n"
            f"  durability: {p.get('durability', 'volatile')}\n"
            f"  deadline:{infinite}\n"
            f"  lifespan:{infinite}\n"
            f"  liveliness: {p.get('liveliness', 'automatic')}\n"
            f"  liveliness_lease_duration:{infinite}\n"
            f"  avoid_ros_namespace_conventions: false"
        )
    return "\n".join(out)


def _compression() -> CompressionType:
    """zstd if the writer's codec is importable, else lz4, else none (all readable everywhere)."""
    for name, ctype in (("zstandard", CompressionType.ZSTD), ("lz4.frame", CompressionType.LZ4)):
        try:
            __import__(name)
            return ctype
        except ImportError:
            continue
    return CompressionType.NONE


class BagWriter:
    """One MCAP file of raw ROS 2 messages. Not thread-safe (one executor thread writes)."""

    def __init__(self, path: str | os.PathLike, metadata: dict[str, str] | None = None,
                 chunk_size: int = CHUNK_SIZE, compression: CompressionType | None = None):
        self.path = pathlib.Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(self.path, "wb")  # noqa: SIM115 - lives until close()
        self._writer = Writer(self._file, chunk_size=chunk_size,
                              compression=_compression() if compression is None else compression)
        self._writer.start(profile=PROFILE, library=LIBRARY)
        self._schemas: dict[str, int] = {}
        self.channels: dict[int, TopicStats] = {}
        self.skipped: dict[str, str] = {}   # topic -> why it is not recorded
        self.write_errors = 0
        self.started_wall = time.time()
        self.closed = False
        if metadata:
            self.add_metadata("humfall_recorder", metadata)
        self._writer.flush()

    def add_topic(self, topic: str, type_name: str, qos_profiles: list[dict[str, Any]] | None = None,
                  schema_text: str | None = None, channel_metadata: dict[str, str] | None = None) -> int:
        """Register a channel; returns its id. Raises SchemaError if the type has no definition.

        ``schema_text``/``channel_metadata`` override the built ones (``recover`` copies them).
        """
        if type_name not in self._schemas:
            text = schema_text if schema_text is not None else build_schema(type_name)
            self._schemas[type_name] = self._writer.register_schema(
                name=type_name, encoding=SCHEMA_ENCODING, data=text.encode())
        metadata = channel_metadata if channel_metadata is not None else {
            "offered_qos_profiles": qos_yaml(qos_profiles or [])}
        cid = self._writer.register_channel(topic=topic, message_encoding=MESSAGE_ENCODING,
                                            schema_id=self._schemas[type_name], metadata=metadata)
        self.channels[cid] = TopicStats(topic, type_name, qos=(qos_profiles or [{}])[0])
        return cid

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        self._writer.add_metadata(name, {k: str(v) for k, v in data.items()})

    def write(self, channel_id: int, data: bytes, log_time: int, publish_time: int | None = None) -> None:
        st = self.channels[channel_id]
        self._writer.add_message(channel_id=channel_id, log_time=log_time, data=data,
                                 publish_time=log_time if publish_time is None else publish_time,
                                 sequence=st.count)
        st.count += 1
        if st.first_log_time_ns is None:
            st.first_log_time_ns = log_time
        st.last_log_time_ns = log_time

    def flush(self) -> None:
        """Write the open chunk and hand it to the OS (survives the process being killed)."""
        if not self.closed:
            self._writer.flush()

    def stats(self) -> dict[str, Any]:
        topics = sorted((s.as_json() for s in self.channels.values()), key=lambda d: d["topic"])
        return {
            "bag": str(self.path),
            "finalized": self.closed,
            "started_wall_time": self.started_wall,
            "message_count": sum(s.count for s in self.channels.values()),
            "topics": topics,
            "skipped_topics": dict(sorted(self.skipped.items())),
            "write_errors": self.write_errors,
        }

    def write_stats(self, path: str | os.PathLike | None = None, extra: dict[str, Any] | None = None) -> pathlib.Path:
        """Write the stats JSON atomically (rename), so a reader never sees half a file."""
        p = pathlib.Path(path) if path else self.path.parent / STATS_FILE
        data = self.stats()
        if extra:
            data.update(extra)
        tmp = p.with_suffix(".json.tmp")
        tmp.write_text(json.dumps(data, indent=2) + "\n")
        os.replace(tmp, p)
        return p

    def close(self) -> None:
        """Finish the file (summary, statistics, footer). Idempotent."""
        if self.closed:
            return
        try:
            self._writer.finish()
        finally:
            self.closed = True
            self._file.close()
