"""``humfall bag info``: a readable summary of a bag (topics, types, counts, rates, duration, holes)."""
from __future__ import annotations

import os
import sys
from typing import Any, TextIO

from humfall_ros.recording.reader import bag_info


def _size(n: int) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n} B"


def _secs(ns: int | None) -> str:
    return "-" if ns is None else f"{ns * 1e-9:.3f}"


def _holes(info: dict[str, Any]) -> str:
    periodic = [t for t in info["topics"] if t.get("missing_stamps") is not None]
    holed = [t for t in periodic if t["missing_stamps"] > 0]
    if not periodic:
        return "holes:     - (no periodic stamped topic)"
    if not holed:
        return f"holes:     none on {len(periodic)} periodic stamped topics"
    return (f"holes:     {sum(t['missing_stamps'] for t in holed)} stamps missing on {len(holed)} of "
            f"{len(periodic)} periodic stamped topics (column 'missing')")


def format_info(info: dict[str, Any]) -> str:
    """The text ``info_main`` prints, from ``bag_info``'s dict."""
    meta = info.get("metadata", {}).get("humfall_recorder", {})
    if info["finalized"]:
        state = "finalized"
    else:
        state = ("NOT finalized (recorder did not close it: cut off at the last flushed chunk; "
                 "`humfall_ros.recording.recover` writes a finalized copy)")
    lines = [
        f"bag:       {info['path']}  ({_size(info['size_bytes'])}, {state})",
        f"log time:  {meta.get('log_time_clock', 'unknown')} clock"
        + (f"   scenario: {meta['scenario']}" if meta.get("scenario") else ""),
        f"duration:  {info['duration_s']:.3f} s   (start {_secs(info['start_ns'])} s, "
        f"end {_secs(info['end_ns'])} s)",
        f"messages:  {info['message_count']} on {len(info['topics'])} topics",
        _holes(info),
        "",
    ]
    # the rate by the messages' own stamps where they carry one (a recorder that fell behind logs late), else by
    # log time
    rows = [("topic", "type", "count", "rate Hz", "first s", "last s", "missing")]
    for t in info["topics"]:
        missing = t.get("missing_stamps")
        rate = t.get("stamp_rate_hz") or t["rate_hz"]
        rows.append((t["topic"], t["type"], str(t["count"]),
                     "-" if rate is None else f"{rate:.1f}",
                     _secs(t["first_ns"]), _secs(t["last_ns"]), "-" if missing is None else str(missing)))
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    for k, r in enumerate(rows):
        cells = [r[0].ljust(widths[0]), r[1].ljust(widths[1])] + [c.rjust(w) for c, w in zip(r[2:], widths[2:])]
        lines.append("  ".join(cells).rstrip())
        if k == 0:
            lines.append("  ".join("-" * w for w in widths))
    return "\n".join(lines)


def info_main(path: str | os.PathLike, out: TextIO | None = None) -> int:
    """Print the summary of a bag (file or run folder). 0 on success, 1 if it cannot be read."""
    out = out or sys.stdout
    try:
        info = bag_info(path)
    except (OSError, ValueError) as exc:
        print(f"humfall bag info: {exc}", file=sys.stderr)
        return 1
    print(format_info(info), file=out)
    return 0
