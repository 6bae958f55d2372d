"""Exceptions of the lab daemon.

Every error that a person can act on is one of these; each carries its fields and
formats itself, so a handler turns it into a protocol reply without string surgery.

    LabError
    ├── GraphError                 the robot graph refused something
    │   ├── UnknownTypeError       no such message, service or action type
    │   ├── MessageError           a message does not fit its type (names the field)
    │   ├── NameError_             a topic, service or action name is malformed
    │   ├── TypeMismatchError      a name is already used with another type
    │   ├── NotFoundError          no such topic, service or action
    │   ├── ConflictError          the name is already provided by someone else
    │   ├── OwnedError             the name is the lab's: a client may not publish or provide it
    │   └── InterfaceError         a repository's own interface definition is malformed or conflicts
    ├── BridgeError                the bridge refused a frame from a client
    │   ├── FrameError             a frame is not a well-formed rosbridge operation
    │   ├── ProtectedError         the name is protected and never crosses the bridge
    │   └── LimitError             a per-client limit would be exceeded
    ├── SimError                   a simulated robot or task refused something
    │   ├── UnknownTaskError       no task of that name
    │   ├── ParamError             a task parameter is unknown, of the wrong kind, out of range
    │   └── EpisodeOverError       the episode has ended; no more steps
    ├── RecordError                a trial's record could not be written (a full disk)
    ├── SummaryError               a record could not be summarized for its page
    ├── HostedError                a hosted repository refused a name, a path or a commit
    │   ├── NotHosted              no such hosted repository, or no such commit in it
    │   └── GitFailed              git itself failed on a hosted repository (a lab fault)
    └── PortInUse                  a port the lab was told to listen on is taken
"""

from __future__ import annotations

import difflib
import errno
import os
from collections.abc import Sequence


class LabError(Exception):
    """Base class of the lab daemon's expected errors."""


class GraphError(LabError):
    """The robot graph refused an operation."""


class UnknownTypeError(GraphError):
    """A type name does not resolve to a known interface."""

    def __init__(self, kind: str, name: str) -> None:
        self.kind = kind
        self.name = name
        super().__init__(f"unknown {kind} type {name!r}")


class MessageError(GraphError):
    """A message value does not fit its type.

    ``path`` is the chain of field names (and list indices) from the root of the
    message to the offending value; handlers prefix it with where the message sat
    in the frame, so the client reads ``publish.msg.linear.x must be a number``.
    """

    def __init__(self, reason: str, path: Sequence[str | int] = ()) -> None:
        self.reason = reason
        self.path: list[str | int] = list(path)
        super().__init__(reason)

    def prefixed(self, *segments: str | int) -> MessageError:
        """Return the same error with ``segments`` put in front of its path."""
        return MessageError(self.reason, [*segments, *self.path])

    @property
    def where(self) -> str:
        out = ""
        for seg in self.path:
            out += f"[{seg}]" if isinstance(seg, int) else (f".{seg}" if out else seg)
        return out

    def __str__(self) -> str:
        return f"{self.where} {self.reason}" if self.path else self.reason


class NameError_(GraphError):
    """A graph name is malformed."""

    def __init__(self, name: str, reason: str) -> None:
        self.name = name
        self.reason = reason
        super().__init__(f"invalid name {name!r}: {reason}")


class TypeMismatchError(GraphError):
    """A name is already in use with another type."""

    def __init__(self, kind: str, name: str, have: str, want: str) -> None:
        self.kind = kind
        self.name = name
        self.have = have
        self.want = want
        super().__init__(f"{kind} {name} has type {have}, not {want}")


class NotFoundError(GraphError):
    """No topic, service or action of that name exists."""

    def __init__(self, kind: str, name: str, hint: str = "") -> None:
        self.kind = kind
        self.name = name
        self.hint = hint
        super().__init__(f"no {kind} {name}" + (f": {hint}" if hint else ""))


class ConflictError(GraphError):
    """A service or action name is already provided by another node."""

    def __init__(self, kind: str, name: str, owner: str) -> None:
        self.kind = kind
        self.name = name
        self.owner = owner
        super().__init__(f"{kind} {name} is already provided by {owner}")


class OwnedError(GraphError):
    """A client tried to publish on, or provide, a name that belongs to the lab.

    ``kind`` is ``topic``, ``service`` or ``action``; ``owner`` the lab node that
    publishes or provides it, or None when the name lies in one of the lab's own
    namespaces (``namespace``), which clients may not use whoever holds it now.
    """

    def __init__(
        self, kind: str, name: str, *, owner: str | None = None, namespace: str | None = None
    ) -> None:
        self.kind = kind
        self.name = name
        self.owner = owner
        self.namespace = namespace
        verb = "advertise or publish on" if kind == "topic" else "provide"
        does = "publishes" if kind == "topic" else "provides"
        if owner is not None:
            why = f" ({owner} {does} it)"
        else:
            why = f", as every name under {namespace} does"
        super().__init__(f"{kind} {name} belongs to the lab{why}; clients cannot {verb} it")


