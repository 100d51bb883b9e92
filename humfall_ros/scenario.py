"""Scenario files (config/scenarios/*.yaml): schema, validation and overrides.

A scenario says what world the robot is in, what happens to it and how long
the run lasts. Unknown keys and wrong types are refused with the dotted path
of the offending key, so a typo never silently runs the wrong experiment.
"""
from __future__ import annotations

import copy
import math
from typing import Any

import yaml

from humfall_ros import paths


class ScenarioError(ValueError):
    pass


NUM = (int, float)
VEC3 = ("vec", 3)

# A schema is a dict of key -> (type, default). Types: python types/tuples,
# VEC3, ("list", item_schema), ("dict", schema), ("map", value_type) for free-form maps.
PUSH = {
    "time": (NUM, 1.0),
    "force": (VEC3, [0.0, 0.0, 0.0]),
    "point": (VEC3, [0.0, 0.0, 0.0]),
    "link": (str, "chest"),
    "duration": (NUM, 0.1),
}
OBSTACLE = {
    "name": (str, "box"),
    "position": (VEC3, [0.0, 0.0, 0.0]),
    "size": (VEC3, [0.3, 0.3, 0.3]),
    "yaw": (NUM, 0.0),
    "is_target": (bool, False),
}
SIM = {
    "physics_rate": (NUM, 1000.0),
    "control_rate": (NUM, 500.0),
    "lockstep": (bool, True),
    "real_time_factor": (NUM, 1.0),
    "friction": (NUM, 0.9),
}
WALK = {
    "start_time": (NUM, 0.0),
    "speed_kmh": (NUM, 0.0),
    "direction_deg": (NUM, 0.0),
}
ESTOP = {
    "time": (NUM, -1.0),
    "random_window": (("vec", 2), [0.0, 0.0]),
    "seed": (int, 0),
}
SCHEMA = {
    "name": (str, ""),
    "description": (str, ""),
    "duration": (NUM, 5.0),
    "controller": (str, "none"),
    "robot": (("dict", {"initial_posture": (("map", NUM), {})}), {}),
    "push": (("list", PUSH), []),
    "obstacles": (("list", OBSTACLE), []),
    "sim": (("dict", SIM), {}),
    "walk": (("dict", WALK), {}),
    "estop": (("dict", ESTOP), {}),
    "params": (("map", dict), {}),
}

CONTROLLERS = ("none", "stepping", "stepping_inertia")
# the bridge's parameter ranges (config/sim_bridge.yaml descriptors)
SIM_RANGES = {"physics_rate": (100.0, 10000.0), "control_rate": (10.0, 2000.0),
              "real_time_factor": (0.0, 100.0), "friction": (0.05, 3.0)}


def _type_name(t) -> str:
    if t is NUM:
        return "number"
    if isinstance(t, tuple) and t and t[0] == "vec":
        return f"list of {t[1]} numbers"
    if isinstance(t, tuple) and t and t[0] == "list":
        return "list"
    if isinstance(t, tuple) and t and t[0] in ("dict", "map"):
        return "mapping"
    return getattr(t, "__name__", str(t))


def _check(value, typ, path: str):
    """Validate and normalise one value against a schema type."""
    if isinstance(typ, tuple) and typ and typ[0] == "vec":
        if not isinstance(value, (list, tuple)) or len(value) != typ[1] or \
                not all(isinstance(v, NUM) and not isinstance(v, bool) for v in value):
            raise ScenarioError(f"{path}: expected a {_type_name(typ)}, got {value!r}")
        out = [float(v) for v in value]
        if not all(math.isfinite(v) for v in out):
            raise ScenarioError(f"{path}: non-finite number in {value!r}")
        return out
    if isinstance(typ, tuple) and typ and typ[0] == "list":
        if not isinstance(value, list):
            raise ScenarioError(f"{path}: expected a list, got {type(value).__name__}")
        return [_fill(item, typ[1], f"{path}.{i}") for i, item in enumerate(value)]
    if isinstance(typ, tuple) and typ and typ[0] == "dict":
        return _fill(value, typ[1], path)
    if isinstance(typ, tuple) and typ and typ[0] == "map":
        if not isinstance(value, dict):
            raise ScenarioError(f"{path}: expected a mapping, got {type(value).__name__}")
        return {str(k): _check(v, typ[1], f"{path}.{k}") for k, v in value.items()}
    if typ is NUM:
        if isinstance(value, str):
            try:  # YAML 1.1 reads 1e7 (no dot) as a string
                value = float(value)
            except ValueError:
                pass
        if isinstance(value, bool) or not isinstance(value, NUM):
            raise ScenarioError(f"{path}: expected a number, got {value!r}")
        if not math.isfinite(float(value)):
            raise ScenarioError(f"{path}: non-finite number {value!r}")
        return float(value)
    if typ is int and (isinstance(value, bool) or not isinstance(value, int)):
        raise ScenarioError(f"{path}: expected an integer, got {value!r}")
    if not isinstance(value, typ):
        raise ScenarioError(f"{path}: expected {_type_name(typ)}, got {value!r}")
    return value


