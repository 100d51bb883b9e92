"""Scenario files (config/scenarios/*.yaml): schema, validation and overrides.

A scenario says what world the robot is in, what happens to it and how long
the run lasts. The schema is a tree of pydantic v2 models (:class:`Scenario`
and its sections); unknown keys and wrong types are refused with the dotted
path of the offending key (``push.0.force: expected a list of 3 numbers, got
[1, 2]``), so a typo never silently runs the wrong experiment.

Callers get a complete, normalised plain dict (:func:`validate`, :func:`load`):
every key present, numbers as floats, vectors as lists of floats, ``null``
for an absent optional section (``push.N.at``, ``estop.at``).

No rclpy and no simulator here: push limits come from
:mod:`humfall_ros.sim.push` (pure), link and joint names from the model
(:func:`humfall_ros.model.humanoid.load_model`), the bridge's rates and
their ranges from ``config/sim_bridge.yaml`` (:mod:`humfall_ros.params`).
"""
from __future__ import annotations

import copy
import importlib.util
import math
import os
import re
import sys
from importlib.machinery import PathFinder
from typing import Annotated, Any, Literal, get_args

import yaml
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    PlainValidator,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)

from humfall_ros import params as params_mod
from humfall_ros import paths
from humfall_ros.sim.push import validate_push


class ScenarioError(ValueError):
    """A scenario is refused; the message is ``<dotted.path>: <reason>`` (one line per error)."""


CONTROLLERS = ("none", "stepping", "stepping_inertia")
# What each fall controller choice (`controller:` of a scenario) runs, in one place for the launcher (processes)
# and the in-process suite: the nodes that serve it, and the parameters it sets on them (params.<node>.<name>
# may not override these).
CONTROLLER_NODES: dict[str, list[str]] = {"none": [], "stepping": ["ftb_monitor", "safe_fall_controller"],
                                          "stepping_inertia": ["ftb_monitor", "safe_fall_controller"]}
CONTROLLER_PARAMS: dict[str, dict[str, dict]] = {
    "stepping": {"safe_fall_controller": {"inertia_shaping": False}},
    "stepping_inertia": {"safe_fall_controller": {"inertia_shaping": True}},
}
# Mux priorities of the built-in command sources (higher wins): a scenario's extra controllers must not reuse them.
BUILTIN_PRIORITIES = {"locomotion": 10, "estop": 20, "safe_fall": 30}
# Gait phases a push or an e-stop can be timed to (walking pattern: double support, then single support).
Phase = Literal["ds_start", "ds_mid", "ss_start", "ss_mid", "ss_end"]
PHASES: tuple[str, ...] = get_args(Phase)
_SIM_KEYS = ("physics_rate", "control_rate", "lockstep", "real_time_factor", "friction", "contact_breaking_threshold",
             "servo_time_constant")
# the bridge's parameter ranges (config/sim_bridge.yaml bounds)
SIM_RANGES = {k: params_mod.declarations("sim_bridge")[k].bounds for k in _SIM_KEYS
              if params_mod.declarations("sim_bridge")[k].bounds is not None}
SOURCE_NAME = re.compile(r"[a-z_][a-z0-9_]*")
MODULE_PATH = re.compile(r"[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*")
# Free-form maps: their keys are not in the schema, --set may add keys below them ("*": any list index).
FREE_MAPS = (("params",), ("robot", "initial_posture"), ("controllers", "*", "params"))


# ----------------------------------------------------------------- errors
class _Reason(ValueError):
    """A short reason, optionally for a key below the one pydantic reports (``sub``)."""

    def __init__(self, reason: str, sub: tuple = ()):
        super().__init__(reason)
        self.sub = tuple(sub)


class _UnknownKey(ValueError):
    def __init__(self, key: str, known: list[str]):
        super().__init__(f"unknown key {key}")
        self.key, self.known = key, known


def _dotted(loc) -> str:
    return ".".join(str(p) for p in loc)


