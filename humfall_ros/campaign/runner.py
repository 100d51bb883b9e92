"""Run a campaign: spec -> trials -> executor -> Parquet rows, resumable, with a progress bar.

Everything that can refuse the spec (unknown keys, an empty design, a key the scenario
does not have, a results folder of another spec) does so before an executor starts.
Ctrl-C (SIGINT) or SIGTERM stops the executor (every worker and trial server), writes
the finished rows and exits; trials that were running are not recorded and run again
on resume.
"""
from __future__ import annotations

import collections
import dataclasses
import json
import os
import signal
import sys
import time
import uuid

from humfall_ros import scenario as scenario_mod
from humfall_ros.campaign import design as design_mod
from humfall_ros.campaign.server import TAG_ENV
from humfall_ros.campaign.spec import CampaignSpec, CampaignSpecError, spec_hash
from humfall_ros.campaign.store import ResultStore
from humfall_ros.campaign.studies import Sweep, ThresholdMap


@dataclasses.dataclass
class RunOptions:
    executor: str = "ray"            # "ray" | "local"
    workers: int | None = None       # None: all cores (local Ray), the cluster's CPUs (--address)
    address: str | None = None       # Ray cluster address; None starts a local Ray
    mode: str | None = None          # override the spec's trial.mode ("graph" for --graph)
    fresh: bool = False              # move an existing folder aside instead of resuming it
    retry_failed: bool = False       # rerun failed / timed-out / crashed trials on resume
    progress: bool = True
    out_dir: str | None = None       # override spec.output.dir


@dataclasses.dataclass
class CampaignSummary:
    results: str | None
    total: int
    ran: int
    resumed: int
    status_counts: dict
    wall_s: float
    interrupted: bool

    @property
    def trials_per_minute(self) -> float:
        return 60.0 * self.ran / self.wall_s if self.wall_s > 0 else float("nan")


def make_row(trial: design_mod.Trial, out: dict, mode: str) -> dict:
    """One table row: trial settings, study tags, status, metrics (``m.*``) and timings."""
    row = {"trial_id": trial.trial_id, "trial_index": trial.index, "base_scenario": trial.base_scenario,
           "overrides": json.dumps(list(trial.overrides)), "mode": mode}
    row.update({f"set.{k}": v for k, v in trial.settings.items()})
    row.update(trial.tags)
    row.update({"status": out.get("status"), "error": out.get("error"), "log_tail": out.get("log_tail")})
    row.update({f"m.{k}": v for k, v in (out.get("metrics") or {}).items()})
    for k in ("wall_s", "cpu_s", "started_unix", "finished_unix", "host", "worker_pid", "worker_rss_mb",
              "server_pid", "server_rss_mb", "server_hwm_mb", "executor"):
        row[k] = out.get(k)
    return row


def prepare(spec: CampaignSpec, opts: RunOptions):
    """Validate everything; returns (spec, base scenario, study, hash). Raises CampaignSpecError."""
    if opts.mode:
        spec = spec.model_copy(update={"trial": spec.trial.model_copy(update={"mode": opts.mode})})
    if opts.out_dir:
        spec = spec.model_copy(update={"output": spec.output.model_copy(update={"dir": opts.out_dir})})
    try:
        base0 = scenario_mod.load(spec.base_scenario)
    except scenario_mod.ScenarioError as e:
        raise CampaignSpecError(f"base_scenario: {e}") from None
    points = design_mod.design_points(spec)
    base = design_mod.check_design(spec, base0, points)
    study = ThresholdMap(spec, base, points) if spec.study.type == "threshold-map" else Sweep(spec, base, points)
    return spec, base0, study, spec_hash(spec, base0)


def _make_executor(opts: RunOptions, log_dir: str, mode: str):
    from humfall_ros.campaign.executors import LocalExecutor, RayExecutor

    if opts.executor == "local":
        return LocalExecutor(opts.workers or os.cpu_count() or 1, log_dir)
    return RayExecutor(opts.address, opts.workers, log_dir, cpus_per_trial=2.0 if mode == "graph" else 1.0)


