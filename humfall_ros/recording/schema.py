"""ROS 2 message definitions as MCAP ``ros2msg`` schemas.

The schema of a channel is what rosbag2 writes, so that every ROS-aware MCAP
reader (mcap_ros2, rosbags, Foxglove) can decode our bags without our Python
packages: the root type's ``.msg`` text, then for each nested type (recursively,
each once, in first-use order) a separator line of 80 ``=``, a line
``MSG: pkg/msg/Type`` and that type's ``.msg`` text.

``.msg`` texts come from ``<share>/<pkg>/msg/<Type>.msg`` (the interface
packages install them there). If a text is missing but the Python type can be
imported (a type from an overlay without share files, say), the definition is
rebuilt from the rosidl introspection data of the Python class: comments and
constants are lost, the wire layout is the same.

Plain Python: no rclpy at import time; the introspection fallback imports the
message module only when it is needed.
"""
from __future__ import annotations

import importlib
import pathlib
import re
from typing import Callable

from humfall_ros import paths

SEPARATOR = "=" * 80
SCHEMA_ENCODING = "ros2msg"
MESSAGE_ENCODING = "cdr"

PRIMITIVES = frozenset({
    "bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16",
    "int32", "uint32", "int64", "uint64", "string", "wstring",
})

# rosidl introspection names (``get_fields_and_field_types``) -> .msg names.
_IDL_TO_MSG = {
    "boolean": "bool", "octet": "byte", "float": "float32", "double": "float64",
    "int8": "int8", "uint8": "uint8", "int16": "int16", "uint16": "uint16",
    "int32": "int32", "uint32": "uint32", "int64": "int64", "uint64": "uint64",
    "char": "char", "string": "string", "wstring": "wstring",
}

# "string<=10[<=3]" -> base "string<=10"; array suffixes: [], [N], [<=N]
_ARRAY_RE = re.compile(r"\[(<=)?\d*\]$")


class SchemaError(LookupError):
    """A message definition (or one of its nested types) cannot be found."""


def split_type_name(type_name: str) -> tuple[str, str]:
    """``pkg/msg/Type`` or ``pkg/Type`` -> (pkg, Type)."""
    parts = type_name.strip("/").split("/")
    if len(parts) == 3 and parts[1] == "msg":
        return parts[0], parts[2]
    if len(parts) == 2:
        return parts[0], parts[1]
    raise SchemaError(f"not a message type name: {type_name!r}")


def full_type_name(type_name: str) -> str:
    pkg, name = split_type_name(type_name)
    return f"{pkg}/msg/{name}"


def _base_type(token: str) -> str:
    """Field type token without array suffix and string bound."""
    base = _ARRAY_RE.sub("", token)
    return base.split("<=")[0]


def nested_types(msg_text: str, package: str) -> list[str]:
    """Full names of the non-primitive field types of one ``.msg`` text, in order.

    Constants (``TYPE NAME=VALUE``) are primitives and so never nested.
    A bare ``Type`` is relative to ``package``; ``Header`` is std_msgs/Header
    (the only legacy alias rosidl still accepts).
    """
    out: list[str] = []
    for line in msg_text.splitlines():
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        token = line.split()[0]
        base = _base_type(token)
        if base in PRIMITIVES:
            continue
        if "/" in base:
            name = full_type_name(base)
        elif base == "Header":
            name = "std_msgs/msg/Header"
        else:
            name = f"{package}/msg/{base}"
        if name not in out:
            out.append(name)
    return out


def msg_file(type_name: str) -> pathlib.Path | None:
    """The installed ``.msg`` file of a type, or None."""
    pkg, name = split_type_name(type_name)
    share = paths.interface_share_dir(pkg)
    if share is None:
        return None
    f = share / "msg" / f"{name}.msg"
    return f if f.is_file() else None


def _idl_field_to_msg(idl: str) -> str:
    """One introspection type string -> a ``.msg`` field type."""
    m = re.fullmatch(r"sequence<(.+?)(?:, (\d+))?>", idl)
    if m:
        inner, bound = m.group(1), m.group(2)
        return _idl_field_to_msg(inner) + (f"[<={bound}]" if bound else "[]")
    m = re.fullmatch(r"(.+)\[(\d+)\]", idl)
    if m:
        return _idl_field_to_msg(m.group(1)) + f"[{m.group(2)}]"
    m = re.fullmatch(r"(w?string)<(\d+)>", idl)
    if m:
        return f"{m.group(1)}<={m.group(2)}"
    if idl in _IDL_TO_MSG:
        return _IDL_TO_MSG[idl]
    if "/" in idl:  # "geometry_msgs/Point"
        return idl
    raise SchemaError(f"cannot express introspection type {idl!r} in .msg syntax")


def msg_text_from_python(type_name: str) -> str:
    """Rebuild a ``.msg`` text from the generated Python class (fallback)."""
    pkg, name = split_type_name(type_name)
    try:
        module = importlib.import_module(f"{pkg}.msg")
        cls = getattr(module, name)
        fields = cls.get_fields_and_field_types()
    except (ImportError, AttributeError) as exc:
        raise SchemaError(f"no .msg file and no Python type for {type_name}: {exc}") from exc
    lines = ["# rebuilt from the rosidl Python type (no .msg file installed)"]
    lines += [f"{_idl_field_to_msg(t)} {f}" for f, t in fields.items()]
    return "\n".join(lines) + "\n"


def default_loader(type_name: str) -> str:
    """The ``.msg`` text of ``type_name`` from the share dirs, else from Python."""
    f = msg_file(type_name)
    if f is not None:
        return f.read_text()
    return msg_text_from_python(type_name)


def build_schema(type_name: str, loader: Callable[[str], str] = default_loader) -> str:
    """The ``ros2msg`` schema text of ``type_name`` (see module docstring).

    ``loader(full_name) -> .msg text`` is injectable so tests need no install.
    Raises SchemaError if the root or any nested type cannot be loaded.
    """
    root = full_type_name(type_name)
    texts: dict[str, str] = {}
    order: list[str] = []

    def visit(name: str) -> None:
        if name in texts:
            return
        try:
            text = loader(name)
        except SchemaError:
            raise
        except Exception as exc:  # noqa: BLE001 - any loader failure is "no schema"
            raise SchemaError(f"cannot load {name}: {exc}") from exc
        texts[name] = text
        order.append(name)
        for dep in nested_types(text, split_type_name(name)[0]):
            visit(dep)

    visit(root)
    parts = [texts[root].rstrip("\n")]
    for name in order[1:]:
        body = texts[name].rstrip("\n")
        parts.append(f"{SEPARATOR}\nMSG: {name}\n{body}")
    return "\n".join(parts) + "\n"


def schema_types(schema_text: str) -> list[str]:
    """Names of the nested types listed in a ``ros2msg`` schema (for tests/info)."""
    return [line[5:].strip() for line in schema_text.splitlines() if line.startswith("MSG: ")]