def _short(err: dict) -> str:
    """'<dotted.path>: <short reason>' for one pydantic error."""
    loc = tuple(err["loc"])
    exc = (err.get("ctx") or {}).get("error")
    if isinstance(exc, _UnknownKey):
        return f"unknown key {_dotted((*loc, exc.key))} (known: {', '.join(exc.known)})"
    if isinstance(exc, _Reason):
        loc, reason = (*loc, *exc.sub), str(exc)
    elif err["type"] == "literal_error":
        reason = f"{err['input']!r} is not one of {err['ctx']['expected']}"
    elif err["type"] == "missing":
        reason = "required key missing"
    elif err["type"] == "list_type":
        reason = f"expected a list, got {type(err['input']).__name__}"
    elif err["type"] in ("model_type", "dict_type"):
        reason = f"expected a mapping, got {type(err['input']).__name__}"
    elif err["type"] == "extra_forbidden":
        return f"unknown key {_dotted(loc)}"
    elif exc is not None:
        reason = str(exc)
    else:
        reason = err["msg"]
    return f"{_dotted(loc) or 'scenario'}: {reason}"


def _scenario_error(e: ValidationError) -> ScenarioError:
    lines = [_short(err) for err in e.errors()]
    return ScenarioError(lines[0] if len(lines) == 1 else f"{len(lines)} errors:\n  " + "\n  ".join(lines))


# ----------------------------------------------------------------- value types
def _number(v: Any) -> float:
    if isinstance(v, str):
        try:  # YAML 1.1 reads 1e7 (no dot) as a string
            v = float(v)
        except ValueError:
            pass
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise _Reason(f"expected a number, got {v!r}")
    if not math.isfinite(float(v)):
        raise _Reason(f"non-finite number {v!r}")
    return float(v)


def _integer(v: Any) -> int:
    if isinstance(v, bool) or not isinstance(v, int):
        raise _Reason(f"expected an integer, got {v!r}")
    return v


def _string(v: Any) -> str:
    if not isinstance(v, str):
        raise _Reason(f"expected str, got {v!r}")
    return v


def _boolean(v: Any) -> bool:
    if not isinstance(v, bool):
        raise _Reason(f"expected bool, got {v!r}")
    return v


def _vector(n: int):
    def check(v: Any) -> list[float]:
        if not isinstance(v, (list, tuple)) or len(v) != n or \
                not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v):
            raise _Reason(f"expected a list of {n} numbers, got {v!r}")
        out = [float(x) for x in v]
        if not all(math.isfinite(x) for x in out):
            raise _Reason(f"non-finite number in {v!r}")
        return out
    return check


def _mapping(v: Any) -> dict:
    if not isinstance(v, dict):
        raise _Reason(f"expected a mapping, got {type(v).__name__}")
    return v


def _map_of(value_check):
    """A free-form map: any (string) key, each value checked by ``value_check`` (errors name the key)."""
    def check(v: Any) -> dict:
        out = {}
        for k, x in _mapping(v).items():
            try:
                out[str(k)] = value_check(x)
            except _Reason as r:
                raise _Reason(str(r), (str(k), *r.sub)) from None
        return out
    return check


Number = Annotated[float, PlainValidator(_number)]
Integer = Annotated[int, PlainValidator(_integer)]
String = Annotated[str, PlainValidator(_string)]
Boolean = Annotated[bool, PlainValidator(_boolean)]
Vec2 = Annotated[list[float], PlainValidator(_vector(2))]
Vec3 = Annotated[list[float], PlainValidator(_vector(3))]
Mapping = Annotated[dict[str, Any], PlainValidator(_mapping)]


def _at_least(lo: float, v, unit: str = ""):
    if v < lo:
        raise _Reason(f"{v}{unit} must be >= {lo}")
    return v


class _Section(BaseModel):
    """A mapping with a fixed set of keys: unknown keys are refused, ``null`` means all defaults."""

    model_config = ConfigDict(extra="forbid", validate_default=True)

    @model_validator(mode="before")
    @classmethod
    def _known_keys(cls, data: Any) -> Any:
        if data is None:
            return {}
        if isinstance(data, BaseModel):
            return data
        _mapping(data)
        unknown = sorted(str(k) for k in data if k not in cls.model_fields)
        if unknown:
            raise _UnknownKey(unknown[0], sorted(cls.model_fields))
        return data


# ----------------------------------------------------------------- robot facts
def _robot():
    from humfall_ros.model.humanoid import load_model  # pinocchio; cached

    return load_model()


def controller_module(node: str) -> str:
    """The python module a ``controllers.N.node`` runs: a bare name is a node of humfall_ros.nodes."""
    return node if "." in node else f"humfall_ros.nodes.{node}"


