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


def leading_stamp_ns(data: bytes) -> int | None:
    """The ``builtin_interfaces/Time`` a CDR message begins with (a header's stamp, ``rosgraph_msgs/Clock``), in ns:
    after the 4-byte encapsulation an int32 sec and a uint32 nanosec. None if too short or not plain CDR."""
    if len(data) < 12 or data[0] != 0 or data[1] not in (0, 1):
        return None
    sec, nanosec = struct.unpack_from("<iI" if data[1] == 1 else ">iI", data, 4)
    return sec * 1_000_000_000 + nanosec


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


def _define(src: str, env: dict, name: str, label: str) -> Callable:
    """Compile our own generated ``def name(...)`` source into ``env`` and return the function."""
    exec(compile(src, f"<cdr {label}>", "exec"), env)  # noqa: S102 - our own generated code
    return env[name]


class _Generator:
    """What the decoder and the encoder compilers share: one generated helper function per message class
    that appears as the element of a sequence (``PREFIX``, ``ARGS``; ``_helper_body`` fills the lines and
    gives the return statement)."""

    PREFIX = ARGS = ""
    env: dict
    helpers: dict
    lines: list
    group: list
    group_align: int
    group_off: int

    def grouped(self, t: str, item: str) -> None:
        """Add a primitive of type ``t`` to the current run of fixed-size fields (one ``struct`` call), with
        its CDR padding; a field aligned wider than the run's start begins a new run."""
        code, size = PRIMITIVES[t]
        if self.group and size > self.group_align:
            self.flush()
        if not self.group:
            self.group_align, self.group_off = size, 0
        pad = -self.group_off % size
        self.group.append(("x" * pad + code, item))
        self.group_off += pad + size

    def helper(self, cls: type) -> str:
        if cls in self.helpers:
            return self.helpers[cls]
        name = f"{self.PREFIX}_{cls.__name__}_{len(self.helpers)}"
        self.helpers[cls] = name
        sub = type(self)()
        sub.env, sub.helpers = self.env, self.helpers
        ret = sub._helper_body(cls)
        sub.flush()
        src = "\n".join([f"def {name}({self.ARGS}):", *sub.lines, ret])
        _define(src, self.env, name, f"{self.PREFIX} {cls.__name__}")
        return name


class _Compiler(_Generator):
    """Generates ``decode(data)`` (see :func:`decoder`); sequence elements via
    ``dec_<Class>(mv, pos) -> (obj, pos)``."""

    PREFIX, ARGS = "dec", "mv, pos"

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
        v = self.var()
        self.grouped(t, v)
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

    def _helper_body(self, cls: type) -> str:
        return f"    return {self.nested_inline(cls)}, pos"

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
        fn = _define(src, self.env, f"decode_{cls.__name__}", cls.__name__)
        fn.__doc__ = f"{cls.__name__} from CDR bytes (generated by humfall_ros.recording.cdr)\n\n{src}"
        return fn


# ==================================================================== encoding
# The other direction, for the suite's per-tick publishers: rclpy's publish of a message object converts
# it field by field through the generated Python classes before serialising (measured on this machine,
# CPU per publish: JointState 25 us, CentroidalState 77 us, WalkingState 97 us; the same bytes published
# raw 9-16 us), and building the message through the classes' checking setters costs as much again.
# :func:`encoder` compiles, once per class, ``encode(msg) -> bytes`` that reads the fields by attribute
# from a real message or from a :func:`blank` namespace tree and writes the same CDR as
# ``rclpy.serialization.serialize_message`` but for zeroed padding (rclpy leaves its padding bytes
# uninitialised and may append trailing bytes); ``test_cdr.py`` reads the bytes back with rclpy.

_enc_cache: dict[type, Callable[[Any], bytes]] = {}
_ZEROS = bytes(8)


