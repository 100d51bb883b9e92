"""Scenario files: schema, validation, overrides."""
import subprocess
import sys

import pytest
import yaml

from humfall_ros import paths, scenario


@pytest.mark.parametrize("name", ["standing_push", "standing_quiet", "small_push"])
def test_shipped_scenarios_validate(name):
    sc = scenario.load(name)
    assert sc["name"] == name and sc["duration"] > 0


def test_standing_push_is_the_papers_setup():
    sc = scenario.load("standing_push")
    (push,) = sc["push"]
    assert push["duration"] == pytest.approx(0.1)
    fx, fy, _ = push["force"]
    assert fx > 0 and fy < 0 and fx / -fy == pytest.approx(4.0)   # forward and to the right, 4:1
    (target,) = [o for o in sc["obstacles"] if o["is_target"]]
    assert target["position"][:2] == pytest.approx([1.2, 0.0])  # T, 1.2 m straight ahead


def test_overrides_apply_and_revalidate():
    sc = scenario.load("standing_push", ["push.0.force=[1, 2, 3]", "duration=2", "params.locomotion.ankle_kp=0.5"])
    assert sc["push"][0]["force"] == [1.0, 2.0, 3.0]
    assert sc["duration"] == 2.0
    assert sc["params"]["locomotion"]["ankle_kp"] == 0.5


@pytest.mark.parametrize("override, message", [
    ("pushh.0.force=[1,2,3]", "no such key pushh"),
    ("push.5.force=[1,2,3]", "no list item push.5"),
    ("push.0.force=[1,2]", "expected a list of 3 numbers"),
    ("duration=abc", "expected a number"),
    ("duration=.nan", "non-finite"),
    ("controller=flying", "is not one of"),
    ("noequals", "expected dotted.key=value"),
    ("push.0.force=[6000, 0, 0]", "exceeds"),
    ("push.0.link=tail", "no link 'tail'"),
    ("push.0.duration=0", "duration"),
    ("robot.initial_posture.warp=0.3", "unknown joints"),
    ("sim.real_time_factor=-3", "outside"),
    ("sim.friction=-1", "outside"),
    ("sim.physics_rate=1e7", "outside"),
])
def test_bad_overrides_are_refused(override, message):
    with pytest.raises(scenario.ScenarioError, match=message):
        scenario.load("standing_push", [override])


