"""The results table on disk: resumable Parquet fragments merged into one ``results.parquet``.

Layout of a campaign folder::

    campaign.json          spec, its hash, base scenario, start/finish stamps, git commit
    fragments/part-*.parquet   finished trials, appended in batches while the campaign runs
    results.parquet        all fragments merged, one row per trial, sorted by trial_index

A fragment is written to a temporary name and renamed, so a crash leaves whole
fragments only; at most the last ``flush_s`` seconds of finished trials are lost and
rerun. A folder made by another spec (another hash) is refused.
"""
from __future__ import annotations

import datetime as dt
import json
import os
import pathlib
import subprocess
import time

import pyarrow as pa
import pyarrow.parquet as pq

# columns that differ between two runs of the same trials (left out when comparing tables)
TIMING_COLUMNS = ("wall_s", "cpu_s", "started_unix", "finished_unix", "host", "worker_pid", "worker_rss_mb",
                  "server_pid", "server_rss_mb", "server_hwm_mb", "log_tail", "executor", "m.bridge_cpu_s",
                  "m.bridge_wall_time_s", "m.graph_wall_time_s", "m.bag")


class ResumeError(RuntimeError):
    """The output folder holds results of another spec."""


def _git_commit() -> str | None:
    try:
        return subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, timeout=5, check=False,
                              cwd=pathlib.Path(__file__).resolve().parent).stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        return None


def _cell(v):
    """A value Parquet can hold in a column of scalars or a list of numbers."""
    if isinstance(v, dict):
        return json.dumps(v, sort_keys=True)
    if isinstance(v, (list, tuple)):
        if all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v):
            return [float(x) for x in v]
        return json.dumps(v)
    if isinstance(v, int) and not isinstance(v, bool):
        return v
    return v


