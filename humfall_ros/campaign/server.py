"""One trial at a time in an isolated, killable process (the "trial server").

A worker (a Ray task's process, or a thread of the local pool) owns one
:class:`TrialServer`: a child Python process started once (imports paid once),
that runs trials sent over a socket and answers with their metrics. The worker
waits at most the trial's time limit; a trial that hangs is killed with its server
(and anything the server started, found by an environment tag) and recorded as
``timeout``; a server that dies (segfault, OOM) is recorded as ``crashed``; an
exception in the trial as ``failed`` with its traceback. Each keeps the tail of
the server's log. The server leaves by itself when its worker dies (it watches
its parent), so killing a worker never leaves a simulation behind.

In-process trials run ``humfall_ros.sim.closed_loop.run_scenario``; graph trials
run ``humfall_ros.launch.up`` (one process per node) in a ROS domain the server
holds a lock on for the trial.
"""
from __future__ import annotations

import dataclasses
import fcntl
import json
import os
import pathlib
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import traceback
import uuid
from multiprocessing.connection import Connection

import numpy as np

TAG_ENV = "HUMFALL_CAMPAIGN_TAG"          # set on every process of a campaign (the driver's tag)
SERVER_TAG_ENV = "HUMFALL_TRIAL_SERVER"   # set on a server and everything it starts
STARTUP_TIMEOUT_S = 180.0
GRAPH_STOP_GRACE_S = 15.0                 # launch.up stops its nodes on SIGINT within this
LOG_TAIL_LINES = 40
SERVER_MAIN = "import sys; from humfall_ros.campaign.server import serve; serve(int(sys.argv[1]), int(sys.argv[2]))"


@dataclasses.dataclass
class TrialRequest:
    trial_id: str
    base_scenario: str
    overrides: list[str]
    mode: str                 # "inprocess" | "graph"
    time_limit_s: float
    bag_dir: str | None       # write the trial's recording here (None: no recording)
    stop_when_fallen: bool = False


STOP_AFTER_LANDING_S = 0.2    # simulated time kept after the trunk meets the ground [s]
STOP_AFTER_FALL_S = 1.0       # ... or after the fall, if nothing but the feet touches down [s]


# ---------------------------------------------------------------------------- process helpers
def tagged_pids(name: str, value: str) -> list[int]:
    """PIDs of this user's processes whose environment has ``name=value`` (Linux /proc)."""
    needle = f"{name}={value}".encode()
    out = []
    for d in pathlib.Path("/proc").iterdir():
        if not d.name.isdigit() or int(d.name) == os.getpid():
            continue
        try:
            if needle in (d / "environ").read_bytes().split(b"\0"):
                out.append(int(d.name))
        except OSError:
            continue
    return out


def rss_mb(pid: int) -> tuple[float | None, float | None]:
    """(resident, peak resident) memory of a process [MB], from /proc/PID/status."""
    vals = {}
    try:
        for line in pathlib.Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith(("VmRSS:", "VmHWM:")):
                k, v = line.split(":", 1)
                vals[k] = float(v.split()[0]) / 1024.0
    except OSError:
        pass
    return vals.get("VmRSS"), vals.get("VmHWM")


def _log_tail(path: pathlib.Path, offset: int, n: int = LOG_TAIL_LINES) -> str:
    try:
        with open(path, "rb") as f:
            f.seek(offset)
            text = f.read().decode(errors="replace")
    except OSError:
        return ""
    return "\n".join(text.splitlines()[-n:])