def test_bad_files_are_refused(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("duration: 3\npush:\n  - time: 1\n    forse: [1, 2, 3]\n")
    with pytest.raises(scenario.ScenarioError, match="unknown key push.0.forse"):
        scenario.load(str(bad))
    bad.write_text("duration: [1]\n")
    with pytest.raises(scenario.ScenarioError, match="duration: expected a number"):
        scenario.load(str(bad))
    with pytest.raises(scenario.ScenarioError, match="no scenario"):
        scenario.load("does_not_exist")
    assert paths.scenario_path("standing_push").is_file()


def test_obstacle_sizes_must_be_positive(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("obstacles:\n  - name: a\n    size: [-1, 0, 0]\n")
    with pytest.raises(scenario.ScenarioError, match="obstacles.0.size"):
        scenario.load(str(bad))


def test_numbers_in_exponent_form_are_numbers():
    assert scenario.load("standing_push", ["sim.physics_rate=2e3"])["sim"]["physics_rate"] == 2000.0


# ---------------------------------------------------------------- pydantic schema, new keys, boundaries
def test_defaults_change_nothing_for_existing_scenarios():
    sc = scenario.validate({})
    assert sc["walk"]["steps"] == 0 and sc["walk"]["speed_kmh"] == 0.0     # no walk
    assert sc["estop"]["time"] == -1.0 and sc["estop"]["at"] is None        # no e-stop
    assert sc["controllers"] == []
    assert scenario.load("standing_push")["push"][0]["at"] is None
    from humfall_ros import params

    bridge = params.defaults("sim_bridge")
    assert sc["sim"] == {k: bridge[k] for k in sc["sim"]}   # one source: config/sim_bridge.yaml
    assert scenario.SIM_RANGES["physics_rate"] == params.declarations("sim_bridge")["physics_rate"].bounds


def test_dump_round_trips():
    sc = scenario.load("standing_push", ["estop.at={step: 5, phase: ds_start}", "walk.steps=8"])
    assert scenario.validate(yaml.safe_load(scenario.dump(sc))) == sc


def test_gait_timed_push_and_estop():
    sc = scenario.load("standing_push", ["push.0.at={step: 3, phase: ss_start}", "estop.at={step: 5, phase: ds_start}"])
    assert sc["push"][0]["at"] == {"step": 3, "phase": "ss_start"}
    assert sc["estop"]["at"] == {"step": 5, "phase": "ds_start"} and sc["estop"]["time"] == -1.0
    assert set(scenario.PHASES) == {"ds_start", "ds_mid", "ss_start", "ss_mid", "ss_end"}


def test_walk_keys():
    sc = scenario.load("standing_push", ["walk={steps: 6, speed_kmh: 2.0, step_period: 0.7, double_support: 0.15}"])
    w = sc["walk"]
    assert (w["steps"], w["speed_kmh"], w["step_period"], w["double_support"]) == (6, 2.0, 0.7, 0.15)
    assert w["turn_rate_deg_s"] == 0.0 and w["direction_deg"] == 0.0
    # the controller clamps the speed (with a warning), the scenario does not
    assert scenario.load("standing_push", ["walk.speed_kmh=4"])["walk"]["speed_kmh"] == 4.0


@pytest.mark.parametrize("override, message", [
    ("push.0.at={step: 2, phase: ds_begin}", r"push\.0\.at\.phase: 'ds_begin' is not one of"),
    ("push.0.at={step: -1, phase: ds_mid}", r"push\.0\.at\.step: -1 must be >= 0"),
    ("push.0.at={step: 1}", r"push\.0\.at\.phase: required key missing"),
    ("push.0.at={step: 1, phase: ds_mid, when: 2}", r"unknown key push\.0\.at\.when \(known: phase, step\)"),
    ("push.0.at.step=3", r"push\.0\.at is null; set it whole"),
    ("push.0.time=-1", r"push\.0\.time: -1\.0 s must be >= 0"),
    ("estop.at=[3]", r"estop\.at: expected a mapping"),
    ("estop.time=-0.5", r"estop\.time: .*-1 for no e-stop"),
    ("estop.random_window=[2, 1]", r"estop\.random_window"),
    ("estop={time: 2, at: {step: 1, phase: ds_start}}", r"estop: give time .* or at, not both"),
    ("walk.steps=-1", r"walk\.steps: -1 must be >= 0"),
    ("walk.steps=2.5", r"walk\.steps: expected an integer"),
    ("walk.step_period=0.3", r"walk\.step_period: 0\.3 s is outside \[0\.4, 1\.5\]"),
    ("walk.double_support=0.8", r"walk\.double_support: 0\.8 s must be in \(0, step_period"),
    ("walk.double_support=0", r"walk\.double_support"),
    ("walk.speed_kmh=-0.5", r"walk\.speed_kmh: -0\.5 km/h must be >= 0"),
    ("walk.speed_kmh=.inf", r"walk\.speed_kmh: non-finite"),
    ("walk.turn_rate_deg_s=abc", r"walk\.turn_rate_deg_s: expected a number"),
    ("walk.stride=3", r"no such key walk\.stride"),
    ("sim.physics_rate=1100", r"sim: physics_rate \(1100\.0 Hz\) must be a positive integer multiple"),
    ("obstacles=[{name: a}, {name: a}]", r"obstacles: names must be unique \('a'"),
    ("robot.initial_posture.l_knee=abc", r"robot\.initial_posture\.l_knee: expected a number"),
    ("params.locomotion=3", r"params\.locomotion: expected a mapping, got int"),
    ("push=null", r"push: expected a list, got NoneType"),
])
def test_bad_new_keys_are_refused_with_their_dotted_path(override, message):
    with pytest.raises(scenario.ScenarioError, match=message):
        scenario.load("standing_push", [override])


def test_several_errors_are_all_reported():
    with pytest.raises(scenario.ScenarioError) as e:
        scenario.validate({"duration": "x", "push": [{"force": [1, 2]}], "walk": {"steps": -1}})
    lines = str(e.value).splitlines()
    assert lines[0] == "3 errors:"
    assert [ln.split(":")[0].strip() for ln in lines[1:]] == ["duration", "push.0.force", "walk.steps"]


def test_a_file_that_is_not_a_mapping_is_refused(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("- 1\n- 2\n")
    with pytest.raises(scenario.ScenarioError, match="scenario: expected a mapping, got list"):
        scenario.load(str(bad))


def extra(*entries):
    return "controllers=[" + ", ".join("{" + e + "}" for e in entries) + "]"


def test_extra_controllers():
    sc = scenario.load("standing_push", [extra("node: locomotion, source: takeover, priority: 15, params: {a: 1}"),
                                         "controllers.0.params.b=2"])   # its params are a free-form map
    assert sc["controllers"] == [{"node": "locomotion", "source": "takeover", "priority": 15,
                                  "params": {"a": 1, "b": 2}}]
    assert scenario.controller_module("locomotion") == "humfall_ros.nodes.locomotion"
    assert scenario.controller_module("mylab.ctrl") == "mylab.ctrl"
    assert scenario.BUILTIN_PRIORITIES == {"locomotion": 10, "estop": 20, "safe_fall": 30}


def test_extra_controller_from_a_module_path(tmp_path, monkeypatch):
    (tmp_path / "mylab").mkdir()
    (tmp_path / "mylab" / "ctrl.py").write_text("def main():\n    pass\n")
    monkeypatch.chdir(tmp_path)   # `python -m mylab.ctrl` started here finds it
    sc = scenario.load("standing_push", [extra("node: mylab.ctrl, source: lab, priority: 5")])
    assert sc["controllers"][0]["node"] == "mylab.ctrl"
    with pytest.raises(scenario.ScenarioError, match=r"controllers\.0\.node: no module mylab\.nope"):
        scenario.load("standing_push", [extra("node: mylab.nope, source: lab, priority: 5")])


@pytest.mark.parametrize("entries, message", [
    (["node: locomotion, source: estop, priority: 5"],
     r"controllers\.0: source 'estop' \(priority 5\) clashes with the built-in source 'estop' \(priority 20\)"),
    (["node: locomotion, source: mine, priority: 30"],
     r"controllers\.0: priority 30 \(source 'mine'\) clashes with the built-in source 'safe_fall' \(priority 30\)"),
    (["node: locomotion, source: a, priority: 5", "node: locomotion, source: b, priority: 5"],
     r"controllers\.1: priority 5 \(source 'b'\) clashes with controllers\.0 \(source 'a', priority 5\)"),
    (["node: locomotion, source: a, priority: 5", "node: locomotion, source: a, priority: 6"],
     r"controllers\.1: source 'a' \(priority 6\) clashes with controllers\.0 \(source 'a', priority 5\)"),
    (["node: locomotion, source: Bad-Name, priority: 5"], r"controllers\.0\.source: 'Bad-Name' is not a source name"),
    (["node: no_such_node, source: a, priority: 5"],
     r"controllers\.0\.node: no module humfall_ros\.nodes\.no_such_node"),
    (["node: 'a b', source: a, priority: 5"], r"controllers\.0\.node: 'a b' is not a node name"),
    (["node: locomotion, source: a"], r"controllers\.0\.priority: required key missing"),
    (["node: locomotion, source: a, priority: 5.5"], r"controllers\.0\.priority: expected an integer"),
    (["node: locomotion, source: a, priority: 5, prio: 3"], r"unknown key controllers\.0\.prio"),
])
def test_conflicting_or_bad_controllers_are_refused(entries, message):
    with pytest.raises(scenario.ScenarioError, match=message):
        scenario.load("standing_push", [extra(*entries)])


@pytest.mark.parametrize("module", ["humfall_ros.scenario", "humfall_ros.launch"])
def test_scenario_and_launcher_import_neither_rclpy_nor_pybullet(module):
    """Issue 9 item 6: validating a scenario (pushes, links, joints, controllers) needs no ROS and no simulator."""
    code = (f"import sys, {module}\n"
            "from humfall_ros import scenario\n"
            "scenario.load('standing_push', ['controllers=[{node: locomotion, source: x, priority: 5}]',"
            " 'robot.initial_posture.l_knee=0.3'])\n"
            "print(sorted(m for m in ('rclpy', 'pybullet', 'humfall_ros.sim.world') if m in sys.modules))\n")
    out = subprocess.run([sys.executable, "-c", code], check=False, capture_output=True, text=True, timeout=60,
                         cwd=paths.share_dir())
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


def test_validate_push_lives_in_a_pure_module():
    from humfall_ros.sim import push, world

    assert world.validate_push is push.validate_push and world.MAX_PUSH_FORCE == push.MAX_PUSH_FORCE
    assert push.validate_push([0, 0, 0], [0, 0, 0], 0.1) is None
    assert "exceeds" in push.validate_push([push.MAX_PUSH_FORCE * 0.6] * 3, [0, 0, 0], 0.1)  # |f| = 1.04 * max


def test_gait_defaults_are_the_walking_controllers():
    from humfall_ros import params

    loco = params.defaults("locomotion")
    walk = scenario.validate({})["walk"]
    for key in ("step_period", "double_support"):
        if key in loco:
            assert walk[key] == loco[key]
    if "double_support" in loco:
        lo, _ = params.declarations("locomotion")["double_support"].bounds
        with pytest.raises(scenario.ScenarioError, match=r"walk\.double_support: .* \(locomotion's double_support\)"):
            scenario.validate({"walk": {"double_support": lo / 2}})


def test_a_walking_scenario_gives_the_fall_trigger_the_gait_reference_on_both_paths(tmp_path):
    # humfall up (plan_nodes) and the in-process loop (node_params) apply scenario.node_defaults alike;
    # the scenario's params.<node> still overrides it; a standing scenario leaves the declared default
    from humfall_ros import launch
    from humfall_ros.suite import node_params

    def graph(sc):
        return {n.name: n.params for n in launch.plan_nodes(sc, tmp_path, record=False)}["ftb_monitor"]

    walking = scenario.load("walking", ["controller=stepping"])
    assert scenario.walks(walking)
    assert graph(walking)["use_walking_state"] is True and graph(walking)["use_estop_status"] is True
    assert node_params(walking, "ftb_monitor")["use_walking_state"] is True
    off = scenario.load("walking", ["controller=stepping", "params.ftb_monitor.use_walking_state=false"])
    assert graph(off)["use_walking_state"] is False and node_params(off, "ftb_monitor")["use_walking_state"] is False
    standing = scenario.load("standing_push", ["controller=stepping"])
    assert not scenario.walks(standing)
    assert "use_walking_state" not in graph(standing) and "use_estop_status" not in graph(standing)
    assert node_params(standing, "ftb_monitor")["use_walking_state"] is False


def test_the_fixed_trigger_gets_the_push_end_on_both_paths(tmp_path):
    # paper 1 sec. V-A's fixed mode needs the push end: humfall up and the in-process loop (sim.fall_runs, the
    # benchmarks) both take it from the scenario's first push; the in-process loop once had none and never fired
    from humfall_ros import launch
    from humfall_ros.scenario import push_time
    from humfall_ros.suite import node_params

    sc = scenario.load("standing_push", ["controller=stepping", "params.ftb_monitor.mode=fixed"])
    first = min(sc["push"], key=lambda p: push_time(sc, p))
    end = push_time(sc, first) + first["duration"]
    graph = {n.name: n.params for n in launch.plan_nodes(sc, tmp_path, record=False)}["ftb_monitor"]
    assert graph["push_end_time_s"] == pytest.approx(end)
    assert node_params(sc, "ftb_monitor")["push_end_time_s"] == pytest.approx(end)
    quiet = scenario.load("standing_quiet", ["controller=stepping"])
    assert not quiet["push"] and node_params(quiet, "ftb_monitor")["push_end_time_s"] < 0


def test_every_controller_choice_says_which_nodes_serve_it():
    """The controller choices, their nodes and their parameters are one table (scenario.py) that the
    launcher and the in-process suite both read: every choice has its nodes, parameters only for
    choices and nodes that exist, and both users see the same objects."""
    from humfall_ros import launch, scenario, suite

    assert set(scenario.CONTROLLER_NODES) == set(scenario.CONTROLLERS)
    for kind, per_node in scenario.CONTROLLER_PARAMS.items():
        assert kind in scenario.CONTROLLERS
        assert set(per_node) <= set(scenario.CONTROLLER_NODES[kind]), (kind, per_node)
    assert launch.CONTROLLER_NODES is scenario.CONTROLLER_NODES and suite.CONTROLLERS is scenario.CONTROLLERS
    assert launch.CONTROLLER_PARAMS is scenario.CONTROLLER_PARAMS