class InterfaceError(GraphError):
    """A repository's own ``.msg``, ``.srv`` or ``.action`` file cannot be registered.

    ``path`` is the file in the repository, ``line`` (from 1) the line at fault, or None
    when the file as a whole is (its name, its package).
    """

    def __init__(self, path: str, reason: str, line: int | None = None) -> None:
        self.path = path
        self.line = line
        self.reason = reason
        where = f"{path}, line {line}" if line is not None else path
        super().__init__(f"{where}: {reason}")


class BridgeError(LabError):
    """The bridge refused a frame."""


class FrameError(BridgeError):
    """A frame is not a well-formed rosbridge operation."""

    def __init__(self, reason: str, op: str | None = None) -> None:
        self.reason = reason
        self.op = op
        super().__init__(reason)


class ProtectedError(BridgeError):
    """The name is protected: it never crosses the bridge."""

    def __init__(self, name: str) -> None:
        self.name = name
        super().__init__(f"{name} is protected")


class LimitError(BridgeError):
    """A per-client limit would be exceeded."""

    def __init__(self, what: str, limit: int) -> None:
        self.what = what
        self.limit = limit
        super().__init__(f"too many {what} (the limit is {limit})")


class SimError(LabError):
    """A simulated robot or task refused something."""


class UnknownTaskError(SimError):
    def __init__(self, name: str, known: Sequence[str]) -> None:
        self.name = name
        self.known = list(known)
        close = difflib.get_close_matches(name, self.known, n=1)
        hint = f" (did you mean {close[0]}?)" if close else ""
        super().__init__(f"no task {name!r}{hint}; the tasks are {', '.join(self.known)}")


class ParamError(SimError):
    """A task parameter is not acceptable; ``valid`` lists the task's parameters."""

    def __init__(self, name: str, reason: str, valid: Sequence[str] = ()) -> None:
        self.name = name
        self.reason = reason
        self.valid = list(valid)
        text = f"parameter {name} {reason}"
        if self.valid:
            text += "; the parameters are:\n  " + "\n  ".join(self.valid)
        super().__init__(text)


class EpisodeOverError(SimError):
    def __init__(self, status: str, reason: str) -> None:
        self.status = status
        self.reason = reason
        super().__init__(f"the episode has ended ({status}: {reason})")


class RecordError(LabError):
    """A record could not be written, so it was deleted: ``error`` is what the disk said."""

    def __init__(self, path: str | os.PathLike[str], error: OSError) -> None:
        self.path = os.fspath(path)
        self.error = error
        self.disk_full = error.errno in (errno.ENOSPC, errno.EDQUOT)
        what = error.strerror or str(error)
        lead = "the lab's disk is full: " if self.disk_full else ""
        super().__init__(
            f"{lead}the trial's record could not be written ({what}: {self.path});"
            " the partial record was deleted"
        )


class SummaryError(LabError):
    """A record could not be summarized (unreadable, or it took too long)."""


class HostedError(LabError):
    """A hosted repository (``labd.hosted``) refused something: ``what`` (a user or
    repository name, a file's path, a commit) and ``reason``, what to do instead."""

    def __init__(self, what: str, reason: str) -> None:
        self.what = what
        self.reason = reason
        super().__init__(f"{what}: {reason}")


class NotHosted(HostedError):
    """No repository ``user/name`` on this lab (``commit`` None), or no ``commit`` in it."""

    def __init__(self, user: str, name: str, commit: str | None = None) -> None:
        self.user = user
        self.name = name
        self.commit = commit
        if commit is None:
            super().__init__(f"repository {user}/{name}", "is not on this lab")
        else:
            super().__init__(f"repository {user}/{name}", f"has no commit {commit}")


class GitFailed(HostedError):
    """git failed on a hosted repository: ``command`` in ``repository``, and the last line
    git wrote (``stderr``). The lab's fault (a full disk, a damaged repository), not the
    caller's."""

    def __init__(self, command: str, repository: str, stderr: str) -> None:
        self.command = command
        self.repository = repository
        self.stderr = stderr
        super().__init__(f"git {command} in {repository}", stderr)


class PortInUse(LabError):
    """A port the lab was told to listen on is taken; ``flag`` is the option to change."""

    def __init__(self, host: str, port: int, flag: str) -> None:
        self.host = host
        self.port = port
        self.flag = flag
        super().__init__(
            f"port {port} on {host} is in use (by another labd, or another program);"
            f" choose another with {flag} PORT (0 picks a free one)"
        )
