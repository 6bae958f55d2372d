"""A bubblewrap job's own cgroup (v1): memory, processes and CPU, and the OOM count.

Docker makes a cgroup per container; bubblewrap does not, so the bwrap backend makes
one per job under the lab's own cgroup in each v1 hierarchy it may write to:

- ``memory``: ``memory.limit_in_bytes`` and, with swap accounting, the same
  ``memory.memsw.limit_in_bytes`` (no swapping past the limit); ``memory.oom_control``
  counts the OOM kills, which is how ``Exit.out_of_memory`` is known;
- ``pids``: ``pids.max`` (processes and threads at once);
- ``cpu``: a CFS quota of ``cpus`` CPUs, as Docker's ``nano_cpus``.

Where the memory hierarchy is missing or read-only (cgroup v2, an unprivileged lab),
``JobCgroup.create`` returns None and the backend falls back to rlimits.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import signal
import time
from pathlib import Path

from .api import Limits

log = logging.getLogger(__name__)

CONTROLLERS = ("memory", "pids", "cpu")
CFS_PERIOD_US = 100_000


def own_cgroups() -> dict[str, Path]:
    """For each v1 controller of ours: the folder of this process's cgroup in it."""
    mounts: dict[str, tuple[Path, str]] = {}
    for line in Path("/proc/self/mountinfo").read_text().splitlines():
        fields = line.split()
        sep = fields.index("-")
        fstype, options = fields[sep + 1], fields[sep + 3].split(",")
        if fstype != "cgroup":
            continue
        for controller in CONTROLLERS:
            if controller in options:
                mounts[controller] = (Path(fields[4]), fields[3])
    found: dict[str, Path] = {}
    for line in Path("/proc/self/cgroup").read_text().splitlines():
        _, names, path = line.split(":", 2)
        for controller in names.split(","):
            if controller in mounts:
                mountpoint, root = mounts[controller]
                relative = os.path.relpath(path, root) if path.startswith(root) else path
                folder = (mountpoint / relative.lstrip("/")).resolve()
                if folder.is_dir():
                    found[controller] = folder
    return found


class JobCgroup:
    """The cgroup folders of one job, one per controller we could write to."""

    def __init__(self, folders: dict[str, Path]) -> None:
        self.folders = folders

    @classmethod
    def create(cls, name: str, limits: Limits) -> JobCgroup | None:
        """Make the job's cgroups with ``limits``; None without a writable memory one."""
        folders: dict[str, Path] = {}
        for controller, parent in own_cgroups().items():
            folder = parent / name
            try:
                folder.mkdir()
            except FileExistsError:
                folders[controller] = folder  # a leftover of ours; reused, then removed
            except OSError as err:
                log.debug("no %s cgroup for jobs: %s", controller, err)
            else:
                folders[controller] = folder
        group = cls(folders)
        if "memory" not in folders:
            group.remove()
            return None
        try:
            group._write("memory", "memory.limit_in_bytes", limits.memory)
            with contextlib.suppress(FileNotFoundError, PermissionError):
                group._write("memory", "memory.memsw.limit_in_bytes", limits.memory)
            if "pids" in folders:
                group._write("pids", "pids.max", limits.processes)
            if "cpu" in folders:
                group._write("cpu", "cpu.cfs_period_us", CFS_PERIOD_US)
                group._write("cpu", "cpu.cfs_quota_us", max(1000, int(limits.cpus * CFS_PERIOD_US)))
        except OSError:
            group.remove()
            raise
        return group

    @property
    def limits_processes(self) -> bool:
        return "pids" in self.folders

    def add(self, pid: int, patience: float = 2.0) -> None:
        """Move ``pid`` (and so what it starts from now on) into the job's cgroups.

        A process forked a moment ago may not have been woken for the first time yet
        (the kernel's TASK_NEW state), and the cpu controller refuses to move it with
        EINVAL until it has: that is retried for up to ``patience`` seconds. Should the
        cpu controller still refuse, the job runs without its CPU share (its CPU time is
        still limited by RLIMIT_CPU) and the lab's log says so; the memory and process
        cgroups are the limits a job cannot run without, so their refusal is an error.
        """
        deadline = time.monotonic() + patience
        for controller in list(self.folders):
            try:
                self._join(controller, pid, deadline)
            except OSError as err:
                folder = self.folders[controller]
                if controller == "cpu":
                    log.warning(
                        "process %d could not join its cpu cgroup %s (%s): it runs without"
                        " its CPU share",
                        pid, folder, err,
                    )  # fmt: skip
                    with contextlib.suppress(OSError):
                        folder.rmdir()
                    del self.folders[controller]
                    continue
                raise OSError(
                    err.errno, f"process {pid} could not join its {controller} cgroup {folder}"
                ) from err

    def _join(self, controller: str, pid: int, deadline: float) -> None:
        delay = 0.001
        while True:
            try:
                self._write(controller, "cgroup.procs", pid)
                return
            except OSError as err:
                if err.errno != errno.EINVAL or time.monotonic() > deadline:
                    raise
            time.sleep(delay)
            delay = min(delay * 2, 0.05)

    def oom_kills(self) -> int:
        """How many processes the kernel killed in this cgroup for lack of memory."""
        try:
            text = (self.folders["memory"] / "memory.oom_control").read_text()
        except (KeyError, OSError):
            return 0
        for line in text.splitlines():
            key, _, value = line.partition(" ")
            if key == "oom_kill":
                return int(value)
        return 0

    def pids(self) -> set[int]:
        found: set[int] = set()
        for folder in self.folders.values():
            with contextlib.suppress(OSError):
                found.update(int(p) for p in (folder / "cgroup.procs").read_text().split())
        return found

    def remove(self, timeout: float = 5.0) -> None:
        """Kill what is left inside and remove the folders."""
        deadline = time.monotonic() + timeout
        for controller, folder in list(self.folders.items()):
            while True:
                for pid in self.pids():
                    with contextlib.suppress(ProcessLookupError):
                        os.kill(pid, signal.SIGKILL)
                try:
                    folder.rmdir()
                    break
                except FileNotFoundError:
                    break
                except OSError as err:  # EBUSY while killed processes are being reaped
                    if time.monotonic() > deadline:
                        log.warning(
                            "could not remove the %s cgroup %s: %s", controller, folder, err
                        )
                        break
                    time.sleep(0.01)
            del self.folders[controller]

    def _write(self, controller: str, name: str, value: int) -> None:
        (self.folders[controller] / name).write_text(f"{value}\n")
