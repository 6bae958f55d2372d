"""A checkout's files on the host: read and written without ever following a link.

A repository may hold symbolic links, and a controller may rely on them: ``data ->
/mnt/x`` or ``lib -> ../shared`` resolve inside its sandbox, against the sandbox's own
tree, and that is its business. On the host the same links would resolve against the
lab's machine (``lab.toml -> /etc/passwd``), so the lab follows none of them:

- ``RepositoryFiles`` is how the lab reads a file of a checkout: ``lab.toml``, the
  requirements file, and any file or folder of files a later ``lab.toml`` key names
  (``listdir`` then ``read_text`` for a folder of ``.msg`` definitions). A name that is
  a link, or that passes through one, is refused with a ``RepositoryFileError`` that
  names the file in the repository and tells nothing of what the link points at;
- ``TreeWriter`` is how a checkout is written (an export from git, a copy of a folder):
  links are made as they are, and nothing is ever written through one; a path that
  would be is a ``RepositoryError``;
- ``copy_files`` copies a folder on disk (a local work tree) into a ``TreeWriter``
  without following a link of the folder either.

Every path is walked one folder at a time, each folder opened with ``O_NOFOLLOW``
relative to the one before, so what is checked is what is read: there is no moment
between a check and an open for a link to slip in.
"""

from __future__ import annotations

import contextlib
import errno
import os
import posixpath
import stat
from collections.abc import Iterable
from pathlib import Path, PurePosixPath
from types import TracebackType
from typing import IO, Literal

from repository.units import KiB, MiB
from scheduler.errors import FileNotInRepository, RepositoryError, RepositoryFileError

MAX_BYTES = MiB  # what the lab reads of one file: lab.toml, requirements, a .msg
CHUNK = MiB

_DIRECTORY = os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | os.O_CLOEXEC
# O_NONBLOCK: opening a FIFO must not wait for a writer; fstat then says it is no file.
_FILE = os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC
_NEW_FILE = os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC

Kind = Literal["missing", "link", "file", "other"]


class _Blocked(Exception):
    """A step of a walk that is not a folder: ``parts[index]`` is ``kind``."""

    def __init__(self, index: int, kind: Kind, target: str = "") -> None:
        self.index = index
        self.kind = kind
        self.target = target  # a link's target, as the repository wrote it
        super().__init__(f"step {index} is {kind}")


def parts_of(name: str) -> tuple[str, ...] | None:
    """The components of a path relative to the repository's root; None if it is none.

    ``a/./b`` and ``a//b`` are ``("a", "b")``; an absolute path, ``..`` anywhere, and
    the empty path are not paths inside the repository.
    """
    if not name or "\0" in name:
        return None
    path = PurePosixPath(name)
    if path.is_absolute() or ".." in path.parts or not path.parts:
        return None
    return path.parts


def _kind(parent: int, name: str) -> tuple[Kind, str]:
    """What ``name`` in the folder ``parent`` is, without following it."""
    try:
        st = os.lstat(name, dir_fd=parent)
    except FileNotFoundError:
        return "missing", ""
    if stat.S_ISLNK(st.st_mode):
        try:
            return "link", os.readlink(name, dir_fd=parent)
        except OSError:
            return "link", ""
    if stat.S_ISREG(st.st_mode):
        return "file", ""
    return "other", ""


def _open_folder(root: int, parts: tuple[str, ...], *, create: bool = False) -> int:
    """Open the folder ``parts`` below the open folder ``root``, following no link.

    With ``create``, missing folders are made (0755). Raises ``_Blocked`` at the first
    step that is missing (without ``create``), a link, a file or anything else.
    """
    fd = os.dup(root)
    try:
        for index, part in enumerate(parts):
            try:
                step = os.open(part, _DIRECTORY, dir_fd=fd)
            except OSError as err:
                if err.errno not in (errno.ENOENT, errno.ELOOP, errno.ENOTDIR):
                    raise
                kind, target = _kind(fd, part)
                if kind != "missing" or not create:
                    raise _Blocked(index, kind, target) from None
                # Made meanwhile? The open below checks what it is.
                with contextlib.suppress(FileExistsError):
                    os.mkdir(part, 0o755, dir_fd=fd)
                step = os.open(part, _DIRECTORY, dir_fd=fd)
            os.close(fd)
            fd = step
        return fd
    except BaseException:
        os.close(fd)
        raise


def _where(folder: tuple[str, ...], target: str) -> str:
    """Where a link points, read from its text alone (nothing on the host is looked at)."""
    if not target or target.startswith("/"):
        return "to somewhere outside the repository"
    joined = posixpath.normpath(posixpath.join(*folder, target))
    if joined == ".." or joined.startswith("../"):
        return "to somewhere outside the repository"
    return f"to {joined!r} in the repository"


