"""Campaign trials over the ROS graph (``--graph``): each trial is ``humfall up`` in a ROS domain of its own.

The identity test: joint states identical in process and over ROS on trials sampled from a
built-in campaign (the in-process loop runs the same controllers through the same mux as the
graph): 3 of the 1,000 standing pushes and 1 safe-fall trial of the avoidance map by default,
``HUMFALL_IDENTITY_TRIALS=10`` for the issue's 10 (each graph trial is a whole ``humfall up``).
"""
from __future__ import annotations

import os
import pathlib
import tempfile
import time

import numpy as np
import pytest

from humfall_ros.campaign import spec as spec_mod
from humfall_ros.campaign.runner import RunOptions, prepare, run_campaign
from humfall_ros.campaign.server import TAG_ENV, DomainLock, TrialRequest, TrialServer, tagged_pids
from humfall_ros.campaign.store import load_results

IDENTITY_TRIALS = int(os.environ.get("HUMFALL_IDENTITY_TRIALS", "3"))


def test_domain_locks_are_exclusive(tmp_path):
    with DomainLock(str(tmp_path)) as a, DomainLock(str(tmp_path)) as b:
        assert a != b and 1 <= a <= 101 and 1 <= b <= 101
    with DomainLock(str(tmp_path)) as c:
        assert 1 <= c <= 101


def test_graph_trial_runs_in_its_own_domain(tmp_path, monkeypatch):
    monkeypatch.setenv(TAG_ENV, "graph-test-" + tmp_path.name)
    scratch = pathlib.Path(tempfile.gettempdir())
    before = set(scratch.glob("humfall-campaign-run*"))
    d = {"name": "graph_smoke", "base_scenario": "standing_push", "set": ["obstacles=[]", "duration=0.6"],
         "design": {"grid": {"push.0.magnitude_n": [80.0]}}, "trial": {"time_limit_s": 120},
         "output": {"dir": str(tmp_path / "out")}}
    s = run_campaign(spec_mod.from_dict(d), RunOptions(executor="local", workers=1, mode="graph", progress=False))
    table, _ = load_results(s.results)
    (row,) = table.to_pylist()
    assert row["status"] == "ok", (row["error"], row["log_tail"])
    assert row["mode"] == "graph" and row["m.fell"] is False
    assert row["m.ticks"] == 300                  # the bridge ran 0.6 s at 500 Hz
    assert tagged_pids(TAG_ENV, os.environ[TAG_ENV]) == []
    # the unrecorded run's folder goes with its trial (a server used to leave one in /tmp per start)
    assert set(scratch.glob("humfall-campaign-run*")) - before == set()


def _bag_joint_positions(bag: str) -> np.ndarray:
    from mcap_ros2.reader import read_ros2_messages

    rows = {}
    for m in read_ros2_messages(bag, topics=["/joint_states"]):
        st = m.ros_msg.header.stamp
        rows.setdefault((st.sec, st.nanosec), tuple(m.ros_msg.position))
    return np.array([rows[k] for k in sorted(rows)])


@pytest.mark.parametrize(("campaign", "n", "extra"), [
    ("standing_push_1000", IDENTITY_TRIALS, ["duration=1.5"]),
    ("avoidance_map", 1, ["duration=2.0"]),     # the FTB, the safe-fall controller and the target layout too
])
def test_inprocess_and_graph_give_identical_joint_states_on_sampled_trials(tmp_path, campaign, n, extra):
    spec = spec_mod.load(campaign)
    spec = spec.model_copy(update={"set": [*spec.set, *extra]})
    _, _, study, _ = prepare(spec, RunOptions())
    picks = np.random.default_rng(13).choice(study.total, n, replace=False)
    server = TrialServer(str(tmp_path / "logs"))
    try:
        for i in picks:
            t = study.trials[int(i)]
            a = server.run(TrialRequest(t.trial_id, t.base_scenario, list(t.overrides), "inprocess", 120.0,
                                        str(tmp_path / "inproc")))
            b = server.run(TrialRequest(t.trial_id, t.base_scenario, list(t.overrides), "graph", 300.0,
                                        str(tmp_path / "graph")))
            assert a["status"] == b["status"] == "ok", (a["error"], b["error"], b["log_tail"])
            q_in = np.load(tmp_path / "inproc" / f"{t.trial_id}.npz")["joint_positions"]
            q_ros = _bag_joint_positions(b["metrics"]["bag"])
            assert len(q_ros) >= len(q_in)
            np.testing.assert_array_equal(q_ros[: len(q_in)], q_in, err_msg=t.trial_id)
            assert a["metrics"]["fell"] == b["metrics"]["fell"]
    finally:
        server.close()


def test_hung_graph_trial_is_killed_with_its_nodes(tmp_path, monkeypatch):
    tag = "graph-timeout-" + tmp_path.name
    monkeypatch.setenv(TAG_ENV, tag)
    s = TrialServer(str(tmp_path))
    try:
        t0 = time.monotonic()
        r = s.run(TrialRequest("slow", "standing_push", ["obstacles=[]", "duration=600"], "graph", 8.0, None))
        assert r["status"] == "timeout" and "time limit" in r["error"]
        assert "sim_bridge" in r["log_tail"]           # the log shows the nodes it started
        assert time.monotonic() - t0 < 8.0 + 30.0
    finally:
        s.close()
    deadline = time.monotonic() + 10
    while tagged_pids(TAG_ENV, tag) and time.monotonic() < deadline:
        time.sleep(0.5)
    assert tagged_pids(TAG_ENV, tag) == []
