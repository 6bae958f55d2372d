"""Message, service and action types of the robot graph.

Standard messages come from the rosbags type store (ROS 2 Jazzy); services, actions
and the lab's own messages come from the interface files in ``interfaces/``. A
service ``pkg/srv/Name`` is two messages, ``pkg/srv/Name_Request`` and
``pkg/srv/Name_Response``; an action ``pkg/action/Name`` is three,
``_Goal``, ``_Result`` and ``_Feedback``, as ROS 2 itself lays them out.

Names are accepted in the short form ``pkg/Type`` as well as ``pkg/msg/Type``.

A trial whose repository brings its own types gets a registry of its own,
``TypeRegistry.extended``: the lab's types and those, so they never reach another
trial or a live robot (``labd.graph.definitions`` checks them first).
"""

from __future__ import annotations

import enum
import re
import threading
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rosbags.interfaces import Nodetype
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from labd.errors import UnknownTypeError

INTERFACES = Path(__file__).with_name("interfaces")

_NAME = re.compile(r"^([A-Za-z][A-Za-z0-9_]*)/(?:(msg|srv|action)/)?([A-Za-z][A-Za-z0-9_]*)$")
_SEPARATOR = re.compile(r"^---[ \t]*$", re.MULTILINE)


class Kind(enum.Enum):
    """How a field holds its values."""

    SCALAR = "scalar"
    ARRAY = "array"  # fixed length
    SEQUENCE = "sequence"  # variable length, maybe bounded


INTEGER_RANGES: dict[str, tuple[int, int]] = {
    "int8": (-(2**7), 2**7 - 1),
    "uint8": (0, 2**8 - 1),
    "char": (0, 2**8 - 1),
    "byte": (0, 2**8 - 1),
    "int16": (-(2**15), 2**15 - 1),
    "uint16": (0, 2**16 - 1),
    "int32": (-(2**31), 2**31 - 1),
    "uint32": (0, 2**32 - 1),
    "int64": (-(2**63), 2**63 - 1),
    "uint64": (0, 2**64 - 1),
}
FLOATS = frozenset({"float32", "float64", "float128"})
BINARY = frozenset({"uint8", "char"})  # arrays of these travel as base64 in JSON
# The little-endian numpy type of each primitive, as CDR lays arrays of it out.
NUMPY_DTYPES = {
    "bool": "bool",
    "int8": "<i1",
    "uint8": "<u1",
    "char": "<u1",
    "byte": "<u1",
    "int16": "<i2",
    "uint16": "<u2",
    "int32": "<i4",
    "uint32": "<u4",
    "int64": "<i8",
    "uint64": "<u8",
    "float32": "<f4",
    "float64": "<f8",
}
# rosbags (like ROS 2's IDL) gives empty messages this member; JSON never shows it.
PLACEHOLDER = "structure_needs_at_least_one_member"


@dataclass(frozen=True)
class Field:
    """One field of a message type.

    Exactly one of ``base`` (a primitive such as ``float64`` or ``string``) and
    ``message`` (a nested type name) is set. ``length`` is the size of a fixed
    array or the bound of a sequence (0: unbounded); ``string_bound`` bounds
    each string (0: unbounded).
    """

    name: str
    kind: Kind
    base: str | None
    message: str | None
    length: int = 0
    string_bound: int = 0

    @property
    def is_binary(self) -> bool:
        return self.kind is not Kind.SCALAR and self.base in BINARY

    @property
    def ros_type(self) -> str:
        """The type as a .msg file spells it, e.g. ``float64[9]`` or ``Point[]``."""
        inner = self.base or short_name(self.message or "")
        if self.base == "string" and self.string_bound:
            inner = f"string<={self.string_bound}"
        if self.kind is Kind.ARRAY:
            return f"{inner}[{self.length}]"
        if self.kind is Kind.SEQUENCE:
            return f"{inner}[<={self.length}]" if self.length else f"{inner}[]"
        return inner


@dataclass(frozen=True)
class Constant:
    name: str
    base: str
    value: Any


