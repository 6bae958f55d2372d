"""Where a controller's code comes from: a local folder or a git repository by URL.

``checkout`` puts the exact files a trial runs into a folder and says what they
are: the commit (when there is one), git's tree hash, and ``tree``, a digest of the
files themselves that names the code whatever its origin.

- A URL (``https://``, ``ssh://``, ``git://``, ``file://``, ``user@host:path``) is
  fetched into a bare mirror in the cache (scheduler.fetch: no hooks run, submodules
  only from the allow-list, each exported into its path) and the commit the ref
  resolves to is exported. A full commit id already in the mirror is exported without
  fetching, so reruns work after a branch has moved. Before anything is written, the
  size of the commit's files (its submodules' included) is read from git's trees and
  held to the policy's ``max_checkout_bytes`` and ``max_checkout_files``: a repository
  compresses well (1 GiB of zeros is about 1 MiB in git, and one blob or tree may be
  named by a thousand paths), so its size says little of its checkout's
  (``CheckoutTooLarge``).
- With a fetch policy (a lab's worker), a local repository path is taken through the
  mirror cache as well, under that policy: the trial runs the pinned commit, whatever
  the folder holds now. Without one (``labd run``), URLs are fetched under
  ``PREFLIGHT`` and local folders are read from disk as follows.
- A local folder inside a git work tree is taken as it is on disk (tracked and
  untracked files, not ignored ones), so a pre-flight runs what the user is editing;
  ``commit`` is HEAD only when the folder has no uncommitted changes, otherwise None
  and ``dirty`` is set. With ``ref`` given, that commit's files are exported instead.
- A plain folder is copied as it is; it has no commit.

Every export streams ``git archive`` into the folder a file at a time: the lab never
holds a checkout in memory.

The repository's symbolic links are kept as they are: they are the controller's
business inside its sandbox. The lab itself follows none of them on the host: files
are written with ``scheduler.files.TreeWriter`` and copied with ``copy_files``, and
``tree_digest`` records a link's target, never what it points at. Whatever goes wrong
while checking out is a ``RepositoryError`` saying what, never another exception.
"""

from __future__ import annotations

import hashlib
import logging
import os
import posixpath
import re
import stat
import subprocess
import sys
import tarfile
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import IO

import git

from repository.manifest import Code
from repository.units import MiB
from scheduler.errors import CheckoutTooLarge, RefNotFound, RepositoryError, TrialError
from scheduler.fetch import PREFLIGHT, Fetched, FetchPolicy, fetch_commit
from scheduler.files import TreeWriter, copy_files

log = logging.getLogger("scheduler.source")
URL = re.compile(r"^(?:[a-z][a-z0-9+.-]*://|[\w.-]+@[\w.-]+:)")
SKIP = {".git", "__pycache__"}


def is_url(source: str) -> bool:
    return bool(URL.match(source))


def checkout(
    source: str, ref: str | None, dest: Path, cache: Path, policy: FetchPolicy | None = None
) -> Code:
    """Put the files of ``source`` at ``ref`` into ``dest`` (which must not exist).

    ``policy`` is the lab's fetch policy; None for ``labd run`` (see the module's doc).
    Every failure is a ``TrialError`` (a ``RepositoryError`` with the reason).
    """
    try:
        if policy is not None or is_url(source):
            return _from_mirror(source, ref, dest, cache, policy or PREFLIGHT)
        return _from_folder(Path(source), ref, dest)
    except TrialError:
        raise
    except (OSError, git.GitError, tarfile.TarError, UnicodeError) as err:
        # Not the repository's doing (a full disk, git broken...): say so, keep the trace.
        log.warning("checking out %s failed", source, exc_info=True)
        raise RepositoryError(source, f"could not be checked out: {_describe(err)}") from None


def tree_digest(folder: Path) -> str:
    """A digest of a folder's files: relative paths, executable bits and contents.

    A symbolic link counts as its target's text (to a file or a folder alike); no link
    is followed.
    """
    entries = []
    for relative in _names(folder):
        path = folder / relative
        st = path.lstat()
        if stat.S_ISLNK(st.st_mode):
            entries.append(f"{relative}\0link\0{os.readlink(path)}\n")
        elif stat.S_ISREG(st.st_mode):
            mode = "x" if st.st_mode & stat.S_IXUSR else "-"
            entries.append(f"{relative}\0{mode}\0{_sha256(path)}\n")
    return "sha256:" + hashlib.sha256("".join(entries).encode()).hexdigest()


def _names(folder: Path) -> list[str]:
    """Every file and link below ``folder`` (not .git's), relative, in the order of
    their paths' components (as the tree digest always had them); links to folders are
    entries too, not followed."""
    found = []
    for root, dirs, names in os.walk(folder):
        base = Path(root)
        found += [
            (base / d).relative_to(folder).as_posix() for d in dirs if (base / d).is_symlink()
        ]
        dirs[:] = [d for d in dirs if d not in SKIP and not (base / d).is_symlink()]
        found += [(base / name).relative_to(folder).as_posix() for name in names]
    return sorted(found, key=lambda name: PurePosixPath(name).parts)  # "a/b" before "a-c"


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC), "rb") as f:
        while block := f.read(MiB):
            digest.update(block)
    return digest.hexdigest()


