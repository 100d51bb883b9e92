"""Campaigns (issue 13): spec validation, designs, bisection, store/resume, timeouts, report. No ROS, no Ray."""
from __future__ import annotations

import json
import math
import pathlib
import time

import pyarrow as pa
import pyarrow.compute  # noqa: F401 - pa.compute
import pytest
import yaml

from humfall_ros import scenario as scenario_mod
from humfall_ros.campaign import cli, design
from humfall_ros.campaign import spec as spec_mod
from humfall_ros.campaign.report import thresholds, write_report
from humfall_ros.campaign.runner import RunOptions, make_row, prepare, run_campaign
from humfall_ros.campaign.server import SERVER_TAG_ENV, TrialRequest, TrialServer, tagged_pids
from humfall_ros.campaign.store import ResultStore, ResumeError, load_results
from humfall_ros.campaign.studies import ThresholdMap


def tiny(tmp_path, **over) -> dict:
    d = {"name": "tiny", "base_scenario": "standing_push", "set": ["obstacles=[]", "duration=0.3"],
         "design": {"grid": {"push.0.direction_deg": [0.0, 90.0], "push.0.magnitude_n": [50.0]}},
         "trial": {"time_limit_s": 60}, "output": {"dir": str(tmp_path / "out")}}
    d.update(over)
    return d


def write_spec(tmp_path, d, name="spec.yaml"):
    p = tmp_path / name
    p.write_text(yaml.safe_dump(d))
    return str(p)


# ---------------------------------------------------------------------------- spec refusals
@pytest.mark.parametrize("change, path", [
    ({"colour": "red"}, "colour"),
    ({"design": {"grid": {"push.0.time": [1.0]}, "bogus": 1}}, "design.bogus"),
    ({"study": {"type": "threshold-map", "low": 1, "high": 2, "tolerence": 5}}, "study.tolerence"),
    ({"trial": {"time_limit": 3}}, "trial.time_limit"),
])
def test_unknown_key_refused_with_dotted_path(tmp_path, change, path):
    with pytest.raises(spec_mod.CampaignSpecError) as e:
        spec_mod.from_dict(tiny(tmp_path, **change))
    assert str(e.value).startswith(f"{path}: unknown key"), str(e.value)


@pytest.mark.parametrize("des", [
    {"grid": {}},
    {"grid": {"push.0.direction_deg": []}},
    {"grid": {"push.0.direction_deg": {"linspace": [0, 1, 0]}}},
    {"random": {"n": 0, "keys": {"push.0.time": {"uniform": [0, 1]}}}},
    {"random": {"n": 5, "keys": {}}},
    {},
])
def test_empty_design_refused(tmp_path, des):
    with pytest.raises(spec_mod.CampaignSpecError) as e:
        spec_mod.from_dict(tiny(tmp_path, design=des))
    assert str(e.value).startswith("design"), str(e.value)


def test_bad_scenario_key_refused_before_anything_starts(tmp_path):
    d = tiny(tmp_path, design={"grid": {"push.0.forse": [[1, 2, 3]]}})
    assert cli.main([write_spec(tmp_path, d), "--local"]) == 2
    assert not (tmp_path / "out").exists()
    with pytest.raises(spec_mod.CampaignSpecError, match=r"^design\.grid\.push\.0\.forse: .*no such key"):
        prepare(spec_mod.from_dict(d), RunOptions())
    # a value the scenario refuses (a 9 kN push) is caught by the sampled check, also before running
    d = tiny(tmp_path, design={"grid": {"push.0.magnitude_n": [100.0, 9000.0]}})
    with pytest.raises(spec_mod.CampaignSpecError, match=r"^design\.grid.*exceeds"):
        prepare(spec_mod.from_dict(d), RunOptions())
    d = tiny(tmp_path, study={"type": "threshold-map", "key": "push.3.magnitude_n", "low": 100, "high": 300})
    with pytest.raises(spec_mod.CampaignSpecError, match=r"^study\.key"):
        prepare(spec_mod.from_dict(d), RunOptions())


