"""Host paths a job's uid cannot reach, bound where it can, for bubblewrap alone.

bwrap opens every path it mounts (the runtime, the code, the python paths, the bridge's
socket) as the job's uid, so each folder on the way must let others search it (o+x). A
lab run as root whose data folder lies under a folder only its owner may enter (0700,
as home folders often are) gave ``bwrap: Can't find source path .../rootfs: Permission
denied``. Passing bwrap a descriptor (``--ro-bind-fd``) does not help: bwrap reads it
through ``/proc/self/fd`` after entering its user namespace, which makes the process
undumpable and that folder root's.

So, where some path is out of the uid's reach, bwrap starts in a mount namespace of its
own (``unshare --mount``), in which root bind-mounts each such path on an empty folder
(or file) under a fresh folder of ``/run/labd/views``, which every uid may traverse and
only root may write; then ``setpriv`` becomes the job's uid and bwrap mounts from there. The binds
live only in that namespace and end with the job; on the host there are only the empty
mount points, removed at the end. Nothing's permissions change.

Only a lab run as root needs this: otherwise bwrap runs as the lab's own uid, which
reaches whatever the lab does. Docker needs none of it (its engine mounts as root).
"""

from __future__ import annotations

import shlex
import shutil
import stat
import tempfile
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from .api import SandboxError

TOOLS = ("unshare", "mount", "setpriv", "sh")  # util-linux, and a shell to chain them
VIEWS = Path("/run/labd/views")  # root's, searchable by all: the jobs' mount points


def unreachable(path: Path, uid: int) -> Path | None:
    """The first folder on the way to ``path`` that ``uid`` may not search, if any."""
    for folder in reversed(path.parents):
        st = folder.stat()
        if st.st_uid == uid:
            ok = st.st_mode & stat.S_IXUSR
        elif st.st_gid == uid:
            ok = st.st_mode & stat.S_IXGRP
        else:
            ok = st.st_mode & stat.S_IXOTH
        if not ok:
            return folder
    return None


def refusal(path: Path, blocked: Path, uid: int, hint: str = "") -> SandboxError:
    """The one-line error for a path ``uid`` cannot reach, saying what to change."""
    return SandboxError(
        f"the sandbox's uid {uid} cannot reach {path}: {blocked} is not searchable by"
        f" others; chmod o+x {blocked}, or keep the lab's data folder elsewhere{hint}"
    )


@dataclass
class Views:
    """Where bwrap finds each host path: itself, or its bind under ``folder``."""

    binds: list[tuple[Path, Path]] = field(default_factory=list)  # (host path, view)
    folder: Path | None = None  # the mount points' folder, when there are binds
    tools: dict[str, str] = field(default_factory=dict)

    @classmethod
    def make(cls, paths: Iterable[Path | None], uid: int) -> Views:
        """Views of those of ``paths`` that ``uid`` cannot reach (none: no binds).

        SandboxError, in one line saying what to change, when some path is out of
        reach and the tools to bind it are missing.
        """
        views = cls()
        wanted = sorted({p for p in paths if p is not None}, key=lambda p: len(p.parts))
        try:
            for path in wanted:
                if views._covers(path) or (blocked := unreachable(path, uid)) is None:
                    continue
                views._bind(path, blocked, uid)
        except BaseException:
            views.remove()
            raise
        return views

    def path(self, host: Path) -> str:
        """Where bwrap, inside the views' namespace, finds the host path ``host``."""
        for source, view in self.binds:
            if host == source or host.is_relative_to(source):
                return str(view / host.relative_to(source))
        return str(host)

    def command(self, argv: Sequence[str], uid: int) -> list[str]:
        """``argv`` run as ``uid`` in a mount namespace with the binds (run it as root)."""
        pairs = [str(p) for bind in self.binds for p in bind]
        tools = self.tools
        return [
            tools["unshare"],
            "--mount",
            "--propagation",
            "private",
            "--",
            tools["sh"],
            "-c",
            # Bind each (host path, view) pair given before "--", then run what follows.
            f'while [ "$1" != -- ]; do {shlex.quote(tools["mount"])} --bind "$1" "$2"'
            ' || exit 125; shift 2; done; shift; exec "$@"',
            "sh",
            *pairs,
            "--",
            tools["setpriv"],
            f"--reuid={uid}",
            f"--regid={uid}",
            "--clear-groups",
            "--",
            *argv,
        ]

    def remove(self) -> None:
        """Remove the mount points (the binds ended with the namespace)."""
        if self.folder is not None:
            shutil.rmtree(self.folder, ignore_errors=True)
            self.folder = None

    def _covers(self, path: Path) -> bool:
        return any(path == s or path.is_relative_to(s) for s, _ in self.binds)

    def _bind(self, path: Path, blocked: Path, uid: int) -> None:
        if not self.tools:
            found = {name: shutil.which(name) for name in TOOLS}
            missing = [name for name, where in found.items() if where is None]
            if missing:
                hint = f" (the lab would bind it, with {', '.join(missing)} on its PATH)"
                raise refusal(path, blocked, uid, hint)
            self.tools = {name: str(where) for name, where in found.items()}
        if self.folder is None:
            try:
                VIEWS.mkdir(parents=True, exist_ok=True)
                for folder in (VIEWS.parent, VIEWS):  # whatever the umask made them
                    folder.chmod(0o755)
                self.folder = Path(tempfile.mkdtemp(prefix="job-", dir=VIEWS))
                self.folder.chmod(0o755)
            except OSError as err:
                raise refusal(path, blocked, uid, f" (binding it needs {VIEWS}: {err})") from None
            if (outer := unreachable(self.folder, uid)) is not None:
                raise refusal(path, blocked, uid, f" (and {outer}, on the way to {VIEWS})")
        view = self.folder / str(len(self.binds))
        if path.is_dir():
            view.mkdir(mode=0o755)
        else:
            view.touch(mode=0o644)
        self.binds.append((path, view))
