"""Fast decoding of ROS 2 messages from their CDR bytes, for the suite's per-tick topics. No rclpy.

Why: taking a message through rclpy builds it through the generated Python classes, whose
constructors and property setters check every field; for ``CentroidalState`` (a dozen nested
``Point``/``Vector3``/``Header``/``Time`` objects) that is ~0.1 ms a message, and a controller
node takes four such messages a tick: profiled (CPU time), it was 60 % of the locomotion node's
CPU and 40 % of the estimator's. A raw take (the serialized bytes) decoded here costs a few
microseconds.

:func:`decoder` compiles, once per message class, a Python function from the class's own field
list (``get_fields_and_field_types``, the rosidl introspection every generated class carries):
runs of fixed-size fields become one precompiled ``struct`` read with their CDR padding, arrays
of numbers one ``numpy.frombuffer``. Decoded messages are :class:`types.SimpleNamespace` trees
with the message's field names, so code that reads ``msg.header.stamp.sec`` or ``msg.com.x``
reads them unchanged; numeric sequences and fixed arrays are numpy arrays (rclpy gives
``array.array`` for sequences), strings ``str``. They are read-only views of what arrived, not
messages: do not publish them or assign their parts into real messages.

The wire format is XCDR1, little endian (what rmw_fastrtps writes): a 4-byte encapsulation
header, then the fields in order, each primitive aligned to its size relative to the end of
that header; strings and sequences carry a uint32 length (strings count their NUL).
``test_cdr.py`` checks every decoder against rclpy's ``deserialize_message``.
"""
from __future__ import annotations

import importlib
import struct
import types
from typing import Any, Callable

import numpy as np

# rosidl type name -> (struct code, size); the alignment is the size
PRIMITIVES: dict[str, tuple[str, int]] = {
    "double": ("d", 8), "float": ("f", 4), "int64": ("q", 8), "uint64": ("Q", 8), "int32": ("i", 4),
    "uint32": ("I", 4), "int16": ("h", 2), "uint16": ("H", 2), "int8": ("b", 1), "uint8": ("B", 1),
    "byte": ("B", 1), "octet": ("B", 1), "char": ("B", 1), "boolean": ("?", 1),
}
CDR_LE = (0, 1)  # encapsulation identifier of little-endian plain CDR

_cache: dict[type, Callable[[Any], Any]] = {}


class UnsupportedType(TypeError):
    """A field type this decoder does not handle (e.g. wstring); use rclpy's deserialisation."""


def decoder(msg_class: type) -> Callable[[Any], Any]:
    """``decode(data) -> SimpleNamespace`` for serialized messages of ``msg_class`` (bytes or a buffer).

    Raises UnsupportedType at compile time for types it cannot decode, ValueError on data that is
    not little-endian CDR or is too short."""
    fn = _cache.get(msg_class)
    if fn is None:
        fn = _cache[msg_class] = _Compiler().compile_top(msg_class)
    return fn


def _msg_class(type_name: str) -> type:
    pkg, _, name = type_name.partition("/")
    if "/" in name:  # pkg/msg/Name
        name = name.rsplit("/", 1)[1]
    return getattr(importlib.import_module(f"{pkg}.msg"), name)


def _split_type(t: str) -> tuple[str, str, int | None]:
    """('sequence' | 'array' | 'single', element type, length) of a rosidl field type string."""
    if t.startswith("sequence<"):
        inner = t[len("sequence<"):-1]
        return "sequence", inner.split(",")[0].strip(), None  # a bound does not change the wire format
    if t.endswith("]") and "[" in t:
        base, n = t[:-1].split("[")
        return "array", base, int(n)
    return "single", t, None


def _is_string(t: str) -> bool:
    return t == "string" or t.startswith("string<")