# ---------------------------------------------------------------------------- designs
def test_push_keys_become_force_and_point():
    base = scenario_mod.load("standing_push")
    ov = design.overrides_for({"push.0.direction_deg": 90.0, "push.0.magnitude_n": 200.0,
                               "push.0.height_m": 0.3, "duration": 1.0}, base)
    sc = base
    for o in ov:
        sc = scenario_mod.apply_override(sc, o)
    f = sc["push"][0]["force"]
    assert f[0] == pytest.approx(0.0, abs=1e-6) and f[1] == pytest.approx(200.0) and f[2] == base["push"][0]["force"][2]
    assert sc["push"][0]["point"][2] == pytest.approx(0.3)
    assert sc["duration"] == 1.0
    # direction alone keeps the base magnitude (|(300, -75)|)
    (o,) = design.overrides_for({"push.0.direction_deg": 180.0}, base)
    fx, fy, _ = json.loads(o.split("=", 1)[1])
    assert math.hypot(fx, fy) == pytest.approx(math.hypot(300, 75)) and fx < 0 and abs(fy) < 1e-6


def test_target_keys_put_the_target_box_along_the_push():
    base = scenario_mod.load("standing_push")
    box = next(o for o in base["obstacles"] if o["is_target"])

    def target_of(settings):
        sc = base
        for o in design.overrides_for(settings, base):
            sc = scenario_mod.apply_override(sc, o)
        (t,) = [o for o in sc["obstacles"] if o["is_target"]]
        return t

    # along push 0's heading (90 deg: the robot's left), the near face 1.0 m out, facing the robot
    t = target_of({"push.0.direction_deg": 90.0, "target.distance_m": 1.0})
    assert t["position"][0] == pytest.approx(0.0, abs=1e-6)
    assert t["position"][1] == pytest.approx(1.0 + box["size"][0] / 2)
    assert t["position"][2] == box["position"][2] and t["size"] == box["size"]
    assert t["yaw"] == pytest.approx(math.pi / 2)
    # without a direction key: the base push's own heading (300 N forward, 75 N right)
    t = target_of({"target.distance_m": 1.2})
    assert math.atan2(t["position"][1], t["position"][0]) == pytest.approx(math.atan2(-75.0, 300.0))
    # an explicit heading wins
    t = target_of({"push.0.direction_deg": 90.0, "target.distance_m": 1.2, "target.heading_deg": 180.0})
    assert t["position"][0] == pytest.approx(-(1.2 + box["size"][0] / 2)) and abs(t["position"][1]) < 1e-6
    with pytest.raises(spec_mod.CampaignSpecError, match="needs target.distance_m"):
        design.overrides_for({"target.heading_deg": 10.0}, base)
    with pytest.raises(spec_mod.CampaignSpecError, match="no obstacle with is_target"):
        design.overrides_for({"target.distance_m": 1.0}, scenario_mod.load("standing_push", ["obstacles=[]"]))


@pytest.mark.parametrize("name", ["avoidance_map", "ftb_rates", "estop_success", "threshold_map",
                                  "standing_push_1000", "smoke"])
def test_built_in_specs_pass_their_own_check(name):
    spec = spec_mod.load(pathlib.Path(__file__).resolve().parents[1] / "config" / "campaigns" / f"{name}.yaml")
    base = scenario_mod.load(spec.base_scenario, list(spec.set))
    points = design.design_points(spec)
    assert points
    design.check_design(spec, base, points)  # raises on a key or value the scenario refuses


@pytest.mark.parametrize("stop_when_fallen", [False, True])
def test_an_inprocess_trial_row_carries_the_controllers_run_metrics(stop_when_fallen):
    """The e-stop's outcome (``estop_*``) reaches the trial's metrics by both in-process paths."""
    from humfall_ros.campaign.server import run_inprocess

    m = run_inprocess(TrialRequest("t0", "standing_quiet", ["estop.time=0.2", "duration=0.6"], "inprocess", 60.0,
                                   None, stop_when_fallen))
    assert m["estop_trigger_time_s"] == pytest.approx(0.2)
    assert m["estop_phase_at_trigger"] == "standing" and m["estop_state"] in ("stopping", "stopped", "holding")
    assert m["estop_feasible"] is True and m["fell"] is False
    plain = run_inprocess(TrialRequest("t1", "standing_quiet", ["duration=0.2"], "inprocess", 60.0, None))
    assert not any(k.startswith("estop_") for k in plain)  # no e-stop in the suite: no e-stop columns


