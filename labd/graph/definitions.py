"""A repository's own interface definitions: parsed line by line, checked, registered.

A controller repository may bring its own ``.msg``, ``.srv`` and ``.action`` files
(``interfaces`` in its ``lab.toml``; docs/trials.md). The scheduler reads them as the
repository's own files and hands their texts to the lab side keyed by their paths in
the repository, whose last three parts name each type, as in a ROS package:
``.../PKG/msg/Name.msg`` is ``PKG/msg/Name``, ``.../PKG/srv/Name.srv`` the service
``PKG/srv/Name``, ``.../PKG/action/Name.action`` the action ``PKG/action/Name``.

``trial_types`` checks them all and returns a ``TypeRegistry`` with the lab's types and
these, for one trial's graph alone. Whatever is wrong is an ``InterfaceError`` naming
the file, and the line where there is one:

- a path outside that layout, or a package or type name that ROS 2 does not allow;
- a package the lab already has (every standard one, the tutorial ones, ``lab_msgs``):
  a repository adds types of its own, it never redefines one;
- the same type defined twice;
- a line that does not parse; a field or constant name ROS 2 does not allow, or given
  twice; a constant whose value does not fit its type; a fixed array of no elements;
  a ``.srv`` not in two parts or an ``.action`` not in three (``---`` between them);
- a field whose type is neither the lab's nor the repository's, or a type that
  contains itself.

Each line is parsed on its own (a ``.msg`` line is a definition by itself), so an error
has its line; the lines' fields and constants then make the type, as rosbags would
parse the whole text.
"""

from __future__ import annotations

import re
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any

from rosbags.interfaces import Nodetype
from rosbags.typesys import get_types_from_msg
from rosbags.typesys.base import TypesysError

from labd.errors import InterfaceError
from labd.graph.codec import codec_for
from labd.graph.types import FLOATS, INTEGER_RANGES, TypeRegistry

PARTS = {
    "msg": ("",),
    "srv": ("_Request", "_Response"),
    "action": ("_Goal", "_Result", "_Feedback"),
}
MAX_TYPES = 1000  # message types one repository may define (a service is two, an action three)

_PACKAGE = re.compile(r"[a-z][a-z0-9_]*")  # REP 144
_TYPE = re.compile(r"[A-Z][A-Za-z0-9]*")
_FIELD = re.compile(r"(?!.*__)(?!.*_$)[a-z][a-z0-9_]*")  # rosidl's rules
_CONSTANT = re.compile(r"[A-Z](?:[A-Z0-9_]?[A-Z0-9]+)*")
_SEPARATOR = re.compile(r"---[ \t]*")


@dataclass
class _Message:
    """One message type being defined: where, and its fields with their lines."""

    name: str  # full name, e.g. my_msgs/msg/Debug or my_msgs/srv/Reset_Request
    path: str
    start: int  # the line its text starts on
    constants: list[tuple[str, str, Any]] = field(default_factory=list)
    fields: list[tuple[str, Any]] = field(default_factory=list)
    lines: dict[str, int] = field(default_factory=dict)  # field or constant -> its line

    def error(self, reason: str, name: str | None = None) -> InterfaceError:
        return InterfaceError(self.path, reason, self.lines.get(name or "", self.start))


def trial_types(base: TypeRegistry, files: Mapping[str, str]) -> TypeRegistry:
    """``base`` extended with the types defined in ``files`` (path -> text).

    ``InterfaceError`` names the first file and line at fault; ``base`` is never changed.
    """
    standard = base.packages()
    messages: dict[str, _Message] = {}
    services: list[str] = []
    actions: list[str] = []
    for path in sorted(files):
        package, kind, stem = _name_of(path)
        if package in standard:
            raise InterfaceError(
                path,
                f"{package} is a package the lab already has (its types are standard or the"
                " lab's own); put your types in a package of your own name",
            )
        for message in _parse(path, files[path], package, kind, stem):
            if message.name in messages:
                raise InterfaceError(
                    path, f"{message.name} is also defined in {messages[message.name].path}"
                )
            messages[message.name] = message
        if len(messages) > MAX_TYPES:
            raise InterfaceError(path, f"a repository may define at most {MAX_TYPES} types")
        if kind == "srv":
            services.append(f"{package}/srv/{stem}")
        elif kind == "action":
            actions.append(f"{package}/action/{stem}")
    known = set(base.typestore.fielddefs) | set(messages)
    for message in messages.values():
        for fname, desc in message.fields:
            reference = _reference(desc)
            if reference is not None and reference not in known:
                raise message.error(_unknown(fname, reference), fname)
    _refuse_cycles(messages)
    parts = {m.name: (m.constants, m.fields) for m in messages.values()}
    try:
        types = base.extended(parts, services, actions)
        for name in messages:
            codec_for(types, name)  # compiled now, so a fault shows here, not mid-trial
            types.definition_text(name)
    except TypesysError as err:  # the checks above are meant to leave nothing for this
        first = sorted(files)[0]
        raise InterfaceError(first, f"the lab could not register the types: {err}") from None
    return types


def _name_of(path: str) -> tuple[str, str, str]:
    """Package, kind and type name from ``.../PKG/KIND/Name.KIND``."""
    parts = path.split("/")
    layout = (
        "interface files lie at PACKAGE/msg/Name.msg, PACKAGE/srv/Name.srv or"
        " PACKAGE/action/Name.action"
    )
    if len(parts) < 3 or parts[-2] not in PARTS or not parts[-1].endswith("." + parts[-2]):
        raise InterfaceError(path, layout)
    package, kind, stem = parts[-3], parts[-2], parts[-1][: -len(parts[-2]) - 1]
    if not _PACKAGE.fullmatch(package):
        raise InterfaceError(
            path,
            f"{package!r} is not a ROS package name (lowercase letters, digits and _,"
            " starting with a letter)",
        )
    if not _TYPE.fullmatch(stem):
        raise InterfaceError(
            path,
            f"{stem!r} is not a ROS type name (letters and digits, starting with a capital)",
        )
    return package, kind, stem


