"""One source per parameter: every node declares exactly what its config/<node>.yaml declares
(type, default, description, range), and in-process users read the same declarations."""
import importlib
import math

import pytest
import yaml

from humfall_ros import params

NODES = {"sim_bridge": "SimBridge", "state_estimator": "StateEstimator", "locomotion": "Locomotion",
         "recorder": "Recorder", "multicontact_planner": "MulticontactPlanner"}
ROS_TYPE = {1: "bool", 2: "int", 3: "double", 4: "string", 6: "bool_array", 7: "int_array", 8: "double_array",
            9: "string_array"}


@pytest.fixture
def rclpy_ctx(in_ros_domain, tmp_path):
    import rclpy

    rclpy.init(args=["test", "--ros-args", "-p", "warm_up:=false", "-p", f"output_dir:={tmp_path}"])
    yield
    rclpy.try_shutdown()


@pytest.mark.parametrize("name", sorted(NODES))
def test_node_declares_what_its_config_declares(rclpy_ctx, name):
    decl = params.declarations(name)
    assert decl, f"config/{name}.yaml declares nothing"
    mod = importlib.import_module(f"humfall_ros.nodes.{name}")
    node = getattr(mod, NODES[name])()
    try:
        declared = {n for n in node._parameters if n not in ("use_sim_time", "start_type_description_service")}
        assert declared == set(decl), (sorted(declared - set(decl)), sorted(set(decl) - declared))
        for d, p in zip(node.describe_parameters(list(decl)), decl.values()):
            assert ROS_TYPE[d.type] == p.type, p.name
            assert d.description == p.description and d.read_only == p.read_only, p.name
            rng = list(d.floating_point_range) + list(d.integer_range)
            if p.bounds is None:
                assert not rng, p.name
            else:
                assert (rng[0].from_value, rng[0].to_value) == pytest.approx(p.bounds), p.name
        for p in decl.values():
            value = node.get_parameter(p.name).value
            if p.name in ("warm_up", "output_dir"):  # overridden on the command line above
                continue
            value = list(value) if isinstance(value, (list, tuple)) or hasattr(value, "tolist") else value
            assert value == p.default or (isinstance(value, float) and math.isclose(value, p.default)), p.name
    finally:
        close = getattr(node, "close", None)
        if callable(close):
            close()
        node.destroy_node()


def test_declarations_are_refused_when_malformed(tmp_path, monkeypatch):
    from humfall_ros import paths

    (tmp_path / "config").mkdir()
    (tmp_path / "config" / "bad.yaml").write_text("bad:\n  x: {type: double, default_value: 1.0}\n")
    monkeypatch.setattr(paths, "config_path", lambda n: tmp_path / "config" / n)
    params.declarations.cache_clear()
    try:
        with pytest.raises(params.ParamError, match="description"):
            params.declarations("bad")
        (tmp_path / "config" / "bad.yaml").write_text(
            "bad:\n  x: {type: double, default_value: 9.0, description: d, validation: {bounds<>: [0, 1]}}\n")
        params.declarations.cache_clear()
        with pytest.raises(params.ParamError, match="outside"):
            params.declarations("bad")
    finally:
        params.declarations.cache_clear()