@dataclass(frozen=True)
class MessageType:
    """A message type: its full name, fields and constants."""

    name: str
    fields: tuple[Field, ...]
    constants: tuple[Constant, ...] = ()
    _index: dict[str, Field] = field(default_factory=dict, compare=False, repr=False)

    def __post_init__(self) -> None:
        self._index.update((f.name, f) for f in self.fields)

    def field(self, name: str) -> Field | None:
        return self._index.get(name)


@dataclass(frozen=True)
class ServiceType:
    name: str
    request: MessageType
    response: MessageType


@dataclass(frozen=True)
class ActionType:
    name: str
    goal: MessageType
    result: MessageType
    feedback: MessageType


def short_name(name: str) -> str:
    """``geometry_msgs/msg/Twist`` -> ``geometry_msgs/Twist`` (the ROS 1 spelling)."""
    parts = name.split("/")
    return f"{parts[0]}/{parts[-1]}" if len(parts) == 3 else name


def full_name(name: str, kind: str) -> str | None:
    """Canonical ``pkg/kind/Type`` for ``pkg/Type`` or ``pkg/kind/Type``, or None."""
    match = _NAME.match(name.strip()) if isinstance(name, str) else None
    if match is None:
        return None
    pkg, given_kind, typ = match.groups()
    if given_kind is not None and given_kind != kind:
        return None
    return f"{pkg}/{kind}/{typ}"


_SHARED: dict[str, TypeRegistry] = {}  # "default": the registry ``shared`` made
_SHARED_LOCK = threading.Lock()


class TypeRegistry:
    """All the types a graph knows, with their definitions.

    Built once at start-up (it compiles code for each type when first used) and
    shared by every graph in the process; a trial with types of its own has an
    ``extended`` one, which shares the lab's compiled code for the lab's types.
    """

    def __init__(
        self,
        typestore: Typestore,
        services: Iterable[str],
        actions: Iterable[str],
        *,
        base: TypeRegistry | None = None,
    ) -> None:
        self.typestore = typestore
        self.standard = False  # only the lab's own interfaces (``default()``, nothing extra)
        self._services = frozenset(services)
        self._actions = frozenset(actions)
        self._messages: dict[str, MessageType] = {}
        self._codecs: dict[str, Any] = {}
        self._cdr: dict[str, Any] = {}
        self.base = base  # the registry this one extends, if any

    def extended(
        self, parts: Mapping[str, Any], services: Iterable[str], actions: Iterable[str]
    ) -> TypeRegistry:
        """A new registry with this one's types and ``parts`` (rosbags' parsed definitions,
        by full name), whose services and actions also include those named. This one is
        left as it was."""
        store = Typestore(max_sequence_length=self.typestore.max_sequence_length)
        store.fielddefs.update(self.typestore.fielddefs)
        store.types.update(self.typestore.types)
        store.cache.update(self.typestore.cache)  # serializers already made, shared
        store.register(dict(parts))
        return TypeRegistry(
            store, self._services | set(services), self._actions | set(actions), base=self
        )

    def owner(self, name: str) -> TypeRegistry:
        """The registry that defined the message ``name`` (full name): the lab's for its
        own types, so compiled converters are shared by every trial."""
        if self.base is not None and name in self.base.typestore.fielddefs:
            return self.base.owner(name)
        return self

    def packages(self) -> frozenset[str]:
        """The packages of every message, service and action this registry knows."""
        return frozenset(n.split("/", 1)[0] for n in self.typestore.fielddefs)

    @classmethod
    def default(cls, extra: Iterable[Path] = ()) -> TypeRegistry:
        """The rosbags ROS 2 Jazzy store plus the interface folders given."""
        typestore = get_typestore(Stores.ROS2_JAZZY)
        services: list[str] = []
        actions: list[str] = []
        for root in (INTERFACES, *extra):
            s, a = _load_interfaces(typestore, root)
            services += s
            actions += a
        made = cls(typestore, services, actions)
        made.standard = not extra
        return made

    @classmethod
    def shared(cls) -> TypeRegistry:
        """The lab's own types (``default()``), made once per process: for whoever only
        reads them (a replay, a summary), which would otherwise parse every interface
        and compile every serializer again each time."""
        with _SHARED_LOCK:
            if "default" not in _SHARED:
                _SHARED["default"] = cls.default()
            return _SHARED["default"]

    # -- lookup -------------------------------------------------------------------

    def message(self, name: str) -> MessageType:
        canonical = full_name(name, "msg")
        if canonical is None or canonical not in self.typestore.fielddefs:
            # Service and action parts are messages too, under their own names.
            if isinstance(name, str) and name in self.typestore.fielddefs:
                canonical = name
            else:
                raise UnknownTypeError("message", str(name))
        cached = self._messages.get(canonical)
        if cached is None:
            cached = self._messages[canonical] = self._build(canonical)
        return cached

    def service(self, name: str) -> ServiceType:
        canonical = full_name(name, "srv")
        if canonical is None or canonical not in self._services:
            raise UnknownTypeError("service", str(name))
        return ServiceType(
            canonical,
            self.message(canonical + "_Request"),
            self.message(canonical + "_Response"),
        )

    def action(self, name: str) -> ActionType:
        canonical = full_name(name, "action")
        if canonical is None or canonical not in self._actions:
            raise UnknownTypeError("action", str(name))
        return ActionType(
            canonical,
            self.message(canonical + "_Goal"),
            self.message(canonical + "_Result"),
            self.message(canonical + "_Feedback"),
        )

    def message_names(self) -> Iterator[str]:
        return (n for n in self.typestore.fielddefs if "/msg/" in n)

    def service_names(self) -> frozenset[str]:
        return self._services

    def action_names(self) -> frozenset[str]:
        return self._actions

    def definition_text(self, name: str) -> str:
        """The full ``ros2msg`` text of a message with its dependencies (for MCAP)."""
        text, _ = self.typestore.generate_msgdef(self.message(name).name, ros_version=2)
        return text

    def codec_cache(self) -> dict[str, Any]:
        """Storage for compiled converters, keyed by type name (see ``codec``)."""
        return self._codecs

    def cdr_cache(self) -> dict[str, Any]:
        """Storage for compiled CDR encoders, keyed by type name (``labd.graph.cdr``)."""
        return self._cdr

    def _build(self, name: str) -> MessageType:
        consts, fields = self.typestore.fielddefs[name]
        return MessageType(
            name,
            tuple(_field(fname, desc) for fname, desc in fields),
            tuple(Constant(c[0], str(c[1]), c[2]) for c in consts),
        )


