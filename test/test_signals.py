"""Every executable of setup.py stops on SIGTERM and on SIGINT within 2 s, with exit code 0
and its files closed (the recorder's bag is finalized)."""
import ast
import signal
import subprocess
import sys
import time

import pytest

from conftest import REPO

STOP_WITHIN_S = 2.0


def executables() -> list[str]:
    tree = ast.parse((REPO / "setup.py").read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.Assign) and any(getattr(t, "id", None) == "NODES" for t in node.targets):
            return [ast.literal_eval(e) for e in node.value.elts]
    raise AssertionError("setup.py has no NODES list")


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_every_node_stops_cleanly_and_quickly(ros_env, tmp_path, sig):
    nodes = executables()
    assert {"sim_bridge", "state_estimator", "locomotion", "recorder", "multicontact_planner"} <= set(nodes)
    procs = {}
    for n in nodes:
        log = open(tmp_path / f"{n}.log", "wb")
        cmd = [sys.executable, "-m", f"humfall_ros.nodes.{n}", "--ros-args", "-p", f"output_dir:={tmp_path / 'bag'}"] \
            if n == "recorder" else [sys.executable, "-m", f"humfall_ros.nodes.{n}"]
        procs[n] = (subprocess.Popen(cmd, env=ros_env, stdout=log, stderr=subprocess.STDOUT), log)
    try:
        # up: each has logged a line, the planner its last start-up line (a signal during a
        # constructor is only seen once the constructor returns, which is not what is measured)
        ready = {"multicontact_planner": b"warm-up:"}  # idle after its warm-up: the case that hung
        deadline = time.monotonic() + 90
        while time.monotonic() < deadline:
            logs = {n: (tmp_path / f"{n}.log").read_bytes() for n in nodes}
            if all(logs[n].count(b"\n") >= 1 and ready.get(n, b"") in logs[n] for n in nodes):
                break
            time.sleep(0.2)
        time.sleep(1.0)
        for n, (p, _) in procs.items():
            assert p.poll() is None, (n, (tmp_path / f"{n}.log").read_text())
        took = {}
        for n, (p, _) in procs.items():
            t0 = time.monotonic()
            p.send_signal(sig)
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                pass
            took[n] = (time.monotonic() - t0, p.returncode)
        print({n: (round(t, 2), c) for n, (t, c) in took.items()})
        for n, (t, code) in took.items():
            assert code == 0, (n, code, (tmp_path / f"{n}.log").read_text()[-2000:])
            assert t <= STOP_WITHIN_S, (n, t)
        from mcap.reader import make_reader

        with open(tmp_path / "bag" / "bag.mcap", "rb") as f:
            assert make_reader(f).get_summary() is not None  # finalized: summary and footer written
    finally:
        for p, log in procs.values():
            if p.poll() is None:
                p.kill()
                p.wait()
            log.close()