def test_overrides_are_typed_and_checked():
    assert params.check_overrides("locomotion", {"ankle_kp": 1}) == {"ankle_kp": 1.0}
    with pytest.raises(params.ParamError, match="no parameter"):
        params.check_overrides("locomotion", {"ankle_kpp": 1.0})
    with pytest.raises(params.ParamError, match="outside"):
        params.check_overrides("locomotion", {"ankle_kp": 1e6})
    with pytest.raises(params.ParamError, match="expected bool"):
        params.check_overrides("sim_bridge", {"lockstep": 1})
    # a string with one_of<>: the declared choices pass, another is refused by name
    assert params.check_overrides("safe_fall_controller", {"fall_ranking": "edge"}) == {"fall_ranking": "edge"}
    with pytest.raises(params.ParamError, match="not one of paper, edge"):
        params.check_overrides("safe_fall_controller", {"fall_ranking": "sideways"})
    # '1e-4' is a string to PyYAML (YAML 1.1): a double takes it as the number YAML 1.2 reads; other text is refused
    assert yaml.safe_load("1e-4") == "1e-4"
    assert params.check_overrides("sim_bridge", {"noise_joint_position": "1e-4"}) == {"noise_joint_position": 1e-4}
    with pytest.raises(params.ParamError, match="expected double"):
        params.check_overrides("sim_bridge", {"noise_joint_position": "1e-4x"})
    with pytest.raises(params.ParamError, match="expected int"):
        params.check_overrides("sim_bridge", {"noise_seed": "1e3"})


def test_config_from_refuses_unknown_keys_and_drops_only_the_ignored():
    import dataclasses

    @dataclasses.dataclass
    class Cfg:
        gain: float = 1.0
        name: str = "a"

    assert params.config_from(Cfg, {"gain": 2.0}) == Cfg(2.0, "a")  # missing keys take the defaults
    assert params.config_from(Cfg, {"gain": 2.0, "queue_size": 3}, ignore=("queue_size",)) == Cfg(2.0)
    with pytest.raises(params.ParamError, match=r"my_node: unknown parameters \['gian'\]"):
        params.config_from(Cfg, {"gian": 2.0}, where="my_node")
    with pytest.raises(ValueError):  # ParamError is a ValueError: callers' except clauses still hold
        params.config_from(Cfg, {"gain": 1.0, "extra": 0})



# config dataclass -> its node's declaration, and the fields whose dataclass default is deliberately not the
# declared one (why)
CONFIG_CLASSES = {
    "humfall_ros.fall.controller:SafeFallConfig": ("safe_fall_controller", {}),
    "humfall_ros.fall.ftb:FtbConfig": ("ftb_monitor", {}),
    "humfall_ros.walking.config:LocomotionConfig": ("locomotion", {}),
    "humfall_ros.estop.config:EstopConfig": ("estop_planner", {}),
    # the node resolves start_time < 0 to the plan file's take-over time; in process there is no file
    "humfall_ros.multicontact.executor:ExecutorConfig": ("multicontact_executor", {"start_time"}),
}


@pytest.mark.parametrize("path", sorted(CONFIG_CLASSES))
def test_config_dataclass_defaults_do_not_drift_from_the_declaration(path):
    """In-process users that build a config with its defaults (``SafeFallConfig()``) run the
    controller the node runs: every field the node's yaml declares has the declared default
    (compared by value: an enum field against its declared string)."""
    import dataclasses
    import enum

    module, name = path.split(":")
    cls = getattr(importlib.import_module(module), name)
    node, exempt = CONFIG_CLASSES[path]
    decl = params.defaults(node)
    inst = cls()
    shared = [f.name for f in dataclasses.fields(cls) if f.name in decl and f.name not in exempt]
    assert len(shared) >= 5, shared    # the comparison is not vacuous
    for field in shared:
        got, want = getattr(inst, field), decl[field]
        if isinstance(got, enum.Enum):
            got = got.value
        if isinstance(want, list):
            want = tuple(want)
        if isinstance(got, list):
            got = tuple(got)
        assert got == want or (isinstance(got, float) and math.isnan(got) and math.isnan(want)), \
            f"{name}.{field}: dataclass {got!r}, config/{node}.yaml {want!r}"


def test_parse_overrides_reads_yaml_values_and_semicolon_lists():
    """The ``--set`` of the benchmarks and of ``build_library``: YAML values, lists written with ';'."""
    assert params.parse_overrides("") == {}
    got = params.parse_overrides("max_iter=300, transition_objective=post_impact,seed_retry_durations=[0.5;1.2],a=true")
    assert got == {"max_iter": 300, "transition_objective": "post_impact", "seed_retry_durations": [0.5, 1.2],
                   "a": True}
    with pytest.raises(ValueError):
        params.parse_overrides("no_value")