def encoder(msg_class: type) -> Callable[[Any], bytes]:
    """``encode(msg) -> bytes``: the CDR serialisation of ``msg`` (a ``msg_class`` or any object with its
    field names as attributes, e.g. from :func:`blank`); publish it with ``publisher.publish(data)``.

    Numbers are not range-checked (struct raises on a value its type cannot hold); numeric sequences and
    arrays may be lists, ``array.array`` or numpy arrays. Raises UnsupportedType at compile time for types
    it cannot encode."""
    fn = _enc_cache.get(msg_class)
    if fn is None:
        fn = _enc_cache[msg_class] = _Encoder().compile_top(msg_class)
    return fn


def blank(msg_class: type) -> types.SimpleNamespace:
    """A namespace tree with ``msg_class``'s fields and default values, to fill and pass to :func:`encoder`'s
    function: assigning its fields costs an attribute store, where the generated classes check every value
    (a 31-float JointState position: ~15 us). Fixed arrays are numpy arrays, sequences lists."""
    return _to_ns(msg_class())


def _to_ns(msg) -> types.SimpleNamespace:
    out = types.SimpleNamespace()
    for name, t in msg.get_fields_and_field_types().items():
        v = getattr(msg, name)
        kind, base, _ = _split_type(t)
        if kind == "single":
            if not (base in PRIMITIVES or _is_string(base) or base.startswith("wstring")):
                v = _to_ns(v)
        elif kind == "array" and base in PRIMITIVES:
            v = np.array(v)
        elif base in PRIMITIVES or _is_string(base):
            v = list(v)
        else:
            v = [_to_ns(x) for x in v]
        setattr(out, name, v)
    return out


def _put_string(out: bytearray, s: str) -> None:
    """Append one CDR string at a 4-byte boundary (relative to the encapsulation header): its uint32 length
    counting the NUL, the UTF-8 bytes, the NUL."""
    out += _ZEROS[:-(len(out) - 4) % 4]
    b = s.encode()
    out += struct.pack("<I", len(b) + 1)
    out += b
    out += b"\0"


def _u8(v) -> int:
    """byte/char/octet fields: rclpy holds them as 1-byte ``bytes`` or 1-char ``str``."""
    return v[0] if isinstance(v, bytes) else ord(v) if isinstance(v, str) else int(v)