def _from_folder(folder: Path, ref: str | None, dest: Path) -> Code:
    if not folder.is_dir():
        raise RepositoryError(str(folder), "no such folder")
    folder = folder.resolve()
    try:
        repo = git.Repo(folder, search_parent_directories=True)
    except (git.InvalidGitRepositoryError, git.NoSuchPathError):
        if ref is not None:
            raise RepositoryError(
                str(folder), "is not in a git repository, so --ref means nothing here"
            ) from None
        dest.mkdir(parents=True)
        with TreeWriter(dest, str(folder)) as writer:
            copy_files(folder, _names(folder), writer)
        return Code(str(folder), None, tree_digest(dest), None, "", dirty=False)
    with repo:
        root = Path(repo.working_tree_dir or folder).resolve()
        subdir = folder.relative_to(root).as_posix() if folder != root else ""
        if ref is not None:
            commit = _resolve(repo, str(folder), ref)
            dest.mkdir(parents=True)
            with TreeWriter(dest, str(folder)) as writer:
                _export(repo, commit, subdir, writer, str(folder))
            return Code(
                str(folder),
                commit,
                tree_digest(dest),
                _git_tree(repo, commit, subdir),
                subdir,
                dirty=False,
            )
        listed = repo.git.ls_files(
            "--cached", "--others", "--exclude-standard", "-z", "--", subdir or "."
        ).split("\0")
        prefix = f"{subdir}/" if subdir else ""
        names = sorted(p.removeprefix(prefix) for p in listed if p and p.startswith(prefix))
        dest.mkdir(parents=True)
        with TreeWriter(dest, str(folder)) as writer:
            copy_files(folder, names, writer)
        dirty = bool(repo.git.status("--porcelain", "--", subdir or "."))
        head = None if dirty or not repo.head.is_valid() else repo.head.commit.hexsha
        return Code(
            str(folder),
            head,
            tree_digest(dest),
            _git_tree(repo, head, subdir) if head else None,
            subdir,
            dirty,
        )


def _from_mirror(
    source: str, ref: str | None, dest: Path, cache: Path, policy: FetchPolicy
) -> Code:
    fetched = fetch_commit(source, ref, cache, policy)
    _check_size(fetched, policy)
    dest.mkdir(parents=True)
    with TreeWriter(dest, fetched.repository) as writer:
        with git.Repo(fetched.mirror) as repo:
            _export(repo, fetched.commit, "", writer, fetched.repository)
            git_tree = _git_tree(repo, fetched.commit, "")
        for sub in fetched.submodules:  # outer first: a submodule's folder exists by now
            with git.Repo(sub.mirror) as repo:
                _export(repo, sub.commit, "", writer, sub.repository, into=sub.path)
    return Code(fetched.repository, fetched.commit, tree_digest(dest), git_tree, "", False)


@dataclass(frozen=True)
class Expanded:
    """What a commit's checkout takes: its files' bytes and how many files (and links)."""

    bytes: int
    files: int

    def __add__(self, other: Expanded) -> Expanded:
        return Expanded(self.bytes + other.bytes, self.files + other.files)


def expanded_size(
    git_dir: Path, commit: str, subdir: str = "", stop_past: Expanded | None = None
) -> Expanded:
    """What ``commit``'s files (of ``subdir``) take when checked out: their blobs' sizes
    added up path by path, read from git's trees (``ls-tree -r -l``), nothing expanded.

    Reading stops as soon as either sum is past ``stop_past``'s: what was counted is then
    returned, already too much. (A tree can name a subtree a thousand times, and that one
    another thousand: the count must stop, as the checkout would not.)
    """
    bound = stop_past or Expanded(sys.maxsize, sys.maxsize)
    size = files = 0
    rest = b""
    with _git_stream(git_dir, ["ls-tree", "-r", "-l", "-z", commit], subdir) as run:
        while chunk := run.stdout.read(1 << 16):
            *entries, rest = (rest + chunk).split(b"\0")
            for entry in entries:
                # "<mode> <type> <object> <size>\t<path>"; a gitlink's size is "-"
                field = entry.partition(b"\t")[0].split()[-1]
                if field.isdigit():
                    size += int(field)
                    files += 1
                if size > bound.bytes or files > bound.files:
                    return Expanded(size, files)
        run.whole = True
    if run.process.returncode != 0:
        raise RepositoryError(str(git_dir), f"could not list {commit[:12]}: {run.reason()}")
    return Expanded(size, files)


@dataclass
class _GitRun:
    """A git command whose output is read as a stream (``_git_stream``)."""

    process: subprocess.Popen[bytes]
    stdout: IO[bytes]
    whole: bool = False  # its output was read to the end: let it exit by itself
    stderr: str = ""  # once it ended

    def reason(self) -> str:
        """Git's own last words on its standard error."""
        return _last_line(self.stderr)


