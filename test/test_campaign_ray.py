"""Campaigns on Ray and Ctrl-C (issue 13): the same table as a local run; no process left after SIGINT.

Each test starts a local Ray (about 10 s on this machine) or a campaign subprocess.
"""
from __future__ import annotations

import os
import pathlib
import signal
import subprocess
import sys
import time
import uuid

import pytest
import yaml

from humfall_ros.campaign import spec as spec_mod
from humfall_ros.campaign.runner import RunOptions, run_campaign
from humfall_ros.campaign.server import TAG_ENV, tagged_pids
from humfall_ros.campaign.store import comparable, load_results

ROOT = pathlib.Path(__file__).resolve().parents[1]


def spec_dict(out: pathlib.Path, n: int, duration: float) -> dict:
    return {"name": "ray_test", "base_scenario": "standing_push", "set": ["obstacles=[]", f"duration={duration}"],
            "design": {"random": {"n": n, "seed": 5, "keys": {"push.0.direction_deg": {"uniform": [0, 360]},
                                                              "push.0.magnitude_n": {"uniform": [150, 450]}}}},
            # generous: a time limit is not what these tests measure, and a loaded 2-core machine took a Ray worker's
            # first 1.5 s trial past 60 s (a fresh-clone run beside three simulations)
            "trial": {"time_limit_s": 300}, "output": {"dir": str(out)}}


def _cmdline(pid: int) -> str:
    try:
        return pathlib.Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""


def test_ray_table_identical_to_local_run(tmp_path):
    def spec(out):
        d = spec_dict(out, 1, 1.5)
        d["design"] = {"grid": {"push.0.direction_deg": [0.0, 200.0], "push.0.magnitude_n": [150.0, 500.0]}}
        return spec_mod.from_dict(d)

    a = run_campaign(spec(tmp_path / "local"), RunOptions(executor="local", workers=1, progress=False))
    b = run_campaign(spec(tmp_path / "ray"), RunOptions(executor="ray", workers=2, progress=False))
    ta, _ = load_results(a.results)
    tb, _ = load_results(b.results)
    assert set(tb.column("executor").to_pylist()) == {"ray"}
    assert set(ta.column("status").to_pylist()) == {"ok"}
    assert comparable(ta).equals(comparable(tb))
    assert any(ta.column("m.fell").to_pylist())     # the design has falls and recoveries: a real comparison
    assert not all(ta.column("m.fell").to_pylist())


@pytest.mark.parametrize("executor", ["local", "ray"])
def test_ctrl_c_leaves_no_process_and_resume_finishes(tmp_path, executor):
    out = tmp_path / "out"
    spec_path = tmp_path / "spec.yaml"
    spec_path.write_text(yaml.safe_dump(spec_dict(out, 12, 1.0)))
    tag = uuid.uuid4().hex
    env = {**os.environ, TAG_ENV: tag, "PYTHONPATH": str(ROOT)}
    cmd = [sys.executable, "-m", "humfall_ros.campaign.cli", str(spec_path), "--workers", "2", "--no-progress"]
    if executor == "local":
        cmd.append("--local")
    # the local run starts like a shell's background job, with SIGINT ignored: Ctrl-C must still stop it
    ignore_sigint = (lambda: signal.signal(signal.SIGINT, signal.SIG_IGN)) if executor == "local" else None
    p = subprocess.Popen(cmd, env=env, cwd=str(ROOT), start_new_session=True, preexec_fn=ignore_sigint,
                         stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 120
        while not list((out / "fragments").glob("part-*.parquet")):
            assert p.poll() is None, p.stdout.read().decode()
            assert time.monotonic() < deadline, "no trial finished in 120 s"
            time.sleep(0.2)
        running = tagged_pids(TAG_ENV, tag)
        names = " ".join(_cmdline(q) for q in running)
        assert "campaign.server" in names                      # trial servers carry the tag ...
        if executor == "ray":
            assert "raylet" in names and "gcs_server" in names  # ... and so do Ray's own processes
        os.killpg(p.pid, signal.SIGINT)                          # what a terminal's Ctrl-C does
        p.wait(60)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
    assert p.returncode == 130, p.stdout.read().decode()
    left = tagged_pids(TAG_ENV, tag)
    deadline = time.monotonic() + 10
    while left and time.monotonic() < deadline:
        time.sleep(0.5)
        left = tagged_pids(TAG_ENV, tag)
    assert left == [], [(q, _cmdline(q)) for q in left]

    stored, _ = load_results(out)
    finished = stored.num_rows
    assert 1 <= finished < 12
    s = run_campaign(spec_mod.load(spec_path), RunOptions(executor="local", workers=2, progress=False))
    assert s.resumed == finished and s.ran == 12 - finished
    table, _ = load_results(s.results)
    assert table.num_rows == 12 and len(set(table.column("trial_id").to_pylist())) == 12
