"""Moving a job's process into its cgroups, as the kernel answers a process just forked."""

from __future__ import annotations

import errno
from pathlib import Path

import pytest

from sandbox.cgroups import JobCgroup


class Refusing(JobCgroup):
    """Cgroup folders whose ``cgroup.procs`` refuse a pid ``times`` times with ``code``
    (in the ``only`` controller, or in all)."""

    def __init__(
        self, folders: dict[str, Path], times: int, code: int, only: str | None = None
    ) -> None:
        super().__init__(folders)
        self.times = times
        self.code = code
        self.only = only
        self.written: list[tuple[str, str, int]] = []

    def _write(self, controller: str, name: str, value: int) -> None:
        if self.times > 0 and self.only in (None, controller):
            self.times -= 1
            raise OSError(self.code, "refused")
        self.written.append((controller, name, value))


def folders(tmp_path: Path) -> dict[str, Path]:
    return {c: tmp_path / c for c in ("memory", "pids", "cpu")}


def test_a_process_not_yet_woken_is_moved_once_it_is(tmp_path):
    """EINVAL (the process is still new to the scheduler) is retried until it goes."""
    group = Refusing(folders(tmp_path), times=3, code=errno.EINVAL)
    group.add(4242)
    assert group.written == [(c, "cgroup.procs", 4242) for c in ("memory", "pids", "cpu")]


def test_a_process_the_memory_cgroup_refuses_is_an_error(tmp_path):
    """Past its patience, a refusal of the memory cgroup is an error naming it."""
    group = Refusing(folders(tmp_path), times=10**6, code=errno.EINVAL, only="memory")
    with pytest.raises(OSError) as raised:
        group.add(4242, patience=0.05)
    assert raised.value.errno == errno.EINVAL
    assert "process 4242 could not join its memory cgroup" in str(raised.value)


def test_a_process_the_cpu_cgroup_keeps_refusing_runs_without_its_share(tmp_path, caplog):
    """The cpu cgroup's lasting refusal drops that cgroup (logged); the others hold."""
    group = Refusing(folders(tmp_path), times=10**6, code=errno.EINVAL, only="cpu")
    group.add(4242, patience=0.05)
    assert group.written == [(c, "cgroup.procs", 4242) for c in ("memory", "pids")]
    assert set(group.folders) == {"memory", "pids"}
    assert "could not join its cpu cgroup" in caplog.text


def test_other_refusals_are_not_retried(tmp_path):
    """A process that is gone (ESRCH) is an error at once."""
    group = Refusing(folders(tmp_path), times=1, code=errno.ESRCH)
    with pytest.raises(OSError) as raised:
        group.add(4242)
    assert raised.value.errno == errno.ESRCH and group.written == []