def _find_module(module: str) -> str | None:
    """None if ``python -m module`` started from this directory finds it, else why not.

    Walks the import path like the import system does, without importing anything; only for a module that
    no path entry holds (a meta-path finder's, e.g. an editable install) it asks importlib, which imports
    the parent packages.
    """
    search = [os.getcwd(), *sys.path]  # what `python -m` sees: the working directory first
    parts = module.split(".")
    for i, part in enumerate(parts):
        spec = PathFinder.find_spec(part, search)
        if spec is None:
            break
        if i == len(parts) - 1:
            return None
        search = list(spec.submodule_search_locations or [])
    try:
        if importlib.util.find_spec(module) is not None:
            return None
    except (ImportError, ValueError):
        pass
    if i > 0:  # a parent was found, but elsewhere (e.g. the stdlib's `test` package) or it is no package
        where = ", ".join(search) or "a module, not a package"
        return f"no module {module} ({'.'.join(parts[:i])} is {where})"
    return f"no module {module} (looked from {os.getcwd()})"


# ----------------------------------------------------------------- the schema
class GaitEvent(_Section):
    """A moment of the walking pattern: the given phase of step ``step`` (0 = the first step)."""

    step: Integer
    phase: Phase

    @field_validator("step")
    @classmethod
    def _step(cls, v: int) -> int:
        return _at_least(0, v)


class Push(_Section):
    """A force on a link for a while: world-frame force [N] at a point in the link frame [m]."""

    time: Number = 1.0               # [s] sim time the push starts (ignored when ``at`` is given)
    at: GaitEvent | None = None      # or: at this moment of the gait
    force: Vec3 = Field(default_factory=lambda: [0.0, 0.0, 0.0])   # [N] world frame
    point: Vec3 = Field(default_factory=lambda: [0.0, 0.0, 0.0])   # [m] link frame
    link: String = "chest"
    duration: Number = 0.1           # [s]

    @field_validator("time")
    @classmethod
    def _time(cls, v: float) -> float:
        return _at_least(0.0, v, " s")

    @field_validator("link")
    @classmethod
    def _link(cls, v: str) -> str:
        names = _robot().link_names
        if v not in names:
            raise _Reason(f"no link {v!r} (links: {', '.join(names)})")
        return v

    @model_validator(mode="after")
    def _sane(self) -> Push:
        reason = validate_push(self.force, self.point, self.duration)
        if reason:
            raise _Reason(reason)
        return self


class Obstacle(_Section):
    """A box on the ground: centre position [m], full extents [m], yaw [rad]."""

    name: String = "box"
    position: Vec3 = Field(default_factory=lambda: [0.0, 0.0, 0.0])
    size: Vec3 = Field(default_factory=lambda: [0.3, 0.3, 0.3])
    yaw: Number = 0.0
    is_target: Boolean = False

    @field_validator("size")
    @classmethod
    def _size(cls, v: list[float]) -> list[float]:
        if min(v) <= 0 or max(v) > 50:
            raise _Reason("each extent must be in (0, 50] m")
        return v


_BRIDGE = params_mod.defaults("sim_bridge")


class Sim(_Section):
    """The bridge's simulation settings (defaults and ranges: config/sim_bridge.yaml)."""

    physics_rate: Number = _BRIDGE["physics_rate"]            # [Hz]
    control_rate: Number = _BRIDGE["control_rate"]            # [Hz]
    lockstep: Boolean = _BRIDGE["lockstep"]
    real_time_factor: Number = _BRIDGE["real_time_factor"]    # 0 = as fast as possible
    friction: Number = _BRIDGE["friction"]
    contact_breaking_threshold: Number = _BRIDGE["contact_breaking_threshold"]   # [m], PyBullet's
    servo_time_constant: Number = _BRIDGE["servo_time_constant"]   # [s], the joint servos' position loop

    @field_validator(*SIM_RANGES)
    @classmethod
    def _in_range(cls, v: float, info: ValidationInfo) -> float:
        lo, hi = SIM_RANGES[info.field_name]
        if not lo <= v <= hi:
            raise _Reason(f"{v} is outside [{lo}, {hi}]")
        return v

    @model_validator(mode="after")
    def _substeps(self) -> Sim:
        ratio = self.physics_rate / self.control_rate
        if abs(ratio - round(ratio)) > 1e-9:
            raise _Reason(f"physics_rate ({self.physics_rate} Hz) must be a positive integer multiple of "
                          f"control_rate ({self.control_rate} Hz)")
        if self.servo_time_constant * self.physics_rate < 1.0:
            raise _Reason(f"servo_time_constant ({self.servo_time_constant} s) must be at least one physics step "
                          f"(1 / physics_rate = {1.0 / self.physics_rate} s)")
        return self


