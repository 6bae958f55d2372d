"""Repositories that try to make the lab read the host's files through their links.

Each is a real git repository made in ``tmp_path``, taken as a local folder and as a
``file://`` URL (workers take code from mirrors), run through ``run_trial`` and through
a worker of a real queue. Each must break at once, with a reason that names the file
in the repository and shows nothing of the host's file, and the next trial must run.
A link the controller itself uses inside its sandbox keeps working.
"""

from __future__ import annotations

import asyncio
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import pytest

from labd.trial import LabHost
from repository.blobs import BlobStore
from repository.index import Derived, Index
from repository.trial import Claim, Filing, Order, Outcome, Trial
from sandbox.api import Backend, Limits
from scheduler.fetch import FetchPolicy
from scheduler.queue import Queue
from scheduler.runner import RunOptions, TrialResult, run_trial
from scheduler.worker import Worker, WorkerConfig
from tests.helpers.githttp import GitRepo, Link

pytestmark = pytest.mark.integration

LAB_TOML = '[controller]\ncommand = ["python", "controller.py"]\ntask = "icreate-maze"\n'
WITH_REQUIREMENTS = LAB_TOML + 'requirements = "{}"\n'
HOST_FILES = ("/etc/passwd", "/etc/shadow")
OPTIONS = RunOptions(limits=Limits(wall=60.0), first_step=20.0, stall=10.0)
QUICKLY = 15.0  # seconds a hostile trial may take, fetching included

# The controller reads a file through an absolute link of its own, which means
# something only inside its sandbox (/code is where its code is), steps once, exits 0.
USES_ITS_OWN_LINK = {
    "lab.toml": LAB_TOML,
    "settings": Link("/code/real-settings"),
    "real-settings/speed.txt": "0.25\n",
    "controller.py": (
        "from pathlib import Path\n"
        "from controllers.client import Lab\n"
        "print('speed', Path('settings/speed.txt').read_text().strip())\n"
        "with Lab.connect() as lab:\n"
        "    lab.step()\n"
    ),
}


@dataclass(frozen=True)
class Hostile:
    files: Mapping[str, str | Link]
    reason: str  # how the reason starts


HOSTILE = {
    "lab-toml-to-passwd": Hostile(
        {"lab.toml": Link("/etc/passwd"), "controller.py": "print(1)\n"},
        "lab.toml: it is a symbolic link (to somewhere outside the repository)",
    ),
    "requirements-to-shadow": Hostile(
        {
            "lab.toml": WITH_REQUIREMENTS.format("requirements.txt"),
            "requirements.txt": Link("/etc/shadow"),
            "controller.py": "print(1)\n",
        },
        "requirements.txt: it is a symbolic link (to somewhere outside the repository)",
    ),
    "lab-toml-escapes-relatively": Hostile(
        {"lab.toml": Link("../../../../../../../../../etc/passwd"), "controller.py": ""},
        "lab.toml: it is a symbolic link (to somewhere outside the repository)",
    ),
    "folder-link-on-the-way": Hostile(
        {
            "lab.toml": WITH_REQUIREMENTS.format("deps/shadow"),
            "deps": Link("/etc"),
            "controller.py": "print(1)\n",
        },
        "deps/shadow: deps is a symbolic link (to somewhere outside the repository)",
    ),
}


def host_lines() -> list[str]:
    """The lines of the host's files the repositories point at (the lab runs as root)."""
    lines = []
    for name in HOST_FILES:
        lines += [line for line in Path(name).read_text().splitlines() if len(line) > 3]
    assert lines
    return lines


def assert_refused(outcome: Outcome | None, reason: str, hostile: Hostile) -> None:
    assert outcome is Outcome.ERROR, reason
    assert reason.startswith(hostile.reason), reason
    assert "never through a link" in reason
    for line in host_lines():
        assert line not in reason


def make_repo(tmp_path: Path, name: str, files: Mapping[str, str | Link]) -> GitRepo:
    repo = GitRepo.create(tmp_path / name, files)
    repo.path.chmod(0o755)
    return repo


def source_of(repo: GitRepo, way: str) -> str:
    return repo.url if way == "url" else str(repo.path)


def run(backend: Backend, cache: Path, host: LabHost, tmp_path: Path, source: str) -> TrialResult:
    out = tmp_path / f"run-{len(list(tmp_path.glob('run-*')))}"
    order = Order(repository=source)
    return asyncio.run(
        run_trial(order, backend=backend, host=host, out=out, cache=cache, options=OPTIONS)
    )


def assert_ran_with_its_own_link(result: TrialResult) -> None:
    """The controller read through its own link inside the sandbox, and stepped."""
    assert "the controller exited with 0 at tick 1" in result.reason, result.reason
    assert result.outcome is Outcome.FAIL  # one step, then it stops: not the goal
    assert result.data_digest and result.mcap is not None
    assert (result.folder / "controller.stdout.log").read_text() == "speed 0.25\n"