def run_campaign(spec: CampaignSpec, opts: RunOptions | None = None) -> CampaignSummary:
    opts = opts or RunOptions()
    spec, base0, study, digest = prepare(spec, opts)
    out_dir = spec.output_dir()
    store = ResultStore(out_dir)
    done = store.open(spec.model_dump(mode="json"), digest, base0, fresh=opts.fresh)
    if opts.retry_failed:
        done = {k: r for k, r in done.items() if r.get("status") == "ok"}
    os.environ.setdefault(TAG_ENV, uuid.uuid4().hex)   # every process of this campaign carries it
    mode = spec.trial.mode
    bag_dir = str((out_dir / "trials").resolve()) if spec.output.bags else None
    log_dir = out_dir / "logs"
    log_dir.mkdir(exist_ok=True)

    # replay the finished trials (the studies are deterministic) before anything runs
    ready = collections.deque(study.start())
    todo: collections.deque = collections.deque()
    resumed = 0
    counts: collections.Counter = collections.Counter()

    def replay():
        nonlocal resumed
        while ready:
            t = ready.popleft()
            if t.trial_id in done:
                resumed += 1
                ready.extend(study.feed(t, done[t.trial_id]))
            else:
                todo.append(t)

    replay()
    executor = None
    interrupted = False
    ran = 0
    t0 = time.monotonic()
    startup = 0.0
    bar = None
    old_term = signal.signal(signal.SIGTERM, signal.default_int_handler)  # SIGTERM: same clean stop as Ctrl-C
    # a shell starts background jobs with SIGINT ignored (and Python keeps that): Ctrl-C / kill -INT must still stop us
    old_int0 = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        if todo:
            executor = _make_executor(opts, str(log_dir), mode)
            startup = time.monotonic() - t0
            t0 = time.monotonic()      # the campaign's wall time counts from a running executor
        if opts.progress:
            from tqdm import tqdm

            # resumed trials are done from the start and do not count in the rate or the ETA
            bar = tqdm(total=study.total, initial=resumed, unit="trial", desc=spec.name, dynamic_ncols=True,
                       file=sys.stderr, smoothing=0.05)
        while todo or (executor is not None and executor.in_flight()):
            while todo and executor.in_flight() < executor.capacity:
                t = todo.popleft()
                executor.submit(t, _request(t, spec, mode, bag_dir))
            for trial, out in executor.completed(timeout=0.5):
                row = make_row(trial, out, mode)
                store.add(row)
                ran += 1
                counts[row["status"]] += 1
                ready.extend(study.feed(trial, row))
                replay()
                if bar is not None:
                    bar.update(1)
                    bar.set_postfix({k: v for k, v in sorted(counts.items())}, refresh=False)
            if bar is not None and study.total != bar.total:
                bar.total = study.total
            if time.monotonic() - store.last_flush > store.flush_s:
                store.flush()
    except KeyboardInterrupt:
        interrupted = True
    finally:
        signal.signal(signal.SIGINT, signal.SIG_IGN)   # a second Ctrl-C must not cut the clean-up short
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        # the finished rows first: a crash inside Ray's shutdown (seen once: SIGSEGV when Ctrl-C came while
        # Ray started its workers) must not lose them
        if bar is not None:
            bar.close()
        store.flush()
        results = store.merge()
        if executor is not None:
            executor.shutdown()
        elif "ray" in sys.modules:
            # interrupted while Ray was starting: ray.init may have started its processes without being
            # "initialized" yet; shutdown() stops whatever it started (a no-op if nothing)
            sys.modules["ray"].shutdown()
        wall = time.monotonic() - t0
        store.finish_session(ran=ran, interrupted=interrupted, wall_s=round(wall, 3),
                             executor=opts.executor, workers=getattr(executor, "workers", None),
                             executor_startup_s=round(startup, 2),
                             status_counts=dict(counts))
        signal.signal(signal.SIGTERM, old_term)
        signal.signal(signal.SIGINT, old_int0)
    return CampaignSummary(str(results) if results else None, study.total, ran, resumed, dict(counts), wall,
                           interrupted)


def _request(trial, spec: CampaignSpec, mode: str, bag_dir: str | None):
    from humfall_ros.campaign.executors import request_for

    return request_for(trial, mode, spec.trial.time_limit_s, bag_dir, spec.trial.stop_when_fallen)