@contextmanager
def _git_stream(git_dir: Path, args: list[str], subdir: str) -> Iterator[_GitRun]:
    """``git ARGS`` on the mirror ``git_dir`` (of ``subdir`` only), its output to be read
    as it comes. Afterwards it is reaped; killed first unless its output was read whole
    (it may be blocked writing what is no longer read)."""
    command = [_git(), "--git-dir", str(git_dir), *args, *(["--", subdir] if subdir else [])]
    with tempfile.TemporaryFile() as errors:
        process = subprocess.Popen(  # noqa: S603 - a fixed git command on the lab's mirror
            command, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=errors
        )
        assert process.stdout is not None
        run = _GitRun(process, process.stdout)
        try:
            yield run
        finally:
            if not run.whole:
                process.kill()
            process.stdout.close()
            process.wait()
            errors.seek(0)
            run.stderr = errors.read().decode(errors="replace")


def _check_size(fetched: Fetched, policy: FetchPolicy) -> None:
    """Refuse a commit whose checkout (its submodules' included) is over the policy's
    limits, before anything of it is written."""
    limit = Expanded(policy.max_checkout_bytes, policy.max_checkout_files)
    parts = [(fetched.mirror, fetched.commit), *((s.mirror, s.commit) for s in fetched.submodules)]
    total = Expanded(0, 0)
    for mirror, commit in parts:
        left = Expanded(limit.bytes - total.bytes, limit.files - total.files)
        total += expanded_size(mirror, commit, "", left)
        if total.bytes > limit.bytes:
            raise CheckoutTooLarge(fetched.repository, fetched.commit, limit.bytes, total.bytes)
        if total.files > limit.files:
            raise CheckoutTooLarge(
                fetched.repository, fetched.commit, limit.files, total.files, files=True
            )


def _resolve(repo: git.Repo, source: str, ref: str) -> str:
    try:
        return str(repo.git.rev_parse("--verify", "--quiet", f"{ref}^{{commit}}"))
    except git.GitCommandError:
        raise RefNotFound(source, ref) from None


def _git_tree(repo: git.Repo, commit: str, subdir: str) -> str | None:
    try:
        tree = repo.commit(commit).tree
        return str((tree / subdir).hexsha if subdir else tree.hexsha)
    except (KeyError, ValueError):
        return None


def _export(
    repo: git.Repo,
    commit: str,
    subdir: str,
    writer: TreeWriter,
    source: str,
    *,
    into: str = "",
) -> None:
    """Write ``commit``'s files (of ``subdir``) through ``writer``, below its folder
    ``into`` (a submodule's path; "" for the root).

    Regular files, folders and symbolic links are written, the links as they are;
    nothing else of a tree is (git has nothing else but submodules, exported apart).
    ``git archive`` is read as a stream, one file at a time, never whole.
    """
    failed = ""
    with _git_stream(Path(repo.git_dir), ["archive", "--format=tar", commit], subdir) as run:
        try:
            _untar(run.stdout, subdir, writer, into)
            while run.stdout.read(1 << 16):  # the archive's padding after its end
                pass
            run.whole = True
        except tarfile.TarError as err:
            failed = str(err)
    if run.process.returncode > 0:  # git's own failure (a missing commit...): its words
        raise RepositoryError(source, f"could not export {commit[:12]}: {run.reason()}")
    if not run.whole:
        raise RepositoryError(source, f"could not export {commit[:12]}: {failed}")


def _untar(stream: IO[bytes], subdir: str, writer: TreeWriter, into: str) -> None:
    """Write the members of the tar ``stream`` through ``writer`` as they come."""
    prefix = f"{subdir}/" if subdir else ""
    with tarfile.open(fileobj=stream, mode="r|") as archive:
        for member in archive:
            name = member.name.rstrip("/")
            if not name.startswith(prefix) or name == prefix:
                continue
            name = posixpath.join(into, name.removeprefix(prefix)) if into else name[len(prefix) :]
            if member.isdir():
                writer.directory(name)
            elif member.issym():
                writer.symlink(name, member.linkname)
            elif member.isfile():
                data = archive.extractfile(member)
                assert data is not None  # a regular file's member has data
                writer.file(name, data, executable=bool(member.mode & 0o111))


def _describe(err: BaseException) -> str:
    """What went wrong, without the host paths an OSError carries."""
    if isinstance(err, git.GitCommandError):
        return _git_reason(err)
    if isinstance(err, OSError) and err.strerror:
        return err.strerror
    return type(err).__name__


def _git() -> str:
    return str(git.Git.GIT_PYTHON_GIT_EXECUTABLE or "git")


def _last_line(stderr: str) -> str:
    """Git's own last words, without its ``fatal:`` prefix."""
    lines = [line.strip() for line in stderr.strip().splitlines() if line.strip()]
    return lines[-1].removeprefix("fatal: ") if lines else "git failed"


def _git_reason(err: git.GitCommandError) -> str:
    text = str(err.stderr or err).strip().splitlines()
    lines = [line.strip() for line in text if line.strip()]
    return lines[-1].removeprefix("stderr: ").strip("'") if lines else "git failed"