def _refusal(name: str, parts: tuple[str, ...], blocked: _Blocked, what: str) -> Exception:
    """The error for a walk to ``name`` that stopped at ``blocked``."""
    at = "/".join(parts[: blocked.index + 1])
    last = blocked.index == len(parts) - 1
    if blocked.kind == "link":
        where = _where(parts[: blocked.index], blocked.target)
        subject = "it" if last else at
        return RepositoryFileError(
            name,
            f"{subject} is a symbolic link ({where}); the lab reads {name} only as a"
            f" regular {what} of the repository, never through a link",
        )
    if blocked.kind == "missing":
        return FileNotInRepository(name)
    if not last:
        return FileNotInRepository(name, f"it is not in the repository ({at} is not a folder)")
    return RepositoryFileError(name, f"it is not a regular {what}")


class RepositoryFiles:
    """The files of a checkout in ``root``, read as the repository's own.

    Names are paths relative to the repository's root, with ``/`` between folders. A
    name that is or passes through a symbolic link is refused, as is one that leaves
    the repository (absolute, ``..``); nothing is ever read through a link.
    """

    def __init__(self, root: Path, *, limit: int = MAX_BYTES) -> None:
        self.root = root
        self.limit = limit  # bytes read of one file at most

    def is_file(self, name: str) -> bool:
        """Whether ``name`` is a regular file (False: nothing is there).

        A link, a folder or anything else there is a ``RepositoryFileError``: the
        repository has something at that name that the lab will not read.
        """
        try:
            os.close(self._open(name))
        except FileNotInRepository:
            return False
        return True

    def read_bytes(self, name: str) -> bytes:
        """The content of the regular file ``name`` (at most ``limit`` bytes)."""
        fd = self._open(name)
        try:
            data = b""
            while chunk := os.read(fd, min(CHUNK, self.limit + 1 - len(data))):
                data += chunk
                if len(data) > self.limit:
                    raise RepositoryFileError(
                        name, f"it is larger than the {self.limit // KiB} KiB the lab reads"
                    )
            return data
        except OSError as err:
            raise RepositoryFileError(name, f"it could not be read ({err.strerror})") from None
        finally:
            os.close(fd)

    def read_text(self, name: str) -> str:
        """The content of the regular file ``name`` as UTF-8 text."""
        try:
            return self.read_bytes(name).decode("utf-8")
        except UnicodeDecodeError:
            raise RepositoryFileError(name, "it is not UTF-8 text") from None

    def listdir(self, folder: str, suffix: str = "") -> list[str]:
        """The regular files directly in ``folder`` whose names end with ``suffix``.

        Returned as names relative to the repository's root, sorted, ready for
        ``read_text``. ``folder`` itself must be a folder reached through no link; an
        entry that matches ``suffix`` but is a link is refused (the lab would have read
        it); subfolders and other entries are left out.
        """
        parts = self._parts(folder, "folder") if folder not in ("", ".") else ()
        fd = self._folder(folder, parts, len(parts), "folder")
        try:
            with os.scandir(fd) as entries:
                found = []
                for entry in entries:
                    if not entry.name.endswith(suffix):
                        continue
                    name = "/".join((*parts, entry.name))
                    if entry.is_symlink():
                        link = _Blocked(len(parts), "link", os.readlink(entry.name, dir_fd=fd))
                        raise _refusal(name, (*parts, entry.name), link, "file")
                    if entry.is_file(follow_symlinks=False):
                        found.append(name)
        except OSError as err:
            raise RepositoryFileError(folder, f"it could not be listed ({err.strerror})") from None
        finally:
            os.close(fd)
        return sorted(found)

    def _parts(self, name: str, what: str = "file") -> tuple[str, ...]:
        parts = parts_of(name)
        if parts is None:
            raise RepositoryFileError(name, f"it is not the path of a {what} inside the repository")
        return parts

    def _folder(self, name: str, parts: tuple[str, ...], depth: int, what: str) -> int:
        """An open descriptor of the folder ``parts[:depth]``, on the way to ``name``."""
        try:
            root = os.open(self.root, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
            try:
                return _open_folder(root, parts[:depth])
            finally:
                os.close(root)
        except _Blocked as blocked:
            if what == "folder" and blocked.kind == "file" and blocked.index == len(parts) - 1:
                raise RepositoryFileError(name, "it is a file, not a folder") from None
            raise _refusal(name, parts, blocked, what) from None
        except OSError as err:
            raise RepositoryFileError(name, f"it could not be read ({err.strerror})") from None

    def _open(self, name: str) -> int:
        """An open descriptor of the regular file ``name``, reached through no link."""
        parts = self._parts(name)
        folder = self._folder(name, parts, len(parts) - 1, "file")
        try:
            fd = os.open(parts[-1], _FILE, dir_fd=folder)
        except OSError as err:
            try:
                kind, target = _kind(folder, parts[-1])
            except OSError:
                kind, target = "other", ""
            if err.errno not in (errno.ENOENT, errno.ELOOP, errno.ENXIO) or kind == "file":
                raise RepositoryFileError(name, f"it could not be read ({err.strerror})") from None
            raise _refusal(name, parts, _Blocked(len(parts) - 1, kind, target), "file") from None
        finally:
            os.close(folder)
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            os.close(fd)
            what = "a folder, not a file" if stat.S_ISDIR(mode) else "not a regular file"
            raise RepositoryFileError(name, f"it is {what}")
        return fd


class TreeWriter:
    """Writes a repository's files into the folder ``root``, never through a link.

    Folders on the way are made as needed; a link is made as it is, whatever it
    points at; a file or link whose path passes through a link already written, or
    that is written twice, is a ``RepositoryError`` naming ``source``. Use it as a
    context manager: it holds ``root`` open, so the checkout stays where it began.
    """

    def __init__(self, root: Path, source: str) -> None:
        self.root = root
        self.source = source  # the repository, as errors name it
        self._fd = -1

    def __enter__(self) -> TreeWriter:
        self._fd = os.open(self.root, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
        return self

    def __exit__(
        self,
        kind: type[BaseException] | None,
        error: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        os.close(self._fd)
        self._fd = -1

    def directory(self, name: str) -> None:
        """Make the folder ``name`` (and those on its way), unless it is there."""
        os.close(self._folder(name, self._parts(name)))

    def file(self, name: str, data: IO[bytes], *, executable: bool) -> None:
        """Write a new regular file ``name`` from ``data`` (0755 or 0644)."""
        parts = self._parts(name)
        folder = self._folder(name, parts[:-1])
        try:
            fd = os.open(parts[-1], _NEW_FILE, 0o600, dir_fd=folder)
        except FileExistsError:
            raise self._twice(name) from None
        finally:
            os.close(folder)
        with os.fdopen(fd, "wb") as out:
            while chunk := data.read(CHUNK):
                out.write(chunk)
            os.fchmod(out.fileno(), 0o755 if executable else 0o644)

    def symlink(self, name: str, target: str) -> None:
        """Make the link ``name`` -> ``target``, as the repository has it."""
        parts = self._parts(name)
        folder = self._folder(name, parts[:-1])
        try:
            os.symlink(target, parts[-1], dir_fd=folder)
        except FileExistsError:
            raise self._twice(name) from None
        finally:
            os.close(folder)

    def _parts(self, name: str) -> tuple[str, ...]:
        parts = parts_of(name)
        if parts is None:
            raise RepositoryError(self.source, f"{name!r} is not a path inside the repository")
        return parts

    def _folder(self, name: str, parts: tuple[str, ...]) -> int:
        try:
            return _open_folder(self._fd, parts, create=True)
        except _Blocked as blocked:
            at = "/".join(parts[: blocked.index + 1])
            if blocked.kind == "link" and at == name:
                reason = f"{name} is both a symbolic link and a folder in it"
            elif blocked.kind == "link":
                reason = (
                    f"{name} lies behind the symbolic link {at}; the lab writes a"
                    " repository's files only into its own folders, never through a link"
                )
            else:
                reason = f"{name} needs {at} to be a folder, and it is a file too"
            raise RepositoryError(self.source, reason) from None

    def _twice(self, name: str) -> RepositoryError:
        return RepositoryError(self.source, f"{name} appears twice in it")


def copy_files(base: Path, names: Iterable[str], writer: TreeWriter) -> None:
    """Copy the files ``names`` (relative to the folder ``base``) through ``writer``.

    A link is copied as a link; a regular file with its content and executable bit;
    a name that is missing, a folder or anything else is left out, and so is one that
    lies behind a link of ``base`` (as git sees a work tree: nothing is tracked there).
    """
    root = os.open(base, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
    try:
        for name in names:
            parts = parts_of(name)
            if parts is None:
                raise RepositoryError(writer.source, f"{name!r} is not a path inside it")
            try:
                folder = _open_folder(root, parts[:-1])
            except _Blocked:
                continue
            try:
                _copy_one(folder, parts[-1], name, writer)
            except OSError as err:
                raise RepositoryError(
                    writer.source, f"{name} could not be read ({err.strerror})"
                ) from None
            finally:
                os.close(folder)
    finally:
        os.close(root)


def _copy_one(folder: int, last: str, name: str, writer: TreeWriter) -> None:
    kind, target = _kind(folder, last)
    if kind == "link":
        writer.symlink(name, target)
    elif kind == "file":
        fd = os.open(last, _FILE, dir_fd=folder)
        with os.fdopen(fd, "rb") as data:
            st = os.fstat(data.fileno())
            if stat.S_ISREG(st.st_mode):  # still a file: it was not swapped meanwhile
                writer.file(name, data, executable=bool(st.st_mode & stat.S_IXUSR))
