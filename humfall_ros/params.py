"""Node parameter declarations: one source per parameter (no rclpy here).

Each node's parameters are declared once in ``config/<node>.yaml``, in the shape
of generate_parameter_library's YAML::

    locomotion:
      ankle_kp:
        type: double
        default_value: 0.3
        description: "ankle offset per metre of CoM error [rad/m]"
        validation:
          bounds<>: [0.0, 20.0]

The node declares them from here (``nodes/common.Params``), the launcher checks
scenario overrides against them, and in-process users (tests, benchmarks, the
in-process loop) read the same defaults through :func:`defaults`.
"""
from __future__ import annotations

import dataclasses
import functools
import math
import re
from typing import Any

import yaml

from humfall_ros import paths

# a float with an exponent and no dot ('1e-4'): YAML 1.2 reads a float, PyYAML (YAML 1.1) a string
_YAML12_FLOAT = re.compile(r"[-+]?(\.[0-9]+|[0-9]+(\.[0-9]*)?)[eE][-+]?[0-9]+")

TYPES = ("bool", "int", "double", "string", "bool_array", "int_array", "double_array", "string_array")


class ParamError(ValueError):
    """A parameter declaration or value is wrong; the message names node and parameter."""


@dataclasses.dataclass(frozen=True)
class Declaration:
    """One parameter: its type, default, description and range.

    Attributes:
        name: parameter name.
        type: one of :data:`TYPES`.
        default: default value, of that type.
        description: what it is, with its unit.
        bounds: inclusive (low, high) for numbers (and each element of a number array), or None.
        read_only: may not change after start.
        choices: the allowed values of a string (``validation: {one_of<>: [[a, b]]}``), or None.
    """

    name: str
    type: str
    default: Any
    description: str
    bounds: tuple[float, float] | None = None
    read_only: bool = False
    choices: tuple[str, ...] | None = None

    def check(self, value: Any, where: str = "") -> Any:
        """``value`` typed like this declaration (an int for a double becomes a float), or ParamError."""
        where = where or self.name
        base = self.type.removesuffix("_array")
        if self.type.endswith("_array"):
            if not isinstance(value, (list, tuple)):
                raise ParamError(f"{where}: expected a list ({self.type}), got {value!r}")
            return [self._scalar(base, v, f"{where}[{i}]") for i, v in enumerate(value)]
        return self._scalar(base, value, where)

    def _scalar(self, base: str, v: Any, where: str) -> Any:
        like = f" like {self.default!r}" if self.default is not None else ""
        if base == "bool":
            if not isinstance(v, bool):
                raise ParamError(f"{where}: expected bool{like}, got {v!r}")
            return v
        if base == "string":
            if not isinstance(v, str):
                raise ParamError(f"{where}: expected string{like}, got {v!r}")
            if self.choices is not None and v not in self.choices:
                raise ParamError(f"{where}: {v!r} is not one of {', '.join(self.choices)}")
            return v
        if base == "double" and isinstance(v, str) and _YAML12_FLOAT.fullmatch(v.strip()):
            v = float(v)        # PyYAML reads YAML 1.1: '1e-4' (no dot) is a string there, a float in YAML 1.2
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise ParamError(f"{where}: expected {'int' if base == 'int' else 'double (a number)'}{like}, got {v!r}")
        if base == "int":
            if not isinstance(v, int):
                raise ParamError(f"{where}: expected int{like}, got {v!r}")
        else:
            v = float(v)
            if not math.isfinite(v):
                raise ParamError(f"{where}: non-finite value {v!r}")
        if self.bounds is not None and not self.bounds[0] <= v <= self.bounds[1]:
            raise ParamError(f"{where}: {v!r} is outside [{self.bounds[0]}, {self.bounds[1]}]")
        return v


