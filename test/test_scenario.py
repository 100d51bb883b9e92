"""Scenario files: schema, validation, overrides."""
import pytest

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