class _Encoder(_Generator):
    """Generates ``encode(m)``: writes into a bytearray ``out`` whose first 4 bytes are the encapsulation
    header, so a field's alignment is taken of ``len(out) - 4``; sequence elements via ``enc_<Class>(out, m)``."""

    PREFIX, ARGS = "enc", "out, m"

    def __init__(self):
        self.lines: list[str] = []
        self.env: dict[str, Any] = {"np": np, "U32": struct.Struct("<I"), "Z": _ZEROS, "u8": _u8,
                                    "put_string": _put_string}
        self.group: list[tuple[str, str]] = []  # (struct code incl. padding, expression)
        self.group_align = 0
        self.group_off = 0
        self.helpers: dict[type, str] = {}
        self.indent = 1
        self.n = 0

    def emit(self, line: str) -> None:
        self.lines.append("    " * self.indent + line)

    def name(self, prefix: str) -> str:
        self.n += 1
        return f"{prefix}{self.n}_{len(self.env)}"

    def align(self, size: int) -> None:
        if size > 1:
            self.emit(f"out += Z[:-(len(out) - 4) % {size}]")

    def prim(self, t: str, expr: str) -> None:
        self.grouped(t, f"u8({expr})" if t in ("byte", "octet", "char") else expr)

    def flush(self) -> None:
        if not self.group:
            return
        s = struct.Struct("<" + "".join(c for c, _ in self.group))
        name = self.name("S")
        self.env[name] = s
        self.align(self.group_align)
        self.emit(f"out += {name}.pack({', '.join(e for _, e in self.group)})")
        self.group, self.group_align, self.group_off = [], 0, 0

    def string(self, expr: str) -> None:
        self.flush()
        self.emit(f"put_string(out, {expr})")

    def numbers(self, t: str, expr: str, count_known: int | None) -> None:
        code, size = PRIMITIVES[t]
        dtype = "'?'" if t == "boolean" else f"'<{code}'"
        if size == 1 and t != "boolean":  # byte[] / uint8[] may be held as bytes
            self.emit(f"a = {expr}")
            self.emit(f"a = np.frombuffer(a, {dtype}) if isinstance(a, (bytes, bytearray)) else np.asarray(a, {dtype})")
        else:
            self.emit(f"a = np.asarray({expr}, {dtype})")
        if count_known is None:
            self.align(4)
            self.emit("out += U32.pack(a.size)")
            self.emit("if a.size:")  # Fast CDR aligns only before a first element
            self.indent += 1
        else:
            self.emit(f"if a.size != {count_known}:")
            self.emit(f"    raise ValueError('array of {count_known} expected, got %d' % a.size)")
        self.align(size)
        self.emit("out += a.tobytes()")
        if count_known is None:
            self.indent -= 1

    def field(self, t: str, expr: str) -> None:
        kind, base, length = _split_type(t)
        if kind == "single":
            if base in PRIMITIVES:
                return self.prim(base, expr)
            if _is_string(base):
                return self.string(expr)
            if base.startswith("wstring"):
                raise UnsupportedType(t)
            return self.nested_inline(_msg_class(base), expr)
        self.flush()
        if base in PRIMITIVES:
            return self.numbers(base, expr, length)
        if base.startswith("wstring"):
            raise UnsupportedType(t)
        seq = self.name("q")
        self.emit(f"{seq} = {expr}")
        if kind == "sequence":
            self.align(4)
            self.emit(f"out += U32.pack(len({seq}))")
        else:
            self.emit(f"if len({seq}) != {length}:")
            self.emit(f"    raise ValueError('array of {length} expected, got %d' % len({seq}))")
        if _is_string(base):
            # the joint names of every JointState: the same list each tick, so its bytes are kept and
            # reused while the list compares equal (one C-level compare instead of 31 encodes); aligned
            # first, so the kept bytes hold no padding that depends on where the list starts
            memo = self.name("M")
            self.env[memo] = [None, b""]
            self.align(4)
            self.emit(f"mm = {memo}")
            self.emit(f"if mm[0] == {seq}:")
            self.emit("    out += mm[1]")
            self.emit("else:")
            self.emit("    start = len(out)")
            self.emit(f"    for s in {seq}:")
            self.emit("        put_string(out, s)")
            self.emit(f"    mm[0], mm[1] = list({seq}), bytes(out[start:])")
            return None
        helper = self.helper(_msg_class(base))
        self.emit(f"for x in {seq}:")
        self.emit(f"    {helper}(out, x)")
        return None

    def nested_inline(self, cls: type, expr: str) -> None:
        for name, t in cls.get_fields_and_field_types().items():
            self.field(t, f"{expr}.{name}")

    def _helper_body(self, cls: type) -> str:
        self.nested_inline(cls, "m")
        return "    return None"

    def compile_top(self, cls: type) -> Callable[[Any], bytes]:
        try:
            self.nested_inline(cls, "m")
        except (KeyError, ValueError, ImportError, AttributeError) as e:
            raise UnsupportedType(f"{cls.__name__}: {e}") from e
        self.flush()
        src = "\n".join([f"def encode_{cls.__name__}(m):", "    out = bytearray(HDR)", *self.lines,
                         "    return bytes(out)"])
        self.env["HDR"] = bytes((*CDR_LE, 0, 0))
        fn = _define(src, self.env, f"encode_{cls.__name__}", f"enc {cls.__name__}")
        fn.__doc__ = f"{cls.__name__} to CDR bytes (generated by humfall_ros.recording.cdr)\n\n{src}"
        return fn