def _parse(node: str, name: str, spec: Any) -> Declaration:
    where = f"config/{node}.yaml: {name}"
    if not isinstance(spec, dict) or "type" not in spec or "default_value" not in spec:
        raise ParamError(f"{where}: expected a mapping with type, default_value and description")
    unknown = set(spec) - {"type", "default_value", "description", "validation", "read_only"}
    if unknown:
        raise ParamError(f"{where}: unknown keys {sorted(unknown)}")
    if spec["type"] not in TYPES:
        raise ParamError(f"{where}: type {spec['type']!r} is not one of {', '.join(TYPES)}")
    if not spec.get("description"):
        raise ParamError(f"{where}: every parameter needs a description")
    bounds = None
    validation = spec.get("validation") or {}
    unknown = set(validation) - {"bounds<>", "one_of<>"}
    if unknown:
        raise ParamError(f"{where}: unsupported validation {sorted(unknown)} (only bounds<> and one_of<>)")
    choices = None
    if "one_of<>" in validation:
        if not spec["type"].startswith("string"):
            raise ParamError(f"{where}: one_of<> is for strings")
        choices = tuple(str(c) for c in validation["one_of<>"][0])
    if "bounds<>" in validation:
        lo, hi = validation["bounds<>"]
        bounds = (lo, hi) if spec["type"].startswith("int") else (float(lo), float(hi))
    d = Declaration(name, spec["type"], None, str(spec["description"]), bounds, bool(spec.get("read_only", False)),
                    choices)
    return dataclasses.replace(d, default=d.check(spec["default_value"], where))


@functools.lru_cache(maxsize=None)
def declarations(node: str) -> dict[str, Declaration]:
    """The declarations of ``config/<node>.yaml`` in file order (empty if the node has no file)."""
    p = paths.config_path(f"{node}.yaml")
    if not p.is_file():
        return {}
    data = yaml.safe_load(p.read_text()) or {}
    if set(data) - {node}:
        raise ParamError(f"config/{node}.yaml: top-level keys must be just {node!r}, got {sorted(data)}")
    return {name: _parse(node, name, spec) for name, spec in (data.get(node) or {}).items()}


def defaults(node: str) -> dict[str, Any]:
    """Default values of a node's parameters (a fresh dict: callers may modify it)."""
    return {n: (list(d.default) if isinstance(d.default, list) else d.default)
            for n, d in declarations(node).items()}


def check_overrides(node: str, values: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """Typed copies of ``values`` for ``node``; ParamError on an unknown name, type or range."""
    decl = declarations(node)
    out = {}
    for key, value in values.items():
        where = f"{prefix}{key}"
        if key not in decl:
            raise ParamError(f"{where}: {node} has no parameter {key!r} (known: {', '.join(sorted(decl))})")
        out[key] = decl[key].check(value, where)
    return out


__all__ = ["Declaration", "ParamError", "check_overrides", "declarations", "defaults"]


def config_from(cls: type, values: dict[str, Any], where: str | None = None, ignore: tuple[str, ...] = ()):
    """``cls(**values)`` for a config dataclass built from declared parameters.

    A key that is not a field of ``cls`` is refused (ParamError naming every such key), never
    dropped: a misspelt parameter must not silently run another controller. Keys in ``ignore``
    (a node's own parameters, which its config does not carry) are left out first. Missing keys
    take the dataclass defaults; the dataclass's ``__post_init__`` does its own checks.
    """
    names = {f.name for f in dataclasses.fields(cls)}
    kept = {k: v for k, v in values.items() if k not in ignore}
    unknown = sorted(set(kept) - names)
    if unknown:
        raise ParamError(f"{where or cls.__name__}: unknown parameters {unknown} (a {cls.__name__} has "
                         f"{', '.join(sorted(names))})")
    return cls(**kept)


def parse_overrides(text: str) -> dict:
    """``name=value,...`` by a node's yaml parameter names (values parsed as YAML; lists in [] with ';'): the
    ``--set`` of the benchmarks and of ``multicontact.build_library``."""
    out = {}
    for kv in filter(None, text.split(",")):
        k, v = kv.split("=", 1)
        out[k.strip()] = yaml.safe_load(v.replace(";", ","))
    return out