def test_random_design_is_seeded(tmp_path):
    def pts(seed):
        return design.design_points(spec_mod.from_dict(tiny(tmp_path, design={"random": {
            "n": 20, "seed": seed, "keys": {"push.0.magnitude_n": {"uniform": [100, 200]},
                                            "push.0.duration": {"choice": [0.1, 0.2]}}}})))

    a, b, c = pts(1), pts(1), pts(2)
    assert a == b and a != c and len(a) == 20
    assert all(100 <= p["push.0.magnitude_n"] <= 200 and p["push.0.duration"] in (0.1, 0.2) for p in a)


def test_grid_is_the_cartesian_product_in_key_order(tmp_path):
    s = spec_mod.from_dict(tiny(tmp_path, design={"grid": {"push.0.direction_deg": {"circle": 4},
                                                           "push.0.height_m": [0.1, 0.3]}}))
    pts = design.design_points(s)
    assert [(p["push.0.direction_deg"], p["push.0.height_m"]) for p in pts] == \
        [(d, h) for d in (0.0, 90.0, 180.0, 270.0) for h in (0.1, 0.3)]


# ---------------------------------------------------------------------------- bisection (no simulation)
def _bisect(study_over: dict, true_threshold: float | None, tmp_path):
    d = tiny(tmp_path, design={"grid": {"push.0.direction_deg": [0.0, 90.0]}},
             study={"type": "threshold-map", "low": 100.0, "high": 600.0, "tolerance": 5.0, **study_over})
    spec, _, study, _ = prepare(spec_mod.from_dict(d), RunOptions())
    assert isinstance(study, ThresholdMap)
    todo, rows = list(study.start()), []
    while todo:
        t = todo.pop(0)
        mag = t.settings["push.0.magnitude_n"]
        # cell 1's threshold is 40 N higher: the cells must not mix
        thr = None if true_threshold is None else true_threshold + 40.0 * t.tags["cell"]
        fell = thr is not None and mag > thr
        row = make_row(t, {"status": "ok", "metrics": {"fell": fell, "fall_direction_deg": 3.0}}, "inprocess")
        rows.append(row)
        todo += study.feed(t, row)
    return spec, rows


def test_threshold_bisection_brackets_to_tolerance(tmp_path):
    spec, rows = _bisect({}, 237.0, tmp_path)
    assert len(rows) == 2 * 7          # ceil(log2(500 / 5)) per cell
    th = thresholds(pa.Table.from_pylist(rows), spec.model_dump(mode="json"))
    for t, true in zip(th, (237.0, 277.0)):
        assert t.status == "ok"
        assert t.low <= true < t.high and t.high - t.low <= 5.0
        assert abs(t.threshold - true) <= 2.5
        assert t.point["push.0.direction_deg"] in (0.0, 90.0)


def test_threshold_outside_range_is_flagged(tmp_path):
    spec, rows = _bisect({}, 50.0, tmp_path)      # everything falls
    th = thresholds(pa.Table.from_pylist(rows), spec.model_dump(mode="json"))
    assert th[0].status == "below_range" and th[0].threshold is None
    spec, rows = _bisect({}, None, tmp_path)      # nothing falls
    th = thresholds(pa.Table.from_pylist(rows), spec.model_dump(mode="json"))
    assert {t.status for t in th} == {"above_range"}


# ---------------------------------------------------------------------------- trial server
def test_failed_and_hung_trials_are_recorded_and_killed(tmp_path):
    s = TrialServer(str(tmp_path))
    try:
        r = s.run(TrialRequest("bad", "standing_push", ["push.0.forse=[1,2,3]"], "inprocess", 30.0, None))
        assert r["status"] == "failed" and "forse" in r["error"] and "Traceback" in r["log_tail"]
        tag = s.tag
        t0 = time.monotonic()
        r = s.run(TrialRequest("hang", "standing_push", ["duration=600"], "inprocess", 1.5, None))
        assert r["status"] == "timeout" and "time limit" in r["error"]
        assert 1.4 < time.monotonic() - t0 < 10.0
        assert "start hang" in r["log_tail"]
        assert tagged_pids(SERVER_TAG_ENV, tag) == []          # the hung server is gone
        r = s.run(TrialRequest("next", "standing_push", ["duration=0.1"], "inprocess", 60.0, None))
        assert r["status"] == "ok" and r["metrics"]["fell"] is False   # a fresh server took over
    finally:
        s.close()
    assert tagged_pids(SERVER_TAG_ENV, s.tag) == []