@pytest.mark.parametrize("way", ["folder", "url"])
@pytest.mark.parametrize("name", sorted(HOSTILE))
def test_a_hostile_repository_breaks_at_once_saying_why(
    backend: Backend, cache: Path, host: LabHost, tmp_path: Path, name: str, way: str
) -> None:
    """Each hostile repository ends quickly as a broken trial naming its file, with
    nothing of the host's file in the reason; the next trial runs."""
    hostile = HOSTILE[name]
    repo = make_repo(tmp_path, name, hostile.files)
    result = run(backend, cache, host, tmp_path, source_of(repo, way))
    assert_refused(result.outcome, result.reason, hostile)
    assert result.wall_seconds < QUICKLY and result.mcap is None
    good = make_repo(tmp_path, "good", USES_ITS_OWN_LINK)
    assert_ran_with_its_own_link(run(backend, cache, host, tmp_path, source_of(good, way)))


@pytest.mark.parametrize("way", ["folder", "url"])
def test_a_controller_uses_its_own_absolute_link(
    backend: Backend, cache: Path, host: LabHost, tmp_path: Path, way: str
) -> None:
    """A link meaningful only inside the sandbox is checked out as it is and works there."""
    repo = make_repo(tmp_path, "own-link", USES_ITS_OWN_LINK)
    result = run(backend, cache, host, tmp_path, source_of(repo, way))
    assert_ran_with_its_own_link(result)
    assert result.manifest.commit == repo.rev()


class Counting:
    """The queue, as the worker sees it, telling when ``expected`` trials are filed."""

    def __init__(self, queue: Queue, expected: int) -> None:
        self.queue = queue
        self.expected = expected
        self.filed: list[int] = []
        self.all_filed = asyncio.Event()
        self.loop = asyncio.get_running_loop()

    def claim(self, worker: str) -> Claim | None:
        return self.queue.claim(worker)

    def heartbeat(self, trial_id: int, worker: str) -> bool:
        return self.queue.heartbeat(trial_id, worker)

    def finish(self, trial_id: int, worker: str, filing: Filing) -> bool:
        done = self.queue.finish(trial_id, worker, filing)
        self.filed.append(trial_id)
        if len(self.filed) >= self.expected:
            self.loop.call_soon_threadsafe(self.all_filed.set)
        return done

    def trial(self, trial_id: int) -> Trial:
        return self.queue.trial(trial_id)

    def derive(self, trial_id: int, worker: str, item: Derived) -> bool:
        return self.queue.derive(trial_id, worker, item)


async def test_one_worker_files_every_hostile_trial_and_runs_the_next(
    backend: Backend, cache: Path, host: LabHost, tmp_path: Path
) -> None:
    """The lab's only worker files each hostile trial as broken, in seconds, and then
    runs a good one: nothing leaves it stuck."""
    index = Index.open(f"sqlite:///{tmp_path / 'index.sqlite'}")
    index.add_user("mallory", max_running=1)
    queue = Queue(index)
    mallory = index.user("mallory")
    submitted = {}
    for name, files in [*((n, h.files) for n, h in sorted(HOSTILE.items())), ("good", None)]:
        repo = make_repo(tmp_path, name, files or USES_ITS_OWN_LINK)
        order = Order(
            repository=repo.url, ref="main", commit=repo.rev(), task="icreate-maze", public=True
        )
        submitted[name] = queue.submit(mallory, order)
    jobs = Counting(queue, expected=len(submitted))
    config = WorkerConfig(
        name="only",
        work=tmp_path / "work",
        cache=cache,
        poll=0.05,
        options=RunOptions(
            limits=OPTIONS.limits,
            first_step=OPTIONS.first_step,
            stall=OPTIONS.stall,
            fetch=FetchPolicy(schemes=frozenset({"file"})),  # the repositories are local
        ),
    )
    worker = Worker(jobs, BlobStore(str(tmp_path / "blobs")), backend, host, config)
    stop = asyncio.Event()
    working = asyncio.create_task(worker.run(stop))
    filed = asyncio.create_task(jobs.all_filed.wait())
    try:
        done, _ = await asyncio.wait(
            {working, filed}, timeout=QUICKLY * len(submitted), return_when="FIRST_COMPLETED"
        )
        if working in done:
            working.result()  # the worker died: its exception is the failure
        assert filed in done, f"only {jobs.filed} of {submitted} were filed"
    finally:
        stop.set()
        filed.cancel()
        await working
    for name, hostile in HOSTILE.items():
        row = index.trial(submitted[name])
        assert_refused(row.outcome, row.reason, hostile)
    good = index.trial(submitted["good"])
    assert "the controller exited with 0 at tick 1" in good.reason, good.reason
    assert good.data_digest and good.stdout
    index.close()
