"""Shared test fixtures.

Multi-process tests start real nodes as real processes; each test gets its own
ROS_DOMAIN_ID (so concurrent graphs never see each other) and stays on
localhost (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST).
"""
from __future__ import annotations

import fcntl
import itertools
import os
import pathlib
import sys
import tempfile

import pytest

REPO = pathlib.Path(__file__).resolve().parents[1]
_domains = itertools.count((os.getpid() * 7) % 100)
_LOCK_DIR = pathlib.Path(tempfile.gettempdir()) / "humfall_ros_test_domains"


def claim_domain_id():
    """A ROS_DOMAIN_ID in 1..100 no other test on this machine holds, and its lock.

    Concurrent pytest runs (two checkouts, a developer and CI) would otherwise
    share domains and see each other's nodes; an flock per id keeps them apart
    and is released when the holder's file is closed (or the process dies).
    """
    _LOCK_DIR.mkdir(exist_ok=True)
    for _ in range(100):
        domain = 1 + next(_domains) % 100  # 0 is the default domain other tools use
        f = open(_LOCK_DIR / f"{domain}.lock", "w")
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return domain, f
        except OSError:
            f.close()
    raise RuntimeError("no free ROS domain id for the test")


@pytest.fixture
def ros_env(tmp_path):
    """Environment for child node processes: own domain, localhost only, a log dir."""
    domain, lock = claim_domain_id()
    env = dict(os.environ)
    env["ROS_DOMAIN_ID"] = str(domain)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env["RMW_IMPLEMENTATION"] = "rmw_fastrtps_cpp"
    env["ROS_LOG_DIR"] = str(tmp_path / "ros_log")
    env.setdefault("HOME", str(tmp_path))
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")])
    env["PYTHONUNBUFFERED"] = "1"
    env["MPLBACKEND"] = "Agg"
    yield env
    lock.close()


@pytest.fixture
def in_ros_domain(ros_env, monkeypatch):
    """Put this test process itself in the test's domain (for in-process rclpy clients)."""
    for k in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_LOG_DIR"):
        monkeypatch.setenv(k, ros_env[k])
    return ros_env


def python_node_cmd(module: str, *args: str) -> list[str]:
    """Command line that runs a node module with this interpreter."""
    return [sys.executable, "-m", module, *args]