_LOCOMOTION = params_mod.declarations("locomotion")


def _gait_default(name: str, fallback: float) -> float:
    """The walking controller's declared default (config/locomotion.yaml), so the two never drift."""
    d = _LOCOMOTION.get(name)
    return float(d.default) if d is not None else fallback


class Walk(_Section):
    """What the walking controller is asked to do (it clamps the speed to what it can do, with a warning)."""

    start_time: Number = 0.0         # [s] sim time walking starts
    speed_kmh: Number = 0.0          # [km/h]
    direction_deg: Number = 0.0      # [deg] walking direction in the robot's initial frame, 0 = forward
    steps: Integer = 0               # number of steps, 0 = no walk
    step_period: Number = _gait_default("step_period", 0.8)         # [s] one step: double then single support
    double_support: Number = _gait_default("double_support", 0.1)   # [s] of each step
    turn_rate_deg_s: Number = 0.0    # [deg/s]

    @field_validator("start_time")
    @classmethod
    def _start(cls, v: float) -> float:
        return _at_least(0.0, v, " s")

    @field_validator("speed_kmh")
    @classmethod
    def _speed(cls, v: float) -> float:
        return _at_least(0.0, v, " km/h")

    @field_validator("steps")
    @classmethod
    def _steps(cls, v: int) -> int:
        return _at_least(0, v)

    @field_validator("step_period")
    @classmethod
    def _period(cls, v: float) -> float:
        if not 0.4 <= v <= 1.5:
            raise _Reason(f"{v} s is outside [0.4, 1.5]")
        return v

    @field_validator("double_support")
    @classmethod
    def _double_support(cls, v: float, info: ValidationInfo) -> float:
        period = info.data.get("step_period")
        if period is not None and not 0 < v < period:
            raise _Reason(f"{v} s must be in (0, step_period = {period} s)")
        d = _LOCOMOTION.get("double_support")
        if d is not None and d.bounds is not None and not d.bounds[0] <= v <= d.bounds[1]:
            raise _Reason(f"{v} s is outside [{d.bounds[0]}, {d.bounds[1]}] (locomotion's double_support)")
        return v


class Estop(_Section):
    """An e-stop: at a sim time, at a gait moment, or at a random time in a window (seeded)."""

    time: Number = -1.0              # [s] sim time, -1 = none
    at: GaitEvent | None = None      # or: at this moment of the gait
    random_window: Vec2 = Field(default_factory=lambda: [0.0, 0.0])   # [s] (lo, hi)
    seed: Integer = 0

    @field_validator("time")
    @classmethod
    def _time(cls, v: float) -> float:
        if v < 0 and v != -1.0:
            raise _Reason(f"{v} s must be >= 0, or -1 for no e-stop at a time")
        return v

    @field_validator("random_window")
    @classmethod
    def _window(cls, v: list[float]) -> list[float]:
        if not 0 <= v[0] <= v[1]:
            raise _Reason(f"{v} must be [lo, hi] with 0 <= lo <= hi")
        return v

    @model_validator(mode="after")
    def _one_trigger(self) -> Estop:
        if self.at is not None and self.time >= 0:
            raise _Reason(f"give time ({self.time} s) or at, not both")
        return self


class Robot(_Section):
    initial_posture: Annotated[dict[str, float], PlainValidator(_map_of(_number))] = Field(default_factory=dict)

    @field_validator("initial_posture")
    @classmethod
    def _joints(cls, v: dict[str, float]) -> dict[str, float]:
        names = _robot().joint_names
        unknown = sorted(set(v) - set(names))
        if unknown:
            raise _Reason(f"unknown joints {unknown} (joints: {', '.join(names)})")
        return v