def _field(name: str, desc: Any) -> Field:
    node, detail = desc
    if node == Nodetype.BASE:
        base, bound = detail
        return Field(name, Kind.SCALAR, base, None, string_bound=bound)
    if node == Nodetype.NAME:
        return Field(name, Kind.SCALAR, None, detail)
    kind = Kind.ARRAY if node == Nodetype.ARRAY else Kind.SEQUENCE
    (inner_node, inner), length = detail
    if inner_node == Nodetype.BASE:
        return Field(name, kind, inner[0], None, length, inner[1])
    return Field(name, kind, None, inner, length)


def _load_interfaces(typestore: Typestore, root: Path) -> tuple[list[str], list[str]]:
    """Register every .msg, .srv and .action file under ``root``; return services, actions."""
    services: list[str] = []
    actions: list[str] = []
    parts: dict[str, Any] = {}
    for path in sorted(root.glob("*/*/*")):
        pkg, kind, stem = path.parent.parent.name, path.parent.name, path.stem
        text = path.read_text()
        if kind == "msg" and path.suffix == ".msg":
            parts.update(get_types_from_msg(text, f"{pkg}/msg/{stem}"))
            continue
        suffixes = {"srv": ["_Request", "_Response"], "action": ["_Goal", "_Result", "_Feedback"]}
        if kind not in suffixes or path.suffix != f".{kind}":
            continue
        sections = _SEPARATOR.split(text)
        if len(sections) != len(suffixes[kind]):
            raise ValueError(f"{path}: expected {len(suffixes[kind])} sections")
        for section, suffix in zip(sections, suffixes[kind], strict=True):
            # Parsed as a msg so that relative type names resolve inside the package.
            parsed = get_types_from_msg(section, f"{pkg}/msg/{stem}{suffix}")
            ((_, definition),) = parsed.items()
            parts[f"{pkg}/{kind}/{stem}{suffix}"] = definition
        (services if kind == "srv" else actions).append(f"{pkg}/{kind}/{stem}")
    typestore.register(parts)
    return services, actions
