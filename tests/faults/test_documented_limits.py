"""Every limit the docs promise is the default the code runs with.

Each row names a sentence of docs/ (whitespace aside) and the value in the code it
states. The fault suite and the tests it cites hit each limit (docs/faults.md has the
table); this keeps the figures they hit and the figures users read the same, so a
change to either fails here until both say it.
"""

from __future__ import annotations

import argparse
import re
from collections.abc import Callable
from pathlib import Path

import pytest

from labd import logs
from labd.api import builds
from labd.api.app import TrialQuery
from labd.api.edges import BODY_LIMIT, limit
from labd.api.git import GitLimits
from labd.api.workers import MAX_BLOB
from labd.commands import serve
from labd.config import BridgeConfig, DriveLimits, HttpConfig
from labd.service import ServiceConfig
from labd.sim import registry
from repository import stats
from repository.index import UserLimits
from repository.mcapfile import MAX_PART
from repository.trial import MAX_ID
from sandbox.api import Limits
from sandbox.jobs import KEEP
from scheduler.fetch import FetchPolicy
from scheduler.queue import QueueConfig
from scheduler.runner import RunOptions
from scheduler.worker import WorkerConfig

DOCS = Path(__file__).resolve().parents[2] / "docs"
MiB, KiB = 1024 * 1024, 1024
BRIDGE, SANDBOX, RUN, QUEUE = BridgeConfig(), Limits(), RunOptions(), QueueConfig()
DRIVES = DriveLimits()
HTTP = HttpConfig()
WORKER = WorkerConfig(name="", work=Path(), cache=Path())
SERVICE = ServiceConfig()


def limit_of_trial_pages() -> int:
    query = TrialQuery.__dataclass_fields__["limit"].type
    le = re.search(r"le=(\d+)", str(query))
    assert le is not None, query
    return int(le.group(1))


def serve_heartbeat(lease: float) -> float:
    args = serve_args("--lease", str(lease))
    config = serve.service_config(args)
    assert config is not None
    return config.heartbeat


def serve_fetch(*argv: str) -> FetchPolicy:
    """The fetch policy of ``labd serve`` with these options."""
    config = serve.service_config(serve_args(*argv))
    assert config is not None
    return config.fetch