def _parse(path: str, text: str, package: str, kind: str, stem: str) -> Iterator[_Message]:
    """The message types of one file (one, or a service's two, or an action's three)."""
    suffixes = PARTS[kind]
    sections: list[list[tuple[int, str]]] = [[]]
    for number, line in enumerate(text.splitlines(), start=1):
        if _SEPARATOR.fullmatch(line):
            if len(sections) == len(suffixes):
                raise InterfaceError(
                    path,
                    f"a .{kind} has {_parts(len(suffixes))}, so at most {len(suffixes) - 1} ---",
                    number,
                )
            sections.append([])
        else:
            sections[-1].append((number, line))
    if len(sections) != len(suffixes):
        raise InterfaceError(
            path,
            f"a .{kind} has {_parts(len(suffixes))} separated by lines of ---; this has"
            f" {_parts(len(sections))}",
        )
    start = 1
    for section, suffix in zip(sections, suffixes, strict=True):
        # Parsed as a msg, so relative type names resolve inside the package.
        scope = f"{package}/msg/{stem}{suffix}"
        message = _Message(
            f"{package}/{kind}/{stem}{suffix}", path, section[0][0] if section else start
        )
        for number, line in section:
            _parse_line(message, scope, number, line)
        start = section[-1][0] + 1 if section else start
        yield message


def _parse_line(message: _Message, scope: str, number: int, line: str) -> None:
    """Add the field or constant of one line (or nothing, for a comment or blank)."""
    path = message.path
    try:
        ((_, (constants, fields)),) = get_types_from_msg(line, scope).items()
    except TypesysError:
        raise InterfaceError(path, f"cannot parse {line.strip()!r}", number) from None
    for cname, ctype, value in constants:
        if not _CONSTANT.fullmatch(cname):
            raise InterfaceError(
                path, f"{cname!r} is not a constant name (capitals, digits and _)", number
            )
        fault = _constant_fault(ctype, value)
        if fault:
            raise InterfaceError(path, f"the constant {cname} {fault}", number)
        _claim(message, cname, number)
        message.constants.append((cname, ctype, value))
    for fname, desc in fields:
        if not _FIELD.fullmatch(fname):
            raise InterfaceError(
                path,
                f"{fname!r} is not a field name (lowercase letters, digits and single _,"
                " starting with a letter)",
                number,
            )
        node, detail = desc
        length = detail[1] if node == Nodetype.ARRAY else 1
        if isinstance(length, int) and length < 1:
            raise InterfaceError(path, f"{fname} is a fixed array of {length} elements", number)
        _claim(message, fname, number)
        message.fields.append((fname, desc))


def _constant_fault(ctype: str, value: Any) -> str:
    """What is wrong with a constant's value for its type ("" if nothing)."""
    if ctype in INTEGER_RANGES:
        low, high = INTEGER_RANGES[ctype]
        if isinstance(value, bool) or not isinstance(value, int):
            return f"must be an integer ({ctype}), not {value!r}"
        if not low <= value <= high:
            return f"is out of the range of {ctype} ({low} to {high})"
    elif ctype in FLOATS:
        if isinstance(value, bool) or not isinstance(value, int | float):
            return f"must be a number ({ctype}), not {value!r}"
    elif ctype == "bool":
        if value not in (True, False, 0, 1):
            return f"must be true or false, not {value!r}"
    elif ctype != "string" and not ctype.startswith("string<="):
        return f"has the type {ctype}; constants are of primitive types"
    return ""


def _claim(message: _Message, name: str, number: int) -> None:
    if name in message.lines:
        raise InterfaceError(
            message.path, f"{name} is defined twice (first on line {message.lines[name]})", number
        )
    message.lines[name] = number


def _reference(desc: Any) -> str | None:
    """The message type a field holds (alone or in an array), if any."""
    node, detail = desc
    if node == Nodetype.NAME:
        return str(detail)
    if node in (Nodetype.ARRAY, Nodetype.SEQUENCE):
        return _reference(detail[0])
    return None


def _unknown(fname: str, reference: str) -> str:
    package, _, name = reference.split("/")
    text = (
        f"{fname} has the type {package}/{name}, which is neither a standard type nor one"
        " the repository defines"
    )
    if not _TYPE.fullmatch(name):
        text += f" ({name!r} is no type name: a misspelt primitive type?)"
    return text


def _refuse_cycles(messages: Mapping[str, _Message]) -> None:
    """A message type may not contain itself, directly or through others."""
    done: set[str] = set()

    def visit(name: str, trail: tuple[str, ...]) -> None:
        message = messages[name]
        for fname, desc in message.fields:
            reference = _reference(desc)
            if reference is None or reference not in messages or reference in done:
                continue
            if reference in trail or reference == name:
                cycle = " -> ".join((*trail, name, reference)[(*trail, name).index(reference) :])
                raise message.error(f"{fname} makes a type that contains itself ({cycle})", fname)
            visit(reference, (*trail, name))
        done.add(name)

    for name in messages:
        if name not in done:
            visit(name, ())


def _parts(count: int) -> str:
    return "one part" if count == 1 else f"{count} parts"
