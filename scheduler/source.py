"""Where a controller's code comes from: a local folder or a git repository by URL.

``checkout`` puts the exact files a trial runs into a folder and says what they
are: the commit (when there is one), git's tree hash, and ``tree``, a digest of the
files themselves that names the code whatever its origin.

- A URL (``https://``, ``ssh://``, ``git://``, ``file://``, ``user@host:path``) is
  fetched into a bare mirror in the cache (scheduler.fetch: no hooks run, submodules
  only from the allow-list, each exported into its path) and the commit the ref
  resolves to is exported. A full commit id already in the mirror is exported without
  fetching, so reruns work after a branch has moved.
- With a fetch policy (a lab's worker), a local repository path is taken through the
  mirror cache as well, under that policy: the trial runs the pinned commit, whatever
  the folder holds now. Without one (``labd run``), URLs are fetched under
  ``PREFLIGHT`` and local folders are read from disk as follows.
- A local folder inside a git work tree is taken as it is on disk (tracked and
  untracked files, not ignored ones), so a pre-flight runs what the user is editing;
  ``commit`` is HEAD only when the folder has no uncommitted changes, otherwise None
  and ``dirty`` is set. With ``ref`` given, that commit's files are exported instead.
- A plain folder is copied as it is; it has no commit.
"""

from __future__ import annotations

import hashlib
import io
import os
import re
import shutil
import stat
import tarfile
from dataclasses import dataclass
from pathlib import Path

import git

from scheduler.errors import RefNotFound, RepositoryError
from scheduler.fetch import PREFLIGHT, FetchPolicy, fetch_commit

URL = re.compile(r"^(?:[a-z][a-z0-9+.-]*://|[\w.-]+@[\w.-]+:)")
SKIP = {".git", "__pycache__"}


@dataclass(frozen=True)
class Source:
    """What a trial runs, and how to name it."""

    repository: str  # the URL, or the folder's absolute path
    commit: str | None  # None for a plain folder or one with uncommitted changes
    tree: str  # "sha256:..." over the files run (paths, executable bits, contents)
    git_tree: str | None  # git's tree hash of the commit's folder
    subdir: str  # the folder within the repository ("" for its root)
    dirty: bool  # a local folder that differs from its commit


def is_url(source: str) -> bool:
    return bool(URL.match(source))


def checkout(
    source: str, ref: str | None, dest: Path, cache: Path, policy: FetchPolicy | None = None
) -> Source:
    """Put the files of ``source`` at ``ref`` into ``dest`` (which must not exist).

    ``policy`` is the lab's fetch policy; None for ``labd run`` (see the module's doc).
    """
    if policy is not None or is_url(source):
        return _from_mirror(source, ref, dest, cache, policy or PREFLIGHT)
    return _from_folder(Path(source), ref, dest)


def tree_digest(folder: Path) -> str:
    """A digest of a folder's files: relative paths, executable bits and contents."""
    entries = []
    for path in sorted(_files(folder)):
        relative = path.relative_to(folder).as_posix()
        if path.is_symlink():
            entries.append(f"{relative}\0link\0{os.readlink(path)}\n")
            continue
        mode = "x" if path.stat().st_mode & stat.S_IXUSR else "-"
        entries.append(f"{relative}\0{mode}\0{hashlib.sha256(path.read_bytes()).hexdigest()}\n")
    return "sha256:" + hashlib.sha256("".join(entries).encode()).hexdigest()


def _files(folder: Path) -> list[Path]:
    found = []
    for root, dirs, names in os.walk(folder):
        dirs[:] = [d for d in dirs if d not in SKIP]
        found += [Path(root) / name for name in names]
    return found


def _from_folder(folder: Path, ref: str | None, dest: Path) -> Source:
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
        _copy(folder, dest, sorted(_files(folder)))
        return Source(str(folder), None, tree_digest(dest), None, "", dirty=False)
    with repo:
        root = Path(repo.working_tree_dir or folder).resolve()
        subdir = folder.relative_to(root).as_posix() if folder != root else ""
        if ref is not None:
            commit = _resolve(repo, str(folder), ref)
            _export(repo, commit, subdir, dest, str(folder))
            return Source(
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
        paths = sorted(root / p for p in listed if p and (root / p).exists())
        _copy(root / subdir if subdir else root, dest, paths)
        dirty = bool(repo.git.status("--porcelain", "--", subdir or "."))
        head = None if dirty or not repo.head.is_valid() else repo.head.commit.hexsha
        return Source(
            str(folder),
            head,
            tree_digest(dest),
            _git_tree(repo, head, subdir) if head else None,
            subdir,
            dirty,
        )


def _from_mirror(
    source: str, ref: str | None, dest: Path, cache: Path, policy: FetchPolicy
) -> Source:
    fetched = fetch_commit(source, ref, cache, policy)
    with git.Repo(fetched.mirror) as repo:
        _export(repo, fetched.commit, "", dest, fetched.repository)
        git_tree = _git_tree(repo, fetched.commit, "")
    for sub in fetched.submodules:
        if not (dest / sub.path).resolve().is_relative_to(dest.resolve()):
            raise RepositoryError(fetched.repository, f"submodule path {sub.path!r} leaves it")
        with git.Repo(sub.mirror) as repo:
            _export(repo, sub.commit, "", dest / sub.path, sub.repository, into=True)
    return Source(fetched.repository, fetched.commit, tree_digest(dest), git_tree, "", False)


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
    repo: git.Repo, commit: str, subdir: str, dest: Path, source: str, *, into: bool = False
) -> None:
    """Extract ``commit``'s files (of ``subdir``) into ``dest``: a new folder, or with
    ``into`` an existing one (a submodule's path, which the superproject's export made).
    """
    buffer = io.BytesIO()
    try:
        repo.archive(buffer, commit, format="tar", path=subdir or None)
    except git.GitCommandError as err:
        raise RepositoryError(
            source, f"could not export {commit[:12]}: {_git_reason(err)}"
        ) from None
    buffer.seek(0)
    dest.mkdir(parents=True, exist_ok=into)
    prefix = f"{subdir}/" if subdir else ""
    with tarfile.open(fileobj=buffer) as archive:
        for member in archive.getmembers():
            if not member.name.startswith(prefix) or member.name == subdir:
                continue
            member.name = member.name[len(prefix) :]
            if member.isfile() or member.isdir() or member.issym():
                archive.extract(member, dest, filter="data")


def _copy(base: Path, dest: Path, paths: list[Path]) -> None:
    dest.mkdir(parents=True)
    for path in paths:
        target = dest / path.relative_to(base)
        target.parent.mkdir(parents=True, exist_ok=True)
        if path.is_symlink():
            target.symlink_to(os.readlink(path))
        elif path.is_file():
            shutil.copy2(path, target)


def _git_reason(err: git.GitCommandError) -> str:
    text = str(err.stderr or err).strip().splitlines()
    lines = [line.strip() for line in text if line.strip()]
    return lines[-1].removeprefix("stderr: ").strip("'") if lines else "git failed"