def _fill(data, schema: dict, path: str) -> dict:
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ScenarioError(f"{path or 'scenario'}: expected a mapping, got {type(data).__name__}")
    unknown = set(data) - set(schema)
    if unknown:
        where = f"{path}." if path else ""
        raise ScenarioError(f"unknown key {where}{sorted(unknown)[0]} (known: {', '.join(sorted(schema))})")
    out = {}
    for key, (typ, default) in schema.items():
        sub = f"{path}.{key}" if path else key
        out[key] = _check(data[key], typ, sub) if key in data else _check(copy.deepcopy(default), typ, sub)
    return out


def validate(data: dict) -> dict:
    """A complete, normalised scenario from a parsed file, or ScenarioError."""
    sc = _fill(data, SCHEMA, "")
    if sc["duration"] <= 0 or sc["duration"] > 3600:
        raise ScenarioError(f"duration: {sc['duration']} s must be in (0, 3600]")
    if sc["controller"] not in CONTROLLERS:
        raise ScenarioError(f"controller: {sc['controller']!r} is not one of {', '.join(CONTROLLERS)}")
    sim = sc["sim"]
    if sim["physics_rate"] <= 0 or sim["control_rate"] <= 0 or \
            abs(sim["physics_rate"] / sim["control_rate"] - round(sim["physics_rate"] / sim["control_rate"])) > 1e-9:
        raise ScenarioError("sim: physics_rate must be a positive integer multiple of control_rate")
    for key, (lo, hi) in SIM_RANGES.items():
        if not lo <= sim[key] <= hi:
            raise ScenarioError(f"sim.{key}: {sim[key]} is outside [{lo}, {hi}]")
    # robot facts come from the URDF: links that can be pushed, joints of the posture
    from humfall_ros.model.humanoid import load_model
    from humfall_ros.sim.world import validate_push

    model = load_model()
    for i, p in enumerate(sc["push"]):
        reason = validate_push(p["force"], p["point"], p["duration"])
        if reason:
            raise ScenarioError(f"push.{i}: {reason}")
        if p["link"] not in model.link_names:
            raise ScenarioError(f"push.{i}.link: no link {p['link']!r} (links: {', '.join(model.link_names)})")
        if p["time"] < 0:
            raise ScenarioError(f"push.{i}.time must be >= 0")
    unknown = set(sc["robot"]["initial_posture"]) - set(model.joint_names)
    if unknown:
        raise ScenarioError(f"robot.initial_posture: unknown joints {sorted(unknown)}")
    names = [o["name"] for o in sc["obstacles"]]
    if len(set(names)) != len(names):
        raise ScenarioError("obstacles: names must be unique")
    for i, o in enumerate(sc["obstacles"]):
        if min(o["size"]) <= 0 or max(o["size"]) > 50:
            raise ScenarioError(f"obstacles.{i}.size: each extent must be in (0, 50] m")
    return sc


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


def apply_override(sc: dict, assignment: str) -> dict:
    """Apply ``dotted.key=value`` (value parsed as YAML) and revalidate."""
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
        last = i == len(parts) - 1
        here = ".".join(parts[: i + 1])
        if isinstance(node, list):
            if not part.isdigit() or int(part) >= len(node):
                raise ScenarioError(f"--set {key}: no list item {here}")
            part = int(part)
        elif isinstance(node, dict):
            # free-form maps (params, initial_posture) may gain keys
            free = parts[0] == "params" or (len(parts) >= 2 and parts[:2] == ["robot", "initial_posture"])
            if part not in node and not (free and i >= (1 if parts[0] == "params" else 2)):
                raise ScenarioError(f"--set {key}: no such key {here}")
        else:
            raise ScenarioError(f"--set {key}: {'.'.join(parts[:i])} is not a mapping or list")
        if last:
            node[part] = value
        else:
            if isinstance(node, dict) and part not in node:
                node[part] = {}
            node = node[part]
    return validate(data)


def dump(sc: dict) -> str:
    return yaml.safe_dump(sc, sort_keys=False)
