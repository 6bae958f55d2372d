"""A direct CDR encoder: normal form to the bytes ROS 2 and MCAP carry, in one pass.

Every message a trial records, and every message a replay compares, is encoded to CDR
(little-endian, with the 4-byte encapsulation header). Going through rosbags meant
building its message objects first and then walking them: a fifth of a replay's time.
Here each message type is compiled once into a Python function that reads the normal
form (``labd.graph.codec``) and appends to a ``bytearray``:

- Consecutive fields of fixed size (numbers, booleans, fixed arrays of ``float64``,
  integers or booleans, and nested messages made only of those, such as a ``Pose``)
  are one ``struct`` call. Where the run starts relative to 8 is known only when
  encoding (a string before it has any length), so each run has eight precompiled
  ``struct`` formats, one per starting offset, with the padding already in them.
- Strings, sequences and arrays of strings or messages are written as they come;
  numeric sequences and ``float32`` arrays through numpy, as rosbags converts them
  (the same rounding and the same bytes).
- The layout is CDR's: each primitive aligned to its own size counted from the end of
  the header, strings and sequence lengths to 4, no padding at the end.

The bytes are rosbags' own, field for field: ``tests/labd/graph/test_cdr.py`` compares
both on every type the lab knows, and ``tests/labd/test_golden_bytes.py`` holds what
every task published before this encoder existed. A type this compiler does not know
how to lay out (``float128``, ``wstring``) goes through rosbags as before.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from typing import Any

import numpy as np

from labd.graph.types import BINARY, NUMPY_DTYPES, PLACEHOLDER, Field, Kind, TypeRegistry

HEADER = b"\x00\x01\x00\x00"  # CDR, little-endian, no options

Encoder = Callable[[Any, bytearray], None]

# The struct code of each primitive; its size and numpy type are those of NUMPY_DTYPES.
_CODES = {
    "bool": "?",
    "byte": "B",
    "char": "B",
    "int8": "b",
    "uint8": "B",
    "int16": "h",
    "uint16": "H",
    "int32": "i",
    "uint32": "I",
    "int64": "q",
    "uint64": "Q",
    "float32": "f",
    "float64": "d",
}
_DTYPES = {name: np.dtype(NUMPY_DTYPES[name]) for name in _CODES}
_PRIMITIVES = {name: (code, _DTYPES[name].itemsize) for name, code in _CODES.items()}
# Fixed arrays that ``struct`` packs exactly as numpy converts them: not float32 (struct
# refuses a float64 beyond float32's range where numpy makes it infinite), and not the
# binary ones, which are ``bytes`` in normal form.
_STRUCT_ARRAYS = frozenset(_CODES) - BINARY - {"float32"}


class Unsupported(Exception):
    """A field this encoder does not lay out; the type goes through rosbags."""


def _runs(items: list[tuple[str, int, int]]) -> tuple[struct.Struct, ...]:
    """Eight formats for a run of (code, size, count) items, one per start offset mod 8."""
    formats = []
    for start in range(8):
        position, parts = start, ["<"]
        for code, size, count in items:
            pad = -position % size
            if pad:
                parts.append(f"{pad}x")
            parts.append(f"{count}{code}" if count != 1 else code)
            position += pad + size * count
        formats.append(struct.Struct("".join(parts)))
    return tuple(formats)


_U32 = _runs([("I", 4, 1)])


class _Compiler:
    """Writes one type's encoder as Python source, nested scalar messages inlined."""

    def __init__(self, registry: TypeRegistry, name: str) -> None:
        self.registry = registry
        self.name = name
        self.lines: list[str] = []
        self.names: dict[str, Any] = {"U32": _U32, "asarray": np.asarray}
        self.run: list[tuple[str, int, int]] = []
        self.run_values: list[str] = []
        self.counter = 0

    def fresh(self, stem: str) -> str:
        self.counter += 1
        return f"{stem}{self.counter}"

    def constant(self, stem: str, value: Any) -> str:
        name = self.fresh(stem)
        self.names[name] = value
        return name

    def emit(self, line: str, depth: int = 1) -> None:
        self.lines.append("    " * depth + line)

    def flush(self) -> None:
        if not self.run:
            return
        formats = self.constant("R", _runs(self.run))
        self.emit(f"out += {formats}[(len(out) + 4) & 7].pack({', '.join(self.run_values)})")
        self.run, self.run_values = [], []

    def compile(self) -> Encoder:
        self.message(self.name, "v")
        self.flush()
        source = "def encode(v, out):\n" + ("\n".join(self.lines) or "    pass") + "\n"
        namespace = dict(self.names)
        exec(compile(source, f"<cdr {self.name}>", "exec"), namespace)  # noqa: S102
        encode: Encoder = namespace["encode"]
        encode.__doc__ = f"Append the CDR of a {self.name} in normal form to ``out``.\n\n{source}"
        return encode

    def message(self, name: str, value: str) -> None:
        """Inline the fields of the message held in the variable ``value``."""
        mtype = self.registry.message(name)
        for field in mtype.fields:
            if field.name == PLACEHOLDER:
                self.run.append(("B", 1, 1))
                self.run_values.append("0")
                continue
            self.field(field, f"{value}[{field.name!r}]")

    def field(self, field: Field, expr: str) -> None:
        base = field.base
        if base is not None and base not in _PRIMITIVES and base != "string":
            raise Unsupported(f"{field.name}: {base}")
        if field.kind is Kind.SCALAR:
            if base == "string":
                self.flush()
                self.string(expr, 1)
            elif base is not None:
                self.run.append((*_PRIMITIVES[base], 1))
                self.run_values.append(expr)
            else:  # a nested message, laid out in place
                var = self.fresh("m")
                self.emit(f"{var} = {expr}")
                self.message(field.message or "", var)
            return
        if field.kind is Kind.ARRAY and base in _STRUCT_ARRAYS:
            self.run.append((*_PRIMITIVES[base], field.length))
            self.run_values.append(f"*{expr}")
            return
        self.flush()
        var = self.fresh("a")
        self.emit(f"{var} = {expr}")
        if field.kind is Kind.ARRAY:
            self.emit(f"if len({var}) != {field.length}:")
            self.emit(f"raise ValueError('{field.name} must hold {field.length} items')", 2)
        else:
            self.emit(f"out += U32[(len(out) + 4) & 7].pack(len({var}))")
        if base == "string":
            item = self.fresh("s")
            self.emit(f"for {item} in {var}:")
            self.string(item, 2)
        elif base is not None:
            self.numbers(field, var)
        else:
            encode = self.constant("E", encoder(self.registry, field.message or ""))
            item = self.fresh("i")
            self.emit(f"for {item} in {var}:")
            self.emit(f"{encode}({item}, out)", 2)

    def string(self, expr: str, depth: int) -> None:
        text = self.fresh("t")
        self.emit(f"{text} = {expr}.encode()", depth)
        self.emit(f"out += U32[(len(out) + 4) & 7].pack(len({text}) + 1)", depth)
        self.emit(f"out += {text}", depth)
        self.emit("out += b'\\0'", depth)

    def numbers(self, field: Field, var: str) -> None:
        """A sequence (its length already written) or a fixed array of numbers."""
        base = field.base or ""
        if field.is_binary:  # bytes in normal form; alignment 1
            self.emit(f"out += {var}")
            return
        size = _PRIMITIVES[base][1]
        dtype = self.constant("D", _DTYPES[base])
        self.emit(f"if len({var}):")
        if size > (4 if field.kind is Kind.SEQUENCE else 1):  # a length is 4-aligned
            self.emit(f"out += bytes(-(len(out) + 4) & {size - 1})", 2)
        self.emit(f"out += asarray({var}, dtype={dtype}).tobytes()", 2)


def encoder(registry: TypeRegistry, name: str) -> Encoder:
    """The compiled encoder of the message type ``name`` (full name), made on first use
    and kept in ``registry`` (``Unsupported`` if it cannot be laid out here)."""
    cache = registry.cdr_cache()
    encode = cache.get(name)
    if encode is None:
        encode = cache[name] = _Compiler(registry, name).compile()
    return encode


def to_cdr_function(registry: TypeRegistry, name: str) -> Callable[[Any], bytes] | None:
    """A function from a ``name`` message in normal form to its CDR, header included;
    None for a type this compiler cannot lay out."""
    try:
        encode = encoder(registry, name)
    except Unsupported:
        return None

    def to_cdr(value: Any) -> bytes:
        out = bytearray(HEADER)
        encode(value, out)
        return bytes(out)

    return to_cdr


__all__ = ["HEADER", "Unsupported", "encoder", "to_cdr_function"]
