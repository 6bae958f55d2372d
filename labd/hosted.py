"""The lab's hosted repositories: bare git repositories the lab writes for its users.

The playground commits a user's script to ``ROOT/USER/NAME.git`` (``ROOT`` is
``DATA/git``), and the lab serves those repositories read-only over git's smart HTTP
(``labd.api.git``), so a trial of a playground script is a commit like any other,
which anyone can clone and rerun. Nothing but ``HostedRepos.commit`` writes them.

A commit is made with git's plumbing, never a work tree: each file is hashed into the
repository, a temporary index gives the tree (nested paths make sub-trees), and
``commit-tree`` makes the commit, whose parent is the current ``main``. Its author and
committer are the user, with the address ``USER@users.labd`` (no real address: the lab
knows none), and both dates are ``when`` (epoch seconds, UTC), passed in: the same
files, message, author, time and parent give the same commit id. A commit whose tree
is the head's makes no new commit. ``main`` moves with a compare-and-swap
(``update-ref main NEW OLD``) while a lock on the repository (``flock`` of
``ROOT/USER/.NAME.lock``) is held, so two threads or processes committing at once
both land, one after the other.

User and repository names follow the lab's rule for user names (``repository.index``
``NAME``: 1 to 64 ASCII letters, digits, ``.``, ``_`` and ``-``, starting with a letter
or digit), and a repository's name does not end in ``.git`` (the lab adds it): no name
can reach outside ``ROOT``. Files are regular files (mode 100644) at relative paths
without ``.``, ``..``, empty or ``.git`` parts.

git runs with a clean environment (no operator's or user's configuration) and blocks:
callers on an event loop run these methods in a thread.
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
import re
import shutil
import subprocess
import tempfile
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path

from labd.errors import GitFailed, HostedError, NotHosted
from repository.index import NAME

log = logging.getLogger("labd.hosted")

BRANCH = "main"
REF = f"refs/heads/{BRANCH}"
MODE = "100644"  # every file a regular, non-executable file
EMAIL_DOMAIN = "users.labd"  # an author's address: USER@users.labd
GIT_TIMEOUT = 60.0  # seconds any one git command may take on a local repository
RULE = "use letters, digits, '.', '_' and '-' (at most 64), starting with a letter or digit"
COMMIT = re.compile(r"[0-9a-f]{4,64}", re.ASCII)
CONTROL = re.compile(r"[\x00-\x1f\x7f]")


def git_environment(extra: Mapping[str, str] | None = None) -> dict[str, str]:
    """The environment git runs in here: the operator's configuration unread, never a
    prompt for credentials, messages in English; ``extra`` added."""
    env = {
        "PATH": os.environ.get("PATH", os.defpath),
        "HOME": os.environ.get("HOME", "/nonexistent"),
        "GIT_CONFIG_GLOBAL": "/dev/null",
        "GIT_CONFIG_NOSYSTEM": "1",
        "GIT_TERMINAL_PROMPT": "0",
        "LC_ALL": "C",
    }
    env.update(extra or {})
    return env


def check_user(user: str) -> None:
    """Refuse a user name outside the rule (HostedError saying the rule)."""
    if not isinstance(user, str) or NAME.fullmatch(user) is None:
        raise HostedError(f"user name {user!r}", RULE)


def check_name(name: str) -> None:
    """Refuse a repository name outside the rule, or ending in ``.git``."""
    if not isinstance(name, str) or NAME.fullmatch(name) is None:
        raise HostedError(f"repository name {name!r}", RULE)
    if name.lower().endswith(".git"):
        raise HostedError(f"repository name {name!r}", "must not end in '.git' (the lab adds it)")


def check_path(path: str) -> None:
    """Refuse a file's path that git or a checkout could read as something else."""
    what = f"path {path!r}"
    if not isinstance(path, str) or not path:
        raise HostedError(what, "a file's path must not be empty")
    if CONTROL.search(path):
        raise HostedError(what, "must not hold control characters")
    if path.startswith("/"):
        raise HostedError(what, "must be relative (no leading '/')")
    parts = path.split("/")
    if any(part in ("", ".", "..") for part in parts):
        raise HostedError(what, "must not have '.', '..' or empty parts")
    if any(part.lower() == ".git" for part in parts):
        raise HostedError(what, "must not have a '.git' part")


def check_paths(paths: Sequence[str]) -> None:
    """Each path is acceptable, and none is both a file and a folder of another."""
    for path in paths:
        check_path(path)
    folders = {"/".join(p.split("/")[:i]) for p in paths for i in range(1, p.count("/") + 1)}
    for path in sorted(set(paths) & folders):
        inside = next(p for p in sorted(paths) if p.startswith(path + "/"))
        raise HostedError(f"path {path!r}", f"is a file and also the folder of {inside!r}")