# ---------------------------------------------------------------------------- runs, resume, report
def test_campaign_runs_resumes_and_refuses_another_spec(tmp_path):
    d = tiny(tmp_path, design={"grid": {"push.0.direction_deg": [0.0, 90.0, 180.0],
                                        "push.0.magnitude_n": [60.0]}})
    d["design"]["grid"]["push.0.direction_deg"] = [0.0, 90.0, 180.0]
    spec = spec_mod.from_dict(d)
    # a crash after one trial: only its fragment is on disk
    _, base0, study, digest = prepare(spec, RunOptions())
    store = ResultStore(tmp_path / "out")
    store.open(spec.model_dump(mode="json"), digest, base0)
    first = study.start()[1]
    store.add(make_row(first, {"status": "ok", "metrics": {"fell": False, "marker": 42.0}}, "inprocess"))
    store.flush()

    s = run_campaign(spec, RunOptions(executor="local", workers=2, progress=False))
    assert (s.ran, s.resumed, s.status_counts) == (2, 1, {"ok": 2})
    table, meta = load_results(s.results)
    assert table.column("trial_id").to_pylist() == ["t000000", "t000001", "t000002"]
    # the resumed row is the stored one, not a rerun
    assert table.column("m.marker").to_pylist() == [None, 42.0, None]
    assert all(w > 0 for w in table.column("wall_s").to_pylist()[::2])
    assert meta["spec_hash"] == digest and len(meta["sessions"]) == 2

    s2 = run_campaign(spec, RunOptions(executor="local", workers=1, progress=False))
    assert (s2.ran, s2.resumed) == (0, 3)

    other = spec_mod.from_dict({**d, "set": ["obstacles=[]", "duration=0.4"]})
    with pytest.raises(ResumeError, match="another spec"):
        run_campaign(other, RunOptions(executor="local", workers=1, progress=False))
    assert cli.main([write_spec(tmp_path, other.model_dump(mode="json")), "--local"]) == 2

    html_path = write_report(tmp_path / "out")
    text = html_path.read_text()
    assert "<h2>Status</h2>" in text and "data:image/png;base64," in text
    assert cli.main(["report", str(tmp_path / "out" / "results.parquet"), "-o", str(tmp_path / "r.html")]) == 0
    assert (tmp_path / "r.html").stat().st_size > 1000


def test_timeout_row_is_kept_in_the_table(tmp_path):
    d = tiny(tmp_path, design={"grid": {"duration": [0.2, 300.0]}},
             trial={"time_limit_s": 8.0})  # slack for a loaded machine
    s = run_campaign(spec_mod.from_dict(d), RunOptions(executor="local", workers=2, progress=False))
    table, _ = load_results(s.results)
    rows = {r["set.duration"]: r for r in table.to_pylist()}
    assert rows[0.2]["status"] == "ok"
    assert rows[300.0]["status"] == "timeout" and "time limit" in rows[300.0]["error"]
    assert rows[300.0]["log_tail"]


def test_stop_when_fallen_keeps_the_fall_metrics(tmp_path):
    ov = ["obstacles=[]", "duration=3.0", "push.0.force=[520,0,0]"]
    s = TrialServer(str(tmp_path))
    try:
        full = s.run(TrialRequest("full", "standing_push", ov, "inprocess", 60.0, None))
        short = s.run(TrialRequest("short", "standing_push", ov, "inprocess", 60.0, None, stop_when_fallen=True))
        held = s.run(TrialRequest("held", "standing_push", ["obstacles=[]", "duration=1.0",
                                                            "push.0.force=[60,0,0]"], "inprocess", 60.0, None,
                                  stop_when_fallen=True))
    finally:
        s.close()
    a, b = full["metrics"], short["metrics"]
    assert a["fell"] and b["fell"]
    assert b["stopped_early_at_s"] is not None and b["sim_duration_s"] < 2.5 and a["sim_duration_s"] == 3.0
    for k in ("fall_time_s", "landing_time_s", "fall_direction_deg", "landing_com"):
        assert b[k] == a[k], k
    assert held["metrics"]["fell"] is False and held["metrics"]["stopped_early_at_s"] is None
    assert held["metrics"]["sim_duration_s"] == 1.0