class ResultStore:
    def __init__(self, out_dir: str | os.PathLike, flush_s: float = 2.0, flush_rows: int = 256):
        self.dir = pathlib.Path(out_dir)
        self.fragments = self.dir / "fragments"
        self.flush_s = flush_s
        self.flush_rows = flush_rows
        self.buffer: list[dict] = []
        self.last_flush = time.monotonic()
        self.seq = 0

    # ------------------------------------------------------------------ opening
    def open(self, spec_json: dict, digest: str, base_scenario: dict, fresh: bool = False) -> dict[str, dict]:
        """Create or reopen the folder; returns the finished rows by trial_id (empty when new).

        Raises ResumeError when the folder was made by another spec (hash), unless ``fresh``
        (then its old results are moved aside to ``<dir>.old-<stamp>``).
        """
        meta_path = self.dir / "campaign.json"
        if meta_path.is_file():
            meta = json.loads(meta_path.read_text())
            if meta.get("spec_hash") != digest and not fresh:
                raise ResumeError(
                    f"{self.dir} holds results of another spec (hash {meta.get('spec_hash', '?')[:12]}, "
                    f"this spec {digest[:12]}): choose another output.dir, or --fresh to move them aside")
            if fresh:
                stamp = dt.datetime.now().strftime("%Y%m%d-%H%M%S")
                self.dir.rename(self.dir.with_name(f"{self.dir.name}.old-{stamp}"))
        elif self.dir.exists() and any(self.dir.iterdir()) and not fresh:
            raise ResumeError(f"{self.dir} exists and is not a campaign folder (no campaign.json)")
        self.fragments.mkdir(parents=True, exist_ok=True)
        done = self.load_rows() if meta_path.is_file() else {}
        meta = json.loads(meta_path.read_text()) if meta_path.is_file() else {
            "spec": spec_json, "spec_hash": digest, "base_scenario": base_scenario,
            "created": dt.datetime.now().isoformat(timespec="seconds"), "git_commit": _git_commit(), "sessions": []}
        meta["sessions"].append({"started": dt.datetime.now().isoformat(timespec="seconds"),
                                 "resumed_trials": len(done), "git_commit": _git_commit()})
        self._write_meta(meta)
        self.seq = len(list(self.fragments.glob("part-*.parquet")))
        return done

    def _write_meta(self, meta: dict) -> None:
        tmp = self.dir / "campaign.json.tmp"
        tmp.write_text(json.dumps(meta, indent=2, default=str))
        tmp.replace(self.dir / "campaign.json")

    def meta(self) -> dict:
        return json.loads((self.dir / "campaign.json").read_text())

    def finish_session(self, **info) -> None:
        meta = self.meta()
        meta["sessions"][-1].update({"ended": dt.datetime.now().isoformat(timespec="seconds"), **info})
        self._write_meta(meta)

    # ------------------------------------------------------------------ rows
    def add(self, row: dict) -> None:
        self.buffer.append(row)
        if len(self.buffer) >= self.flush_rows or time.monotonic() - self.last_flush >= self.flush_s:
            self.flush()

    def flush(self) -> None:
        if self.buffer:
            table = pa.Table.from_pylist([{k: _cell(v) for k, v in r.items()} for r in self.buffer])
            name = f"part-{self.seq:06d}-{os.getpid()}.parquet"
            tmp = self.fragments / f".{name}.tmp"
            pq.write_table(table, tmp)
            tmp.replace(self.fragments / name)
            self.seq += 1
            self.buffer = []
        self.last_flush = time.monotonic()

    def read_fragments(self) -> pa.Table | None:
        parts = sorted(self.fragments.glob("part-*.parquet"))
        if not parts:
            return None
        return pa.concat_tables([pq.read_table(p) for p in parts], promote_options="permissive")

    def load_rows(self) -> dict[str, dict]:
        t = self.read_fragments()
        if t is None:
            return {}
        return {r["trial_id"]: r for r in t.to_pylist()}  # a later fragment wins (a retried trial)

    def merge(self) -> pathlib.Path | None:
        """Write results.parquet: every finished trial once (the latest attempt), sorted by trial_index."""
        self.flush()
        t = self.read_fragments()
        if t is None:
            return None
        rows = {r["trial_id"]: r for r in t.to_pylist()}
        table = pa.Table.from_pylist(sorted(rows.values(), key=lambda r: r["trial_index"]), schema=t.schema)
        meta = self.meta()
        table = table.replace_schema_metadata({b"humfall_campaign": json.dumps(
            {"spec": meta["spec"], "spec_hash": meta["spec_hash"]}).encode()})
        out = self.dir / "results.parquet"
        tmp = self.dir / ".results.parquet.tmp"
        pq.write_table(table, tmp)
        tmp.replace(out)
        return out


def load_results(path: str | os.PathLike) -> tuple[pa.Table, dict]:
    """(table, campaign.json) from a campaign folder or its results.parquet (fragments merged if need be)."""
    p = pathlib.Path(path)
    d = p if p.is_dir() else p.parent
    meta_path = d / "campaign.json"
    meta = json.loads(meta_path.read_text()) if meta_path.is_file() else {}
    if p.is_file():
        table = pq.read_table(p)
        if not meta:
            raw = (table.schema.metadata or {}).get(b"humfall_campaign")
            meta = json.loads(raw) if raw else {}
        return table, meta
    store = ResultStore(d)
    if (d / "results.parquet").is_file() and not any(
            f.stat().st_mtime > (d / "results.parquet").stat().st_mtime for f in store.fragments.glob("part-*")):
        return pq.read_table(d / "results.parquet"), meta
    if store.read_fragments() is None:
        raise FileNotFoundError(f"no results in {d}")
    return pq.read_table(store.merge()), meta


def comparable(table: pa.Table) -> pa.Table:
    """The table without timing/host columns, sorted: equal for two runs of the same trials."""
    keep = [c for c in table.column_names if c not in TIMING_COLUMNS]
    return table.select(keep).sort_by("trial_index")