class HostedRepos:
    """Bare repositories under ROOT/USER/NAME.git, written only by the lab."""

    def __init__(self, root: Path) -> None:
        self.root = root  # created with its first repository

    def path(self, user: str, name: str) -> Path:
        """Where ``user``'s repository ``name`` is (or would be); HostedError if a name
        breaks the rule, before any path is made of it."""
        check_user(user)
        check_name(name)
        return self.root / user / f"{name}.git"

    def commit(
        self,
        user: str,
        name: str,
        files: Mapping[str, bytes],
        message: str,
        *,
        author: str,
        when: int,
    ) -> str:
        """Commit ``files`` (path -> bytes; the whole tree) to ``main`` of ``user``'s
        repository ``name``, made if missing, and return the commit's id: the head's
        when the tree is the head's already."""
        repo = self.path(user, name)
        check_user(author)
        if isinstance(when, bool) or not isinstance(when, int) or when < 0:
            raise HostedError(f"time {when!r}", "must be whole seconds since 1970 (UTC)")
        if not isinstance(message, str) or "\0" in message:
            raise HostedError("commit message", "must be text without NUL characters")
        paths = sorted(files)
        check_paths(paths)
        with self._locked(user, name):
            if not repo.is_dir():
                self._create(repo)
            old = self._head(repo)
            tree = self._tree(repo, files, paths)
            if old is not None and self._git(repo, "rev-parse", f"{old}^{{tree}}") == tree:
                return old
            person = {"NAME": author, "EMAIL": f"{author}@{EMAIL_DOMAIN}", "DATE": f"@{when} +0000"}
            env = {
                f"GIT_{role}_{key}": v
                for role in ("AUTHOR", "COMMITTER")
                for key, v in person.items()
            }
            parents = ["-p", old] if old is not None else []
            new = self._git(repo, "commit-tree", tree, *parents, stdin=message.encode(), env=env)
            # Compare-and-swap: main must still be `old` (all zeros: must not exist yet).
            self._git(repo, "update-ref", REF, new, old or "0" * len(new))
            log.info("%s/%s: %s committed by %s", user, name, new[:12], author)
            return new

    def head(self, user: str, name: str) -> str | None:
        """The commit of ``main``; None if there is no such repository or no commit."""
        repo = self.path(user, name)
        return self._head(repo) if repo.is_dir() else None

    def read(self, user: str, name: str, commit: str | None = None) -> dict[str, bytes]:
        """The files of ``commit`` (a full or abbreviated id; default the head), path ->
        bytes; NotHosted if the repository or the commit is not there."""
        repo = self._existing(user, name)
        if commit is None:
            found = self._head(repo)
            if found is None:
                raise NotHosted(user, name, f"on {BRANCH}")
        else:
            if not isinstance(commit, str) or COMMIT.fullmatch(commit) is None:
                raise HostedError(f"commit {commit!r}", "give 4 to 64 hexadecimal digits")
            found = self._resolve(repo, f"{commit}^{{commit}}")
            if found is None:
                raise NotHosted(user, name, commit)
        listing = self._run(repo, "ls-tree", "-r", "-z", "--full-tree", found).stdout
        blobs: list[tuple[str, str]] = []
        for entry in listing.split(b"\0"):
            if not entry:
                continue
            meta, _, path = entry.partition(b"\t")
            _mode, kind, oid = meta.decode().split(" ")
            if kind == "blob":
                blobs.append((path.decode("utf-8", "surrogateescape"), oid))
        return dict(
            zip([p for p, _ in blobs], self._blobs(repo, [o for _, o in blobs]), strict=True)
        )

    def names(self, user: str) -> list[str]:
        """The names of ``user``'s repositories, sorted."""
        check_user(user)
        folder = self.root / user
        if not folder.is_dir():
            return []
        found = []
        for entry in folder.iterdir():
            name = entry.name.removesuffix(".git")
            if entry.name.endswith(".git") and NAME.fullmatch(name) and entry.is_dir():
                found.append(name)
        return sorted(found)

    def users(self) -> list[str]:
        """The users who have a folder of repositories, sorted."""
        if not self.root.is_dir():
            return []
        return sorted(
            entry.name
            for entry in self.root.iterdir()
            if entry.is_dir() and NAME.fullmatch(entry.name) is not None
        )

    def copy_all(self, dest: Path) -> list[str]:
        """Copy every repository to ``dest/USER/NAME.git`` (``labd backup``), each while
        its lock is held, so no commit is copied half made; ``USER/NAME`` of each."""
        copied = []
        for user in self.users():
            for name in self.names(user):
                target = dest / user / f"{name}.git"
                target.parent.mkdir(parents=True, exist_ok=True)
                with self._locked(user, name):
                    shutil.copytree(self.path(user, name), target, symlinks=True)
                copied.append(f"{user}/{name}")
        return copied

    # -- git ---------------------------------------------------------------------------

    def _existing(self, user: str, name: str) -> Path:
        repo = self.path(user, name)
        if not repo.is_dir():
            raise NotHosted(user, name)
        return repo

    @contextlib.contextmanager
    def _locked(self, user: str, name: str) -> Iterator[None]:
        """Hold the repository's lock (a file beside it whose name no repository can
        have: it starts with a dot) while it is written."""
        folder = self.root / user
        folder.mkdir(parents=True, exist_ok=True)
        fd = os.open(folder / f".{name}.lock", os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX)
            yield
        finally:
            os.close(fd)  # releases the lock

    def _create(self, repo: Path) -> None:
        """Make the bare repository in a temporary folder, then move it into place, so a
        reader never finds one half made."""
        repo.parent.mkdir(parents=True, exist_ok=True)
        temporary = Path(tempfile.mkdtemp(prefix=".new-", dir=repo.parent))
        try:
            self._git(
                None, "init", "--quiet", "--bare", f"--initial-branch={BRANCH}", str(temporary)
            )
            self._git(temporary, "config", "http.receivepack", "false")  # never pushed to
            temporary.rename(repo)
        except BaseException:
            shutil.rmtree(temporary, ignore_errors=True)
            raise

    def _head(self, repo: Path) -> str | None:
        return self._resolve(repo, f"{REF}^{{commit}}")

    def _resolve(self, repo: Path, revision: str) -> str | None:
        done = self._run(repo, "rev-parse", "--verify", "--quiet", revision, ok=(0, 1))
        return done.stdout.decode().strip() if done.returncode == 0 else None

    def _tree(self, repo: Path, files: Mapping[str, bytes], paths: list[str]) -> str:
        """Write ``files`` as blobs and their tree (through a temporary index); its id."""
        with tempfile.TemporaryDirectory(prefix="labd-hosted-") as scratch:
            where = Path(scratch)
            for i, path in enumerate(paths):
                (where / str(i)).write_bytes(files[path])
            # Temporary names are digits, never quoted; --no-filters: the bytes as given.
            names = "".join(f"{where / str(i)}\n" for i in range(len(paths))).encode()
            hashed = self._git(
                repo, "hash-object", "-w", "--no-filters", "--stdin-paths", stdin=names
            )
            oids = hashed.split()
            entries = b"".join(
                f"{MODE} blob {oid}\t".encode() + path.encode("utf-8", "surrogateescape") + b"\0"
                for path, oid in zip(paths, oids, strict=True)
            )
            index = {"GIT_INDEX_FILE": str(where / "index")}
            self._git(repo, "update-index", "-z", "--add", "--index-info", stdin=entries, env=index)
            return self._git(repo, "write-tree", env=index)

    def _blobs(self, repo: Path, oids: list[str]) -> list[bytes]:
        """The bytes of each blob, read by one ``cat-file --batch``."""
        if not oids:
            return []
        out = self._run(repo, "cat-file", "--batch", stdin="".join(f"{o}\n" for o in oids).encode())
        data, at, found = out.stdout, 0, []
        for _ in oids:
            end = data.index(b"\n", at)
            size = int(data[at:end].split(b" ")[2])
            found.append(data[end + 1 : end + 1 + size])
            at = end + 1 + size + 1  # the blob, then a newline
        return found

    def _git(
        self,
        repo: Path | None,
        *args: str,
        stdin: bytes | None = None,
        env: Mapping[str, str] | None = None,
    ) -> str:
        """Run git on ``repo`` and return its output, stripped."""
        return self._run(repo, *args, stdin=stdin, env=env).stdout.decode().strip()

    def _run(
        self,
        repo: Path | None,
        *args: str,
        stdin: bytes | None = None,
        env: Mapping[str, str] | None = None,
        ok: tuple[int, ...] = (0,),
    ) -> subprocess.CompletedProcess[bytes]:
        """The one place git runs: on ``repo`` (its git directory), in the clean
        environment; an exit status not in ``ok`` is a GitFailed with git's last line."""
        command = ["git", *(("--git-dir", str(repo)) if repo is not None else ()), *args]
        where = str(repo) if repo is not None else str(self.root)
        try:
            done = subprocess.run(  # noqa: S603 - git, with arguments of our own making
                command,
                input=stdin if stdin is not None else b"",
                capture_output=True,
                env=git_environment(env),
                timeout=GIT_TIMEOUT,
                check=False,
            )
        except FileNotFoundError as err:
            raise GitFailed(args[0], where, "git is not installed") from err
        except subprocess.TimeoutExpired as err:
            raise GitFailed(args[0], where, f"took longer than {GIT_TIMEOUT:g} s") from err
        if done.returncode not in ok:
            lines = done.stderr.decode(errors="replace").strip().splitlines()
            raise GitFailed(
                args[0], where, lines[-1] if lines else f"exit status {done.returncode}"
            )
        return done
