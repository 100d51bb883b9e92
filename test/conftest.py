"""Shared test fixtures.

Multi-process tests start real nodes as real processes; each test gets its own
ROS_DOMAIN_ID (so concurrent graphs never see each other) and stays on
localhost (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST).
"""
from __future__ import annotations

import itertools
import os
import pathlib
import sys

import pytest

REPO = pathlib.Path(__file__).resolve().parents[1]
_domains = itertools.count((os.getpid() * 7) % 90)


def next_domain_id() -> int:
    # 1..100: 0 is the default domain that other tools on the machine use.
    return 1 + next(_domains) % 100


@pytest.fixture
def ros_env(tmp_path):
    """Environment for child node processes: own domain, localhost only, a log dir."""
    env = dict(os.environ)
    env["ROS_DOMAIN_ID"] = str(next_domain_id())
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env["RMW_IMPLEMENTATION"] = "rmw_fastrtps_cpp"
    env["ROS_LOG_DIR"] = str(tmp_path / "ros_log")
    env.setdefault("HOME", str(tmp_path))
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")])
    env["PYTHONUNBUFFERED"] = "1"
    env["MPLBACKEND"] = "Agg"
    return env


@pytest.fixture
def in_ros_domain(ros_env, monkeypatch):
    """Put this test process itself in the test's domain (for in-process rclpy clients)."""
    for k in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_LOG_DIR"):
        monkeypatch.setenv(k, ros_env[k])
    return ros_env


def python_node_cmd(module: str, *args: str) -> list[str]:
    """Command line that runs a node module with this interpreter."""
    return [sys.executable, "-m", module, *args]