def serve_args(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    commands = parser.add_subparsers(dest="command")
    serve.add_parser(commands)
    return parser.parse_args(["serve", *argv])


# (doc, what it says, the code's value, the value the sentence states)
ROWS: list[tuple[str, str, Callable[[], object], object]] = [
    # docs/trials.md: the sandbox and a trial's stages
    ("trials.md", "| wall time | 600 s", lambda: SANDBOX.wall, 600),
    ("trials.md", "| memory | 1 GiB |", lambda: SANDBOX.memory, 1024 * MiB),
    ("trials.md", "| processes and threads | 64 |", lambda: SANDBOX.processes, 64),
    ("trials.md", "3,600 s in all", lambda: SANDBOX.cpu_seconds, 3600),
    ("trials.md", "| open files | 256 |", lambda: SANDBOX.open_files, 256),
    ("trials.md", "| output (stdout and stderr) | 8 MiB |", lambda: SANDBOX.output, 8 * MiB),
    ("trials.md", "the first and last 64 KiB of each are kept", lambda: KEEP, 64 * KiB),
    ("trials.md", "| scratch | 256 MiB |", lambda: SANDBOX.scratch, 256 * MiB),
    ("trials.md", "no `/lab/step` for 10 s", lambda: RUN.stall, 10),
    ("trials.md", "or 60 s before the first one", lambda: RUN.first_step, 60),
    ("trials.md", "the controller gets 2 seconds to exit by itself", lambda: RUN.grace, 2),
    ("trials.md", "installing requirements: 15 minutes", lambda: RUN.prepare, 15 * 60),
    ("trials.md", "filing it (5 minutes)", lambda: WORKER.filing, 5 * 60),
    # docs/live.md: what a drive of a live robot files
    ("live.md", "`session`, `interface` and `user` are at most 64 characters each",
     lambda: DRIVES.max_text, 64),
    ("live.md", "| a client's drive shorter than N ticks files nothing | 20 (1 s at 20 Hz) |",
     lambda: DRIVES.min_ticks, 20),
    ("live.md", "files at most N drives a minute, over all the lab's robots | 10 |",
     lambda: DRIVES.filings_per_minute, 10),
    ("live.md", "the driver's events past it are not recorded | 64 | `--max-drive-mb` |",
     lambda: (DRIVES.max_record, serve_args().max_drive_mb), (64 * MiB, 64)),
    # docs/protocol.md: the bridge
    ("protocol.md", "limited per stream (its `queue_length`, default 100)",
     lambda: BRIDGE.default_queue_length, 100),
    ("protocol.md", "and in total (32 MiB)", lambda: BRIDGE.max_queue_bytes, 32 * MiB),
    ("protocol.md", "the server pings every 20 s", lambda: BRIDGE.ping_interval, 20),
    ("protocol.md", "does not answer within 20 s", lambda: BRIDGE.ping_timeout, 20),
    ("protocol.md", "a frame over 16 MiB is refused", lambda: BRIDGE.max_message_size, 16 * MiB),
    ("protocol.md", "a frame over 64 MiB closes the connection (1009)",
     lambda: BRIDGE.max_frame_size, 64 * MiB),
    ("protocol.md", "at most 1,000 subscriptions", lambda: BRIDGE.max_subscriptions, 1000),
    ("protocol.md", "1,000 advertised topics", lambda: BRIDGE.max_publishers, 1000),
    ("protocol.md", "200 provided services and 200 provided actions",
     lambda: BRIDGE.max_services, 200),
    ("protocol.md", "1,000 calls waiting for an answer and 1,000 goals in progress",
     lambda: BRIDGE.max_pending, 1000),
    ("protocol.md", "at most 200 connections per server", lambda: BRIDGE.max_connections, 200),
    ("protocol.md", "At most 16 messages may be in parts at once per client",
     lambda: BRIDGE.max_fragmented, 16),
    ("protocol.md", "parts that stop coming are forgotten after 30 s",
     lambda: BRIDGE.fragment_timeout, 30),
    ("protocol.md", "`timeout` defaults to 5 s", lambda: BRIDGE.service_timeout, 5),
    ("protocol.md", "(20 lines a second, bursts of 50)",
     lambda: (BRIDGE.log_rate, BRIDGE.log_burst), (20, 50)),
    ("protocol.md", "no key within 10 s closes the connection", lambda: BRIDGE.auth_timeout, 10),
    ("protocol.md", "A client has 10 s from connecting to send its WebSocket handshake",
     lambda: BRIDGE.handshake_timeout, 10),
    ("protocol.md", "holds at most 32 of those connections, and at most 32 more still in",
     lambda: BRIDGE.max_connections_per_address, 32),
    # docs/service.md: fetching, the queue, the archive
    ("service.md", "| `--max-repo-mb N` | 512 |", lambda: FetchPolicy().max_bytes, 512 * MiB),
    ("service.md", "| `--fetch-timeout S` | 300 |", lambda: FetchPolicy().timeout, 300),
    ("service.md", "| `--max-checkout-mb N` | 512 |",
     lambda: (FetchPolicy().max_checkout_bytes, serve_fetch().max_checkout_bytes),
     (512 * MiB, 512 * MiB)),
    ("service.md", "refuses one of more than 100,000 files the same way",
     lambda: FetchPolicy().max_checkout_files, 100_000),
    ("service.md", "| `--resolve-timeout S` | 60 |",
     lambda: (FetchPolicy().resolve_timeout, serve_fetch().resolve_timeout), (60, 60)),
    ("service.md", "| `--allow-local-repos` | off |",
     lambda: ("file" in FetchPolicy().schemes, "file" in serve_fetch().schemes), (False, False)),
    ("service.md", "| `--allow-private-hosts` | off |",
     lambda: (FetchPolicy().private_hosts, serve_fetch().private_hosts), (False, False)),
    ("service.md", "8 at once, 64 more waiting their turn",
     lambda: (SERVICE.submit_threads, SERVICE.submit_waiting), (8, 64)),
    ("service.md", "(`--lease`, 30 s)", lambda: QUEUE.lease, 30),
    ("service.md", "(`--lease`, 30 s)", lambda: serve_args().lease, 30),
    ("service.md", "renew by heartbeat (every third of the lease)",
     lambda: (serve_heartbeat(30), serve_heartbeat(3)), (10, 1)),
    ("service.md", "after three lost leases it ends as an `error`",
     lambda: QUEUE.max_attempts, 3),
    ("service.md", "`max_running` trials running (default 2)",
     lambda: UserLimits().max_running, 2),
    ("service.md", "`max_daily` (default 500)", lambda: UserLimits().max_daily, 500),
    ("service.md", "`limit` up to 500", limit_of_trial_pages, 500),
    ("service.md", "Records are read within one limit: **256 MiB**, the most one part of",
     lambda: MAX_PART, 256 * MiB),
    ("service.md", "Every JSON body and form is held to 1 MiB", lambda: BODY_LIMIT, MiB),
    ("service.md", "and a worker's blob upload to 4 GiB", lambda: MAX_BLOB, 4096 * MiB),
    ("service.md", "whole numbers from 1 to 2,147,483,647", lambda: MAX_ID, 2**31 - 1),
    # docs/service.md: the playground's repositories over git's HTTP
    ("service.md", "A fetch's request body is held to 16 MiB (413 above it)",
     lambda: limit("POST", "/git/alice/robot.git/git-upload-pack"), 16 * MiB),
    ("service.md", "the lab runs at most 8 of them at once", lambda: GitLimits().backends, 8),
    ("service.md", "kills one that runs longer than 300 s", lambda: GitLimits().timeout, 300),
    # docs/service.md: many clients, and slow ones
    ("service.md", "| a request's line and headers | within 10 s |",
     lambda: (HTTP.header_timeout, serve_args().header_timeout), (10, 10)),
    ("service.md", "| HTTP connections per address | 256 connections at once |",
     lambda: HTTP.max_connections_per_address, 256),
    ("service.md", "| an idle kept connection | 5 s |", lambda: HTTP.keep_alive, 5),
    ("service.md", "| bridge connections per address | 32 |",
     lambda: serve_args().max_connections_per_address, 32),
    ("service.md", "written five times at once, then twice a second",
     lambda: (logs.BURST, logs.RATE), (5, 2)),
    ("service.md", "and one export at a time, with at most 8 more waiting their turn",
     lambda: (builds.BUILDS, builds.WAITING), (1, 8)),
    ("service.md", "at most 1 GiB of them is kept", lambda: builds.KEEP_BYTES, 1024 * MiB),
    # docs/evaluations.md
    ("evaluations.md", "| `icreate-maze` | `dev` | 1 | 20 | 0 to 19, public |",
     lambda: suite_of("icreate-maze", "dev"), (1, 20, tuple(range(20)), False)),
    ("evaluations.md", "| `icreate-maze` | `test` | 1 | 50 | held out |",
     lambda: suite_of("icreate-maze", "test"), (1, 50, (), True)),
    ("evaluations.md", "| `pr2-table` | `dev` | 1 | 20 | 0 to 19, public |",
     lambda: suite_of("pr2-table", "dev"), (1, 20, tuple(range(20)), False)),
    ("evaluations.md", "| `pr2-table` | `test` | 1 | 50 | held out |",
     lambda: suite_of("pr2-table", "test"), (1, 50, (), True)),
    ("evaluations.md", "(2,000 resamples from a generator seeded with the evaluation's id",
     lambda: stats.RESAMPLES, 2000),
    ("evaluations.md", "towards the submitter's daily limit (500 trials by default)",
     lambda: UserLimits().max_daily, 500),
]  # fmt: skip


def suite_of(task: str, name: str) -> tuple[int, int, tuple[int, ...], bool]:
    suite = registry.get(task).suite(name)
    assert suite is not None, f"{task} has no suite {name}"
    return suite.version, suite.episodes, suite.seeds, suite.held_out


@pytest.mark.parametrize(
    ("doc", "sentence", "value", "stated"), ROWS, ids=[f"{r[0]}: {r[1]}" for r in ROWS]
)
def test_the_docs_state_the_default(doc, sentence, value, stated):
    """The sentence is in the doc, and the code's default is the figure it states."""
    text = " ".join((DOCS / doc).read_text().split())
    assert " ".join(sentence.split()) in text, f"{doc} no longer says {sentence!r}"
    assert value() == stated