class DomainLock:
    """A ROS_DOMAIN_ID (1..101) held exclusively on this machine for one graph trial (flock)."""

    def __init__(self, lock_dir: str | None = None):
        self.lock_dir = pathlib.Path(lock_dir or tempfile.gettempdir()) / "humfall-domains"
        self.lock_dir.mkdir(parents=True, exist_ok=True)
        self.fd = None
        self.domain = None

    def __enter__(self) -> int:
        start = os.getpid() % 101
        for k in range(101):
            d = 1 + (start + k) % 101
            fd = os.open(self.lock_dir / f"{d}.lock", os.O_CREAT | os.O_RDWR, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                os.close(fd)
                continue
            self.fd, self.domain = fd, d
            return d
        raise RuntimeError("no free ROS_DOMAIN_ID (1..101) on this machine")

    def __exit__(self, *exc) -> None:
        if self.fd is not None:
            os.close(self.fd)  # releases the flock
        self.fd = None


# ---------------------------------------------------------------------------- the trial itself (server side)
def run_inprocess(req: TrialRequest) -> dict:
    """The closed loop without ROS; returns the metrics dict of its LoopResult."""
    import inspect

    from humfall_ros.campaign.design import build_scenario
    from humfall_ros.sim.closed_loop import run_scenario

    sc = build_scenario(req.base_scenario, req.overrides)
    if req.stop_when_fallen:
        result = _run_until_fallen(sc)
    else:
        kwargs = {}
        if "trunk_tilt_limit_deg" in inspect.signature(run_scenario).parameters:
            kwargs["trunk_tilt_limit_deg"] = 0.0  # no estimator-vs-truth comparison: not a campaign metric
        result = run_scenario(sc, **kwargs)
    if req.bag_dir:
        pathlib.Path(req.bag_dir).mkdir(parents=True, exist_ok=True)
        np.savez_compressed(pathlib.Path(req.bag_dir) / f"{req.trial_id}.npz",
                            joint_positions=np.asarray(result.joint_positions))
    m = dict(result.metrics)
    m.setdefault("sim_duration_s", m.get("stopped_early_at_s") or float(sc["duration"]))
    return m


def _run_until_fallen(sc: dict):
    """The closed loop (ClosedLoop, the engine of run_scenario) stopped once the fall is decided."""
    from humfall_ros.sim.closed_loop import ClosedLoop, LoopResult

    loop = ClosedLoop(sc)
    try:
        m = loop.ground_truth.metrics
        ticks = int(round(sc["duration"] * sc["sim"]["control_rate"]))
        stopped = None
        for _ in range(ticks):
            loop.step()
            t = loop.world.time
            if m.fell and ((m.landing_time is not None and t >= m.landing_time + STOP_AFTER_LANDING_S)
                           or t >= m.fall_time + STOP_AFTER_FALL_S):
                stopped = t
                break
        r = loop.metrics()
        r["stopped_early_at_s"] = stopped
        return LoopResult(r, np.array(loop.joint_positions), {}, r["max_trunk_tilt_deg"])
    finally:
        loop.close()


def run_graph(req: TrialRequest) -> dict:
    """The trial as ``humfall up`` in a ROS domain of its own; returns the bridge's metrics.

    Without a ``bag_dir`` nothing is recorded and the run's folder (its result.json, read here) is a
    temporary one, removed with the trial: a server used to keep one folder per start in /tmp for good
    (hundreds after a test session)."""
    from humfall_ros import launch

    scratch_dir = tempfile.TemporaryDirectory(prefix="humfall-campaign-run-", ignore_cleanup_errors=True)
    with DomainLock() as domain, scratch_dir as scratch:
        os.environ["ROS_DOMAIN_ID"] = str(domain)
        os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
        print(f"[campaign] trial {req.trial_id} in ROS_DOMAIN_ID={domain}", flush=True)
        status, result = launch.up(req.base_scenario, None, list(req.overrides), runs_dir=req.bag_dir or scratch,
                                   record=bool(req.bag_dir), plots=False, quiet=False,
                                   timeout=req.time_limit_s + 60.0)  # the worker's limit governs
    if status != 0:
        raise RuntimeError(f"humfall up exited with status {status}")
    m = dict(result.get("metrics") or {})
    m["graph_wall_time_s"] = result.get("wall_time_s")
    if result.get("bag"):
        m["bag"] = result["bag"]
    return m


def _watch_parent(parent: int, graph: dict) -> None:
    """Leave when the worker that started us is gone (so no simulation outlives its campaign)."""
    while True:
        time.sleep(0.5)
        if os.getppid() != parent:
            if graph["on"]:  # let launch.up stop its nodes (it handles SIGINT), then go
                os.kill(os.getpid(), signal.SIGINT)
                time.sleep(GRAPH_STOP_GRACE_S)
            os._exit(3)


def serve(fd: int, parent: int) -> None:
    """Server main loop: receive TrialRequest dicts, answer {status, metrics, error, cpu_s, wall_s}."""
    conn = Connection(fd)
    graph_mode = {"on": False}
    threading.Thread(target=_watch_parent, args=(parent, graph_mode), daemon=True).start()
    signal.signal(signal.SIGINT, signal.SIG_IGN)   # a terminal's Ctrl-C is the driver's business
    # pay the imports once, before the first trial's clock starts
    import humfall_ros.campaign.design
    import humfall_ros.sim.closed_loop  # noqa: F401
    from humfall_ros.model.humanoid import load_model

    load_model()
    conn.send({"ready": os.getpid()})
    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            break
        if msg is None:
            break
        req = TrialRequest(**msg)
        t0, c0 = time.monotonic(), os.times()
        out = {"status": "ok", "metrics": {}, "error": None}
        try:
            print(f"[campaign] start {req.trial_id}: {req.base_scenario} {' '.join(req.overrides)}", flush=True)
            if req.mode == "graph":
                graph_mode["on"] = True
                signal.signal(signal.SIGINT, signal.default_int_handler)  # launch.up installs its own
                out["metrics"] = run_graph(req)
                signal.signal(signal.SIGINT, signal.SIG_IGN)
            else:
                out["metrics"] = run_inprocess(req)
        except BaseException as e:  # noqa: BLE001 - every failure is a recorded trial
            out["status"] = "failed"
            out["error"] = f"{type(e).__name__}: {e}"
            traceback.print_exc()
            sys.stdout.flush()
        c1 = os.times()
        out["wall_s"] = time.monotonic() - t0
        out["cpu_s"] = (c1.user - c0.user) + (c1.system - c0.system) + \
            (c1.children_user - c0.children_user) + (c1.children_system - c0.children_system)
        print(f"[campaign] end {req.trial_id}: {out['status']}", flush=True)
        conn.send(json.loads(json.dumps(out, default=float)))


# ---------------------------------------------------------------------------- the worker side
class TrialServer:
    """Parent side of a trial server: start it, send a trial, wait at most its time limit."""

    def __init__(self, log_dir: str | None = None):
        self.log_dir = pathlib.Path(log_dir or tempfile.mkdtemp(prefix="humfall-campaign-logs-"))
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.proc: subprocess.Popen | None = None
        self.conn: Connection | None = None
        self.tag = ""
        self.log_path = self.log_dir / "server.log"

    def _start(self) -> None:
        self.tag = uuid.uuid4().hex
        self.log_path = self.log_dir / f"server-{os.getpid()}-{self.tag[:8]}.log"
        ours, theirs = socket.socketpair()
        env = dict(os.environ)
        env[SERVER_TAG_ENV] = self.tag
        env["PYTHONUNBUFFERED"] = "1"
        env["MPLBACKEND"] = "Agg"
        pkg_root = str(pathlib.Path(__file__).resolve().parents[2])
        env["PYTHONPATH"] = os.pathsep.join(x for x in (pkg_root, env.get("PYTHONPATH", "")) if x)
        with open(self.log_path, "ab") as log:
            self.proc = subprocess.Popen(
                [sys.executable, "-c", SERVER_MAIN, str(theirs.fileno()), str(os.getpid())],
                pass_fds=[theirs.fileno()], stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env)
        theirs.close()
        self.conn = Connection(ours.detach())
        if not self.conn.poll(STARTUP_TIMEOUT_S):
            tail = _log_tail(self.log_path, 0)
            self.kill()
            raise RuntimeError(f"trial server did not start in {STARTUP_TIMEOUT_S:.0f} s:\n{tail}")
        try:
            self.conn.recv()
        except EOFError:
            tail = _log_tail(self.log_path, 0)
            self.kill()
            raise RuntimeError(f"trial server died on start:\n{tail}") from None

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def kill(self, graceful: bool = False) -> None:
        """Stop the server and everything it started (found by its tag)."""
        if self.proc is not None and self.proc.poll() is None:
            if graceful:  # graph mode: launch.up stops its nodes on SIGINT; the closed socket then ends the server
                self._close_conn()
                self.proc.send_signal(signal.SIGINT)
                try:
                    self.proc.wait(GRAPH_STOP_GRACE_S)
                except subprocess.TimeoutExpired:
                    pass
            self.proc.kill()
            self.proc.wait()
        if self.tag:
            for pid in tagged_pids(SERVER_TAG_ENV, self.tag):
                try:
                    os.kill(pid, signal.SIGKILL)
                except OSError:
                    pass
        self._close_conn()
        self.proc = None

    def _close_conn(self) -> None:
        # taken first, closed once, an already closed handle ignored: on Ctrl-C the runner's shutdown closed a
        # handle that was no longer open (EBADF; once in a fresh-clone make test, likely a kill() re-entered from
        # the interrupt) and the campaign exited 1 instead of 130
        conn, self.conn = self.conn, None
        if conn is not None:
            try:
                conn.close()
            except OSError:
                pass

    def close(self) -> None:
        if self.alive():
            try:
                self.conn.send(None)
                self.proc.wait(5.0)
            except (OSError, subprocess.TimeoutExpired):
                pass
        self.kill()

    def run(self, req: TrialRequest) -> dict:
        """{status: ok|failed|timeout|crashed, metrics, error, log_tail, wall_s, cpu_s, server_* ...}."""
        if not self.alive():
            self._start()
        offset = self.log_path.stat().st_size if self.log_path.exists() else 0
        started = time.time()
        t0 = time.monotonic()
        self.conn.send(dataclasses.asdict(req))
        out = None
        if self.conn.poll(req.time_limit_s):
            try:
                out = self.conn.recv()
            except (EOFError, OSError):
                out = None
            if out is None:
                code = self.proc.wait(10.0) if self.proc else None
                out = {"status": "crashed", "metrics": {},
                       "error": f"trial server died (exit status {code})"}
                self.kill()
        else:
            out = {"status": "timeout", "metrics": {},
                   "error": f"killed at the per-trial time limit of {req.time_limit_s:g} s"}
        pid = self.proc.pid if self.proc else None
        rss, hwm = rss_mb(pid) if pid else (None, None)
        if out["status"] == "timeout":
            self.kill(graceful=req.mode == "graph")
        out.setdefault("wall_s", time.monotonic() - t0)
        out.setdefault("cpu_s", None)
        out["log_tail"] = _log_tail(self.log_path, offset) if out["status"] != "ok" else None
        out["started_unix"] = started
        out["finished_unix"] = time.time()
        out["server_pid"] = pid
        out["server_rss_mb"], out["server_hwm_mb"] = rss, hwm
        return out
