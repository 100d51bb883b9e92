"""Where trials run: a local pool of trial servers, or Ray tasks (a local Ray or a cluster).

Both run :meth:`humfall_ros.campaign.server.TrialServer.run` on a
:class:`~humfall_ros.campaign.server.TrialRequest` and give back the same answer dict,
so a table from one is identical (less timings) to a table from the other.

``LocalExecutor(workers)``: ``workers`` threads, each owning one trial server process
(workers=1 is a serial run). ``RayExecutor(address)``: one Ray task per trial; each Ray
worker process keeps one trial server across its tasks. ``address=None`` starts a local
Ray with ``workers`` CPUs (all cores by default) and stops it at the end; an address
joins an existing cluster (its nodes need this package importable at the same path or
installed).
"""
from __future__ import annotations

import contextlib
import dataclasses
import os
import pathlib
import queue
import socket
import tempfile
import threading
import time

from humfall_ros.campaign.design import Trial
from humfall_ros.campaign.server import TAG_ENV, TrialRequest, TrialServer, rss_mb


def request_for(trial: Trial, mode: str, time_limit_s: float, bag_dir: str | None,
                stop_when_fallen: bool = False) -> TrialRequest:
    return TrialRequest(trial.trial_id, trial.base_scenario, list(trial.overrides), mode, time_limit_s,
                        bag_dir, stop_when_fallen and mode == "inprocess")


def _worker_info(executor: str) -> dict:
    rss, _ = rss_mb(os.getpid())
    return {"host": socket.gethostname(), "worker_pid": os.getpid(), "worker_rss_mb": rss, "executor": executor}


class LocalExecutor:
    name = "local"

    def __init__(self, workers: int, log_dir: str | None = None):
        self.workers = max(1, int(workers))
        self.log_dir = log_dir or tempfile.mkdtemp(prefix="humfall-campaign-logs-")
        self.todo: queue.Queue = queue.Queue()
        self.done: queue.Queue = queue.Queue()
        self.stop = threading.Event()
        self.servers = [TrialServer(self.log_dir) for _ in range(self.workers)]
        self.pending = 0
        self.threads = [threading.Thread(target=self._loop, args=(s,), daemon=True) for s in self.servers]
        for t in self.threads:
            t.start()

    @property
    def capacity(self) -> int:
        return 2 * self.workers

    def _loop(self, server: TrialServer) -> None:
        while not self.stop.is_set():
            try:
                trial, req = self.todo.get(timeout=0.2)
            except queue.Empty:
                continue
            try:
                out = server.run(req)
            except Exception as e:  # noqa: BLE001 - a server that cannot start is a failed trial
                out = {"status": "crashed", "metrics": {}, "error": f"{type(e).__name__}: {e}", "log_tail": None}
            if not self.stop.is_set():
                self.done.put((trial, {**out, **_worker_info(self.name)}))

    def submit(self, trial: Trial, req: TrialRequest) -> None:
        self.pending += 1
        self.todo.put((trial, req))

    def in_flight(self) -> int:
        return self.pending

    def completed(self, timeout: float) -> list[tuple[Trial, dict]]:
        out = []
        try:
            out.append(self.done.get(timeout=timeout))
            while True:
                out.append(self.done.get_nowait())
        except queue.Empty:
            pass
        self.pending -= len(out)
        return out

    def shutdown(self) -> None:
        self.stop.set()
        for s in self.servers:
            s.kill()
        for t in self.threads:
            t.join(5.0)
        for s in self.servers:  # a thread may have restarted its server while we killed it
            s.kill()


_SERVER: TrialServer | None = None   # one per Ray worker process, kept across its tasks


def _ray_task(req: dict, log_dir: str | None) -> dict:
    global _SERVER
    if _SERVER is None:
        _SERVER = TrialServer(log_dir if log_dir and pathlib.Path(log_dir).is_dir() else None)
    return {**_SERVER.run(TrialRequest(**req)), **_worker_info("ray")}


class RayExecutor:
    name = "ray"

    def __init__(self, address: str | None, workers: int | None, log_dir: str | None = None,
                 cpus_per_trial: float = 1.0):
        import ray

        self.ray = ray
        self.log_dir = log_dir
        pkg_root = str(pathlib.Path(__file__).resolve().parents[2])
        env = {"PYTHONPATH": os.pathsep.join(x for x in (pkg_root, os.environ.get("PYTHONPATH", "")) if x)}
        if os.environ.get(TAG_ENV):
            env[TAG_ENV] = os.environ[TAG_ENV]
        os.environ.setdefault("RAY_DEDUP_LOGS", "0")
        kwargs = {"include_dashboard": False, "log_to_driver": False, "logging_level": "ERROR",
                  "runtime_env": {"env_vars": env}}
        self.owns_cluster = address is None
        if self.owns_cluster:
            kwargs["num_cpus"] = int(workers or os.cpu_count() or 1)
            ray.init(**kwargs)
        else:
            ray.init(address=address, **kwargs)
        self.workers = int(workers or ray.cluster_resources().get("CPU", 1) // cpus_per_trial)
        self.remote = ray.remote(num_cpus=cpus_per_trial, max_retries=0)(_ray_task)
        self.refs: dict = {}

    @property
    def capacity(self) -> int:
        return 2 * self.workers

    def submit(self, trial: Trial, req: TrialRequest) -> None:
        self.refs[self.remote.remote(dataclasses.asdict(req), self.log_dir)] = trial

    def in_flight(self) -> int:
        return len(self.refs)

    def completed(self, timeout: float) -> list[tuple[Trial, dict]]:
        if not self.refs:
            time.sleep(min(timeout, 0.05))
            return []
        ready, _ = self.ray.wait(list(self.refs), num_returns=1, timeout=timeout)
        if ready:
            ready, _ = self.ray.wait(list(self.refs), num_returns=len(self.refs), timeout=0)
        out = []
        for ref in ready:
            trial = self.refs.pop(ref)
            try:
                res = self.ray.get(ref)
            except Exception as e:  # noqa: BLE001 - a dead worker is a crashed trial, recorded
                res = {"status": "crashed", "metrics": {}, "error": f"{type(e).__name__}: {e}"[:4000],
                       "log_tail": None, "executor": self.name}
            out.append((trial, res))
        return out

    def shutdown(self) -> None:
        for ref in list(self.refs):
            with contextlib.suppress(Exception):  # already finished or gone
                self.ray.cancel(ref, force=True)
        self.refs.clear()
        self.ray.shutdown()