class ControllerNode(_Section):
    """An extra lockstep controller node: its mux source name and priority (higher wins), its parameters."""

    node: String                     # a node of humfall_ros.nodes, a dotted module path or a .py file, with a main()
    source: String                   # joint_command/<source>
    priority: Integer
    params: Mapping = Field(default_factory=dict)

    @field_validator("node")
    @classmethod
    def _node(cls, v: str) -> str:
        if v.endswith(".py"):  # a script (e.g. a test-only controller node in test/)
            if not os.path.isfile(v):
                raise _Reason(f"no file {v} (looked from {os.getcwd()})")
            return os.path.abspath(v)  # the launcher's children may start elsewhere
        if not MODULE_PATH.fullmatch(v):
            raise _Reason(f"{v!r} is not a node name, a dotted module path or a .py file")
        why = _find_module(controller_module(v))
        if why:
            raise _Reason(why)
        return v

    @field_validator("source")
    @classmethod
    def _source(cls, v: str) -> str:
        if not SOURCE_NAME.fullmatch(v):
            raise _Reason(f"{v!r} is not a source name ([a-z_][a-z0-9_]*)")
        return v


class Scenario(_Section):
    name: String = ""
    description: String = ""
    duration: Number = 5.0           # [s] sim time
    controller: Literal[CONTROLLERS] = "none"
    controllers: list[ControllerNode] = Field(default_factory=list)
    robot: Robot = Field(default_factory=Robot)
    push: list[Push] = Field(default_factory=list)
    obstacles: list[Obstacle] = Field(default_factory=list)
    sim: Sim = Field(default_factory=Sim)
    walk: Walk = Field(default_factory=Walk)
    estop: Estop = Field(default_factory=Estop)
    params: Annotated[dict[str, dict], PlainValidator(_map_of(_mapping))] = Field(default_factory=dict)

    @field_validator("duration")
    @classmethod
    def _duration(cls, v: float) -> float:
        if v <= 0 or v > 3600:
            raise _Reason(f"{v} s must be in (0, 3600]")
        return v

    @field_validator("controllers")
    @classmethod
    def _distinct(cls, v: list[ControllerNode]) -> list[ControllerNode]:
        """No two sources (built-in or listed) share a name or a priority."""
        seen = [(f"the built-in source {s!r} (priority {p})", s, p) for s, p in BUILTIN_PRIORITIES.items()]
        for i, c in enumerate(v):
            for who, source, priority in seen:
                if source == c.source:
                    raise _Reason(f"source {c.source!r} (priority {c.priority}) clashes with {who}: "
                                  "source names must differ", (i,))
                if priority == c.priority:
                    raise _Reason(f"priority {c.priority} (source {c.source!r}) clashes with {who}: "
                                  "priorities must differ", (i,))
            seen.append((f"controllers.{i} (source {c.source!r}, priority {c.priority})", c.source, c.priority))
        return v

    @field_validator("obstacles")
    @classmethod
    def _unique(cls, v: list[Obstacle]) -> list[Obstacle]:
        names = [o.name for o in v]
        twice = sorted({n for n in names if names.count(n) > 1})
        if twice:
            raise _Reason(f"names must be unique ({', '.join(map(repr, twice))} more than once)")
        return v


# ----------------------------------------------------------------- public API
def validate(data: dict) -> dict:
    """A complete, normalised scenario (plain dict) from a parsed file, or ScenarioError."""
    try:
        return Scenario.model_validate(data).model_dump()
    except ValidationError as e:
        raise _scenario_error(e) from None


def load(name_or_path: str, overrides: list[str] | None = None) -> dict:
    """Load a scenario by name (config/scenarios/NAME.yaml) or path, apply ``--set`` overrides."""
    p = paths.scenario_path(name_or_path)
    if not p.is_file():
        available = sorted(x.stem for x in p.parent.glob("*.yaml")) if p.parent.is_dir() else []
        raise ScenarioError(f"no scenario {name_or_path!r} (available: {', '.join(available)})")
    try:
        data = yaml.safe_load(p.read_text()) or {}
    except yaml.YAMLError as e:
        raise ScenarioError(f"{p}: not valid YAML: {e}") from e
    sc = validate(data)
    if not sc["name"]:
        sc["name"] = p.stem
    for ov in overrides or []:
        sc = apply_override(sc, ov)
    return sc