def test_string_choices_are_declared_as_the_code_accepts_them():
    """Every string parameter with a fixed set of values declares it (``one_of<>``: checked for launch and scenario
    overrides, listed in the ROS descriptor), and the declaration is the set the code accepts."""
    from humfall_ros.estop.config import BETA_POLICIES, BLEND_PROFILES, FALLBACKS
    from humfall_ros.fall.controller import RECRUIT
    from humfall_ros.fall.ftb import TriggerMode
    from humfall_ros.fall.inertia_shaping import SHAPING_DIRECTIONS
    from humfall_ros.fall.step_search import FALL_RANKINGS
    from humfall_ros.multicontact.collocation import TRANSITION_OBJECTIVES
    from humfall_ros.multicontact.tree import FRONTIER_ORDERS, LANDING_POLICIES
    from humfall_ros.walking.config import RESUME_STANCES

    # the executor checks its config against the declaration itself; these are the values its code branches on
    code = {("multicontact_executor", "hold"): ("planar", "measured"),
            ("multicontact_executor", "swing_control"): ("joints", "task"),
            ("multicontact_planner", "transition_objective"): TRANSITION_OBJECTIVES,
            ("multicontact_planner", "frontier_order"): FRONTIER_ORDERS,
            ("multicontact_planner", "landing_policy"): LANDING_POLICIES,
            ("estop_planner", "beta_policy"): BETA_POLICIES, ("estop_planner", "fallback"): FALLBACKS,
            ("estop_planner", "blend_profile"): BLEND_PROFILES,
            ("ftb_monitor", "mode"): tuple(m.value for m in TriggerMode),
            ("locomotion", "resume_stance"): RESUME_STANCES,
            ("safe_fall_controller", "shaping_recruit"): tuple(RECRUIT),
            ("safe_fall_controller", "shaping_direction"): SHAPING_DIRECTIONS,
            ("safe_fall_controller", "fall_ranking"): FALL_RANKINGS}
    for (node, name), accepted in code.items():
        d = params.declarations(node)[name]
        assert d.choices is not None and set(d.choices) == set(accepted), (node, name, d.choices, accepted)
        assert d.default in d.choices, (node, name)
    assert params.declarations("recorder")["clock"].choices == ("sim", "wall")    # the node checks against it
    with pytest.raises(params.ParamError, match="swing_control"):
        params.check_overrides("multicontact_executor", {"swing_control": "joint"})


def test_a_node_refuses_a_string_outside_its_declared_choices(rclpy_ctx):
    """rclpy enforces the descriptor's number ranges, not a string's choices: ``Params`` does, at start-up (an
    override such as ``-p swing_control:=joint``) and on a later set (``ros2 param set``), with the choices in the
    reason."""
    from rclpy.exceptions import InvalidParameterValueException
    from rclpy.node import Node
    from rclpy.parameter import Parameter

    from humfall_ros.nodes.common import Params

    bad = Node("choices_test_bad", parameter_overrides=[Parameter("swing_control", value="joint")])
    try:
        with pytest.raises(InvalidParameterValueException, match="joints, task"):
            Params(bad, "multicontact_executor").declare("swing_control")
    finally:
        bad.destroy_node()
    node = Node("choices_test")
    try:
        p = Params(node, "multicontact_executor")
        assert p.declare("swing_control") == "task"
        refused = node.set_parameters([Parameter("swing_control", value="joint")])[0]
        assert not refused.successful and "joints, task" in refused.reason
        assert node.get_parameter("swing_control").value == "task"
        assert node.set_parameters([Parameter("swing_control", value="joints")])[0].successful
    finally:
        node.destroy_node()
