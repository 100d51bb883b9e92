"""multicontact_planner as a real process: the plan_fall service answers a valid
and an invalid request, keeps serving, and the CLI client prints JSON."""
from __future__ import annotations

import contextlib
import json
import pathlib
import subprocess
import sys
import time

import pytest

from conftest import python_node_cmd


@contextlib.contextmanager
def planner_node(ros_env, *params: str):
    """The planner node as a process (no warm-up), with ``name:=value`` parameters; stopped after."""
    cmd = python_node_cmd("humfall_ros.nodes.multicontact_planner", "--ros-args", "-p", "warm_up:=false",
                          *[x for p in params for x in ("-p", p)])
    proc = subprocess.Popen(cmd, env=ros_env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        yield proc
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


@pytest.fixture
def planner_process(ros_env):
    with planner_node(ros_env) as proc:
        yield proc


def test_plan_fall_service_valid_and_invalid(planner_process, in_ros_domain, tmp_path):
    import rclpy
    from humfall_interfaces.srv import PlanFall

    rclpy.init()
    node = rclpy.create_node("test_plan_fall_client")
    try:
        client = node.create_client(PlanFall, "plan_fall")
        assert client.wait_for_service(timeout_sec=30.0), "plan_fall service did not appear"

        def call(req, timeout=90.0):
            fut = client.call_async(req)
            t0 = time.monotonic()
            while not fut.done() and time.monotonic() - t0 < timeout:
                rclpy.spin_until_future_complete(node, fut, timeout_sec=0.5)
            assert fut.done(), "no answer"
            return fut.result()

        bad = PlanFall.Request()
        bad.kinetic_energy = float("nan")
        r = call(bad)
        assert not r.success and "not a finite" in r.reason and r.nlp_count == 0

        bad_len = PlanFall.Request()
        bad_len.q = [0.0] * 4
        r = call(bad_len)
        assert not r.success and "q has 4 entries" in r.reason

        good = PlanFall.Request()
        good.kinetic_energy = 10.0
        good.direction = 1.0
        good.initial_mode = "LF/RF"
        good.time_budget = 60.0
        r = call(good)
        assert r.success, r.reason
        assert list(r.contact_sequence) == ["LF/RF"] and r.final_ke < 0.1
        assert len(r.segments) == 1 and r.nlp_count == len(r.nlp_times_s) == 1
        seg = r.segments[0]
        n = len(seg.coordinate_names)
        assert n == 13 and len(seg.actuated_names) == 10
        assert len(seg.q) == len(seg.time) * n and len(seg.u) == len(seg.time) * 10
        assert len(seg.contact_force) == len(seg.time) * 2 * 4  # toe + heel of two feet
        tree = json.loads(r.tree_json)
        assert tree["success"] and tree["nodes"][0]["mode"] == "LF/RF"
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    assert planner_process.poll() is None, "node died"

    # the CLI client against the same node: wrong mode name -> JSON with the reason, exit 1
    out = subprocess.run([sys.executable, "-c",
                          "import sys; from humfall_ros.nodes.plan_fall_client import main; "
                          "sys.exit(main(sys.argv[1:]))", "--ke", "20", "--mode", "LF/QQ", "--json"],
                         env=in_ros_domain, capture_output=True, text=True, timeout=60)
    assert out.returncode == 1, out.stderr
    d = json.loads(out.stdout)
    assert d["success"] is False and "unknown extremity 'QQ'" in d["reason"]
    for key in ("contact_sequence", "node_ke", "final_ke", "nlp_times_s", "total_time_s"):
        assert key in d

    # ... a plan with its figures: tree, stick figures and KE over time from the answer alone
    out = subprocess.run([sys.executable, "-c",
                          "import sys; from humfall_ros.nodes.plan_fall_client import main; "
                          "sys.exit(main(sys.argv[1:]))", "--ke", "10", "--json", "--plots", str(tmp_path)],
                         env=in_ros_domain, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stdout + out.stderr
    d = json.loads(out.stdout)
    assert d["success"] and d["contact_sequence"] == ["LF/RF"]
    # issue 14: the paper's objective, and a landing report list (empty: no contact added at 10 J)
    assert d["transition_objective"] == "pre_impact" and d["landings"] == [] and d["landings_within_limits"]
    names = sorted(pathlib.Path(f).name for f in d["plots"])
    assert names == ["plan_10J_ke.png", "plan_10J_sticks.png", "plan_10J_tree.png"]
    for f in d["plots"]:
        assert pathlib.Path(f).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_client_reports_missing_service(in_ros_domain):
    out = subprocess.run([sys.executable, "-c",
                          "import sys; from humfall_ros.nodes.plan_fall_client import main; "
                          "sys.exit(main(sys.argv[1:]))", "--ke", "20", "--wait", "1", "--json"],
                         env=in_ros_domain, capture_output=True, text=True, timeout=60)
    assert out.returncode == 2
    d = json.loads(out.stdout)
    assert d["success"] is False and "not available" in d["reason"]


def test_plan_fall_from_the_shipped_library(ros_env, in_ros_domain, tmp_path):
    """The node with ``library_file`` (the shipped library): a 21 J request is answered by a
    warm re-plan of the 21.25 J entry (no tree), a NaN request still gets its reason, the client prints
    the answer's figures (no tree figure), the node keeps serving, and a request beyond the library goes
    to the tree search with the library's reason in the node's log."""
    with planner_node(ros_env, "library_file:=multicontact_library/standing_pushes.json.gz") as proc:
        run = [sys.executable, "-c", "import sys; from humfall_ros.nodes.plan_fall_client import main; "
               "sys.exit(main(sys.argv[1:]))", "--wait", "60", "--json"]
        out = subprocess.run(run + ["--ke", "21", "--plots", str(tmp_path)], env=in_ros_domain,
                             capture_output=True, text=True, timeout=180)
        assert out.returncode == 0, out.stdout + out.stderr
        d = json.loads(out.stdout)
        assert d["success"] and "re-solved library plan for 21.25 J" in d["reason"], d["reason"]
        assert d["tree_nodes"] == 0 and d["final_ke"] < 0.1 and len(d["contact_sequence"]) >= 1
        assert d["nlp_count"] == len(d["nlp_times_s"]) == len(d["contact_sequence"])
        assert sorted(pathlib.Path(f).name for f in d["plots"]) == ["plan_21J_ke.png", "plan_21J_sticks.png"]
        out = subprocess.run(run + ["--ke", "nan"], env=in_ros_domain, capture_output=True, text=True, timeout=60)
        assert out.returncode == 1 and "not a finite" in json.loads(out.stdout)["reason"]
        # beyond the library: the tree search answers, and the node's log says why the library did not
        out = subprocess.run(run + ["--ke", "60", "--budget", "0.5"], env=in_ros_domain, capture_output=True,
                             text=True, timeout=90)
        assert json.loads(out.stdout)["tree_nodes"] >= 1, out.stdout
        # a plan for the 3-D robot (planner_profile "execution"): FOR_EXECUTION with its own library, not the node's
        # (planned with the declared margin); an unknown profile gets its reason
        out = subprocess.run(run + ["--ke", "21", "--profile", "execution", "--budget", "120"], env=in_ros_domain,
                             capture_output=True, text=True, timeout=240)
        d = json.loads(out.stdout)
        assert d["success"] and d["tree_nodes"] == 0, d["reason"]
        assert "re-solved library plan for 21.25 J" in d["reason"] and d["contact_sequence"] == ["LF/RF", "RF", "LF/RF"]
        out = subprocess.run(run + ["--ke", "21", "--profile", "bogus"], env=in_ros_domain, capture_output=True,
                             text=True, timeout=60)
        assert out.returncode == 1 and "unknown planner_profile 'bogus'" in json.loads(out.stdout)["reason"]
        assert proc.poll() is None, "node died"
        proc.terminate()
        log = proc.communicate(timeout=20)[0]
        assert "the library first: no library entry within 5 J of 60.0 J (nearest 50 J)" in log, log[-2000:]
    assert "profile=execution source=library" in log, log[-2000:]


def test_planner_node_refuses_an_unreadable_library(ros_env, tmp_path):
    """A ``library_file`` that cannot be used stops the node at start with exit code 2 and the reason."""
    (tmp_path / "lib.json").write_text('{"format": 99, "entries": []}')
    cmd = python_node_cmd("humfall_ros.nodes.multicontact_planner", "--ros-args", "-p", "warm_up:=false",
                          "-p", f"library_file:={tmp_path / 'lib.json'}")
    out = subprocess.run(cmd, env=ros_env, capture_output=True, text=True, timeout=60)
    assert out.returncode == 2, out.stdout + out.stderr
    assert "format 99, this code reads 1" in out.stdout + out.stderr


def test_the_client_summary_names_the_strategy():
    """``humfall plan-fall`` (human output) names the plan's strategy as the paper does, from the sequence alone."""
    from humfall_ros.nodes.plan_fall_client import summary

    d = {"success": True, "reason": "stabilised", "contact_sequence": ["RF", "LF/RF"], "node_ke": [40.0, 38.0],
         "final_ke": 1e-9, "segments": [], "landings": [], "nlp_times_s": [], "transition_objective": "pre_impact"}
    text = summary(d)
    assert "RF (40.0 J)  ->  LF/RF (38.0 J)  [protective step]" in text
    assert "[inertial shaping]" in summary({**d, "contact_sequence": ["LF/RF"], "node_ke": [10.0]})