def _free(parts: list[str], depth: int) -> bool:
    """Whether ``parts[depth]`` is a key of a free-form map (so it may be new)."""
    for pattern in FREE_MAPS:
        n = len(pattern)
        if depth >= n and all(a == "*" or a == b for a, b in zip(pattern, parts[:n])):
            return True
    return False


def apply_override(sc: dict, assignment: str) -> dict:
    """Apply ``dotted.key=value`` (value parsed as YAML) and revalidate.

    The key must exist, except below a free-form map (:data:`FREE_MAPS`: ``params.*``,
    ``robot.initial_posture.*``, ``controllers.N.params.*``), where it may be new.
    """
    if "=" not in assignment:
        raise ScenarioError(f"--set {assignment!r}: expected dotted.key=value")
    key, raw = assignment.split("=", 1)
    try:
        value = yaml.safe_load(raw)
    except yaml.YAMLError as e:
        raise ScenarioError(f"--set {key}: cannot parse value {raw!r}: {e}") from e
    parts = key.strip().split(".")
    data = copy.deepcopy(sc)
    node: Any = data
    for i, part in enumerate(parts):
        here = ".".join(parts[: i + 1])
        if isinstance(node, list):
            if not part.isdigit() or int(part) >= len(node):
                raise ScenarioError(f"--set {key}: no list item {here}")
            part = int(part)
        elif isinstance(node, dict):
            if part not in node and not _free(parts, i):
                raise ScenarioError(f"--set {key}: no such key {here}")
        elif node is None:
            where = ".".join(parts[:i])
            raise ScenarioError(f"--set {key}: {where} is null; set it whole, e.g. --set '{where}={{...}}'")
        else:
            raise ScenarioError(f"--set {key}: {'.'.join(parts[:i])} is not a mapping or list")
        if i == len(parts) - 1:
            node[part] = value
        else:
            if isinstance(node, dict) and part not in node:
                node[part] = {}
            node = node[part]
    return validate(data)


def dump(sc: dict) -> str:
    return yaml.safe_dump(sc, sort_keys=False)


def walks(sc: dict) -> bool:
    """The scenario schedules a walk (``walk.steps`` > 0 at a speed > 0)."""
    w = sc.get("walk") or {}
    return w.get("steps", 0) > 0 and w.get("speed_kmh", 0.0) > 0


def push_time(sc: dict, push: dict) -> float:
    """When a scenario push begins [s]: its ``time``, or the gait event ``at`` of the scenario's walk.

    The gait is planned deterministically from the scenario (humfall_ros.walking.scenario),
    so a push at ``{step: K, phase: ss_start}`` is an absolute time known before the run,
    the same in process and over ROS.
    """
    if push.get("at") is None:
        return float(push["time"])
    from humfall_ros.walking.scenario import phase_time

    return float(phase_time(sc, push["at"]))


def node_defaults(sc: dict, node: str) -> dict[str, Any]:
    """A node's parameter values that follow from what the scenario contains.

    They sit between the node's declared defaults and the scenario's ``params.<node>``,
    which may still override them (``humfall up`` and the in-process loop apply them alike):
    a scenario that walks gives the fall trigger boundary the gait reference
    (``ftb_monitor.use_walking_state``), since the standing boundary fires in normal steps
    (docs/safe_fall.md: at 2.9 s of a 1.0 km/h walk), and one that runs the e-stop the stop's
    reference (``use_estop_status``: the standing boundary fired 12 ms into an unpushed stop).
    A pushed scenario gives the boundary's ``fixed`` mode (paper 1 §V-A: the controller starts
    0.05 s after the push ends) the end of its first push (``push_end_time_s``).
    """
    out: dict[str, Any] = {}
    if node == "ftb_monitor" and sc.get("push"):
        first = min(sc["push"], key=lambda p: push_time(sc, p))
        out["push_end_time_s"] = float(push_time(sc, first) + first["duration"])
    if node == "ftb_monitor" and walks(sc):
        out["use_walking_state"] = True
    if node == "ftb_monitor" and runs_estop(sc):
        out["use_estop_status"] = True  # a stop is referenced to its own plan, not to the standing boundary
    return out


def runs_estop(sc: dict) -> bool:
    """``humfall up`` starts the e-stop (``estop_planner``): the scenario walks or schedules a trigger."""
    from humfall_ros.estop.config import trigger_params

    return walks(sc) or bool(trigger_params(sc.get("estop") or {}))