def test_check_validates_and_runs_nothing(tmp_path, capsys):
    d = tiny(tmp_path, design={"grid": {"push.0.direction_deg": {"circle": 12}, "push.0.height_m": [0.1, 0.3]}},
             study={"type": "threshold-map", "low": 100.0, "high": 600.0, "tolerance": 5.0})
    assert cli.main([write_spec(tmp_path, d), "--check"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["trials"] == 24 * 7 and out["study"] == "threshold-map" and len(out["spec_hash"]) == 64
    assert not (tmp_path / "out").exists()


def test_threshold_report_from_a_stored_map(tmp_path):
    spec, rows = _bisect({}, 237.0, tmp_path)
    _, base0, _, digest = prepare(spec, RunOptions())
    store = ResultStore(tmp_path / "out")
    store.open(spec.model_dump(mode="json"), digest, base0)
    for r in rows:
        store.add(r)
    store.merge()
    text = write_report(tmp_path / "out").read_text()
    assert "Fall threshold" in text and text.count("data:image/png;base64,") >= 2
    assert "below_range" not in text and ">ok<" in text


def test_sweep_report_draws_both_avoidance_angles_per_controller_and_a_cross_table(tmp_path):
    d = tiny(tmp_path, design={"grid": {"push.0.direction_deg": [0.0, 90.0, 180.0],
                                        "controller": ["stepping", "stepping_inertia"]}})
    spec, base0, study, digest = prepare(spec_mod.from_dict(d), RunOptions())
    store = ResultStore(tmp_path / "out")
    store.open(spec.model_dump(mode="json"), digest, base0)
    for t in study.trials:  # synthetic outcomes: every stepping_inertia trial falls, stepping ones only at 180 deg
        falls = t.settings["controller"] == "stepping_inertia" or t.settings["push.0.direction_deg"] == 180.0
        store.add(make_row(t, {"status": "ok", "metrics": {"fell": falls, "avoidance_angle_deg": 100.0,
                                                           "avoidance_angle_p2_deg": 150.0}}, "inprocess"))
    store.merge()
    text = write_report(tmp_path / "out").read_text()
    assert "Mean avoidance angle α (" in text and "Mean avoidance angle α2 (" in text
    assert "Fell / trials: push.0.direction_deg (rows) × controller (columns)" in text
    table = text[text.index("Fell / trials"):]
    cells = [c.split("</td>")[0] for c in table.split("<td>")[1:7]]
    # rows 0, 90, 180 deg (numeric order); columns stepping, stepping_inertia
    assert cells == ["0 / 1", "1 / 1", "0 / 1", "1 / 1", "1 / 1", "1 / 1"]


def test_threshold_map_resumes_mid_bisection(tmp_path):
    import pyarrow.parquet as pq

    d = tiny(tmp_path, design={"grid": {"push.0.direction_deg": [0.0]}},
             study={"type": "threshold-map", "low": 100.0, "high": 500.0, "tolerance": 100.0})
    spec = spec_mod.from_dict(d)
    s = run_campaign(spec, RunOptions(executor="local", workers=1, progress=False))
    assert (s.ran, s.resumed) == (2, 0)          # 400 N -> 200 -> 100 N bracket: 2 trials
    full, _ = load_results(s.results)
    # as if the campaign had died after its first trial
    store = ResultStore(tmp_path / "out")
    first = store.read_fragments().filter(pa.compute.equal(store.read_fragments().column("step"), 0))
    for f in store.fragments.glob("part-*.parquet"):
        f.unlink()
    pq.write_table(first, store.fragments / "part-000000-0.parquet")
    s = run_campaign(spec, RunOptions(executor="local", workers=1, progress=False))
    assert (s.ran, s.resumed) == (1, 1)
    again, _ = load_results(s.results)
    assert comparable_eq(full, again)


def comparable_eq(a, b) -> bool:
    from humfall_ros.campaign.store import comparable

    return comparable(a).equals(comparable(b))