class _Compiler:
    def __init__(self):
        self.lines: list[str] = []
        self.env: dict[str, Any] = {"np": np, "NS": types.SimpleNamespace}
        self.n = 0
        self.group: list[tuple[str, str]] = []  # (struct code incl. padding, variable or '')
        self.group_align = 0
        self.group_off = 0
        self.helpers: dict[type, str] = {}

    def var(self) -> str:
        self.n += 1
        return f"v{self.n}"

    # ------------------------------------------------------------ fixed-size runs
    def prim(self, t: str) -> str:
        code, size = PRIMITIVES[t]
        if self.group and size > self.group_align:
            self.flush()
        if not self.group:
            self.group_align, self.group_off = size, 0
        pad = -self.group_off % size
        v = self.var()
        self.group.append(("x" * pad + code, v))
        self.group_off += pad + size
        return v

    def flush(self) -> None:
        if not self.group:
            return
        fmt = "<" + "".join(c for c, _ in self.group)
        s = struct.Struct(fmt)
        name = f"S{len(self.env)}"
        self.env[name] = s
        names = [v for _, v in self.group]
        if self.group_align > 1:
            self.emit(f"pos = (pos + {self.group_align - 1}) & -{self.group_align}")
        self.emit(f"{', '.join(names)}, = {name}.unpack_from(mv, pos)")
        self.emit(f"pos += {s.size}")
        self.group, self.group_align, self.group_off = [], 0, 0

    def emit(self, line: str) -> None:
        self.lines.append("    " + line)

    # ------------------------------------------------------------ variable-size parts
    def string(self) -> str:
        self.flush()
        v = self.var()
        self.emit("pos = (pos + 3) & -4")
        self.emit("n, = U32.unpack_from(mv, pos)")
        self.emit(f"{v} = str(mv[pos + 4:pos + 3 + n], 'utf-8') if n else ''")
        self.emit("pos += 4 + n")
        return v

    def numbers(self, t: str, count: str) -> str:
        code, size = PRIMITIVES[t]
        v = self.var()
        # an empty sequence has no elements to align: Fast CDR pads only before a first element
        self.emit(f"if {count}:")
        if size > 1:
            self.emit(f"    pos = (pos + {size - 1}) & -{size}")
        self.emit(f"    {v} = np.frombuffer(mv, '<{code}', {count}, pos).copy()")
        self.emit(f"    pos += {count} * {size}")
        self.emit("else:")
        self.emit(f"    {v} = np.empty(0, '<{code}')")
        return v

    def field(self, t: str) -> str:
        """Statements reading one field of type ``t``; returns the expression of its value."""
        kind, base, length = _split_type(t)
        if kind == "single":
            if base in PRIMITIVES:
                return self.prim(base)
            if _is_string(base):
                return self.string()
            if base.startswith("wstring"):
                raise UnsupportedType(t)
            return self.nested_inline(_msg_class(base))
        # arrays and sequences
        self.flush()
        if kind == "sequence":
            self.emit("pos = (pos + 3) & -4")
            cnt = self.var()
            self.emit(f"{cnt}, = U32.unpack_from(mv, pos)")
            self.emit("pos += 4")
        else:
            cnt = str(length)
        if base in PRIMITIVES:
            return self.numbers(base, cnt)
        v = self.var()
        if _is_string(base):
            # the joint names of every JointState: the same bytes each tick, so the last decoded list is
            # reused when its bytes repeat (a compare of the span instead of a loop over 30 strings)
            memo = f"M{len(self.env)}"
            self.env[memo] = [(b"", [])]
            start = self.var()
            self.emit(f"{start} = pos")
            self.emit(f"mb, ml = {memo}[0]")
            self.emit(f"if {cnt} == len(ml) and mv[pos:pos + len(mb)] == mb:")
            self.emit("    pos += len(mb)")
            self.emit(f"    {v} = list(ml)")
            self.emit("else:")
            self.emit(f"    {v} = []")
            self.emit(f"    for _ in range({cnt}):")
            self.emit("        pos = (pos + 3) & -4")
            self.emit("        n, = U32.unpack_from(mv, pos)")
            self.emit(f"        {v}.append(str(mv[pos + 4:pos + 3 + n], 'utf-8') if n else '')")
            self.emit("        pos += 4 + n")
            self.emit(f"    {memo}[0] = (bytes(mv[{start}:pos]), list({v}))")
            return v
        if base.startswith("wstring"):
            raise UnsupportedType(t)
        helper = self.helper(_msg_class(base))
        self.emit(f"{v} = []")
        self.emit(f"for _ in range({cnt}):")
        self.emit(f"    x, pos = {helper}(mv, pos)")
        self.emit(f"    {v}.append(x)")
        return v

    def nested_inline(self, cls: type) -> str:
        parts = [f"{name}={self.field(t)}" for name, t in cls.get_fields_and_field_types().items()]
        return f"NS({', '.join(parts)})"

    def helper(self, cls: type) -> str:
        """A separate function ``(mv, pos) -> (obj, pos)`` for elements of a sequence of ``cls``."""
        if cls in self.helpers:
            return self.helpers[cls]
        name = f"dec_{cls.__name__}_{len(self.helpers)}"
        self.helpers[cls] = name
        sub = _Compiler()
        sub.env = self.env
        sub.helpers = self.helpers
        expr = sub.nested_inline(cls)
        sub.flush()
        src = "\n".join([f"def {name}(mv, pos):", *sub.lines, f"    return {expr}, pos"])
        exec(compile(src, f"<cdr {cls.__name__}>", "exec"), self.env)  # noqa: S102 - our own generated code
        return name

    def compile_top(self, cls: type) -> Callable[[Any], Any]:
        self.env["U32"] = struct.Struct("<I")
        try:
            expr = self.nested_inline(cls)
        except (KeyError, ValueError, ImportError, AttributeError) as e:
            raise UnsupportedType(f"{cls.__name__}: {e}") from e
        self.flush()
        body = [f"def decode_{cls.__name__}(data):",
                "    mv = memoryview(data)",
                "    if len(mv) < 4 or (mv[0], mv[1]) != CDR_LE:",
                "        raise ValueError('not little-endian CDR (encapsulation %r)' % bytes(mv[:4]))",
                "    mv = mv[4:]",
                "    pos = 0",
                *self.lines,
                f"    return {expr}"]
        self.env["CDR_LE"] = CDR_LE
        src = "\n".join(body)
        exec(compile(src, f"<cdr {cls.__name__}>", "exec"), self.env)  # noqa: S102 - our own generated code
        fn = self.env[f"decode_{cls.__name__}"]
        fn.__doc__ = f"{cls.__name__} from CDR bytes (generated by humfall_ros.recording.cdr)\n\n{src}"
        return fn
