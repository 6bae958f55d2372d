"""Graph names: resolution of relative names, validation, protected prefixes, the lab's own.

The lab's graphs have a single namespace, the root, so ``chatter`` and ``/chatter``
name the same topic. A name is a ``/``-separated list of tokens of letters, digits
and underscores, each not starting with a digit (the ROS 2 rules).

Names under ``LAB_NAMESPACES`` (``/lab/step``, ``/lab/episode``, ``/rosapi/topics``)
are the lab's, on every graph: a client may not advertise a topic or provide a
service or action there, even where the lab has none of that name (``/lab/step`` on a
live robot), so a client can never pass for the lab.
"""

from __future__ import annotations

import functools
import re
from collections.abc import Iterable
from dataclasses import dataclass

from labd.errors import NameError_

_TOKEN = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
MAX_NAME = 255
LAB_NAMESPACES = ("/lab/", "/rosapi/")


def resolve(name: object) -> str:
    """The absolute form of a topic, service or action name; NameError_ if malformed."""
    if not isinstance(name, str):
        raise NameError_(repr(name), "a name must be a string")
    return _resolve(name)


@functools.lru_cache(maxsize=4096)
def _resolve(name: str) -> str:
    if not name or name == "/":
        raise NameError_(name, "a name must not be empty")
    if len(name) > MAX_NAME:
        raise NameError_(name[:40] + "...", f"a name must be at most {MAX_NAME} characters")
    absolute = name if name.startswith("/") else "/" + name
    for token in absolute[1:].split("/"):
        if not _TOKEN.fullmatch(token):
            raise NameError_(name, "tokens are letters, digits and '_', not starting with a digit")
    return absolute


def is_protected(name: str, prefixes: Iterable[str]) -> bool:
    """True if the absolute ``name`` lies under one of the protected prefixes.

    ``/protected`` covers ``/protected`` and ``/protected/arm``, and also
    ``/protected_arm``: the rosjs paper protects by prefix, and a prefix that also
    matches the longer names is the safe reading.
    """
    return any(name.startswith(p) for p in prefixes)


def lab_namespace(name: str) -> str | None:
    """The lab namespace the absolute ``name`` lies in (``/lab/``), or None."""
    for namespace in LAB_NAMESPACES:
        if name.startswith(namespace):
            return namespace
    return None


SHARED = ("/clock", "/lab/", "/rosapi/")  # what every side of a graph reaches as it is


@dataclass(frozen=True)
class Namespace:
    """One client's view of a graph under a prefix: a match's side (``/home``), so each
    team's controller names its own players ``/player_0/...`` and its score ``/score``
    and cannot reach the other side's (``/away/score`` is ``/home/away/score`` to it).

    Every name is put under the prefix but the ``shared`` ones (an entry ending in ``/``
    covers the names under it, any other only itself): the lab's time, its services
    and rosapi, which are the same for both sides. A name a client spells is mapped in
    with ``inward``; a graph name is shown to it with ``outward`` (None: out of its view).
    """

    prefix: str  # an absolute name, without a trailing slash: /home
    shared: tuple[str, ...] = SHARED

    def __post_init__(self) -> None:
        if resolve(self.prefix) != self.prefix:
            raise NameError_(self.prefix, "a namespace is an absolute name, without a final /")

    def _is_shared(self, absolute: str) -> bool:
        return any(
            absolute.startswith(entry) if entry.endswith("/") else absolute == entry
            for entry in self.shared
        )

    def inward(self, name: object) -> str:
        """The graph's name for ``name`` as this client spells it (NameError_ if malformed)."""
        absolute = resolve(name)
        return absolute if self._is_shared(absolute) else resolve(self.prefix + absolute)

    def outward(self, name: str) -> str | None:
        """How this client names the graph's absolute ``name``; None if it lies outside."""
        if self._is_shared(name):
            return name
        if name.startswith(self.prefix + "/"):
            return name[len(self.prefix) :]
        return None
