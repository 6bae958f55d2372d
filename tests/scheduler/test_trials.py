"""Trials for real: labd run's runner with both sandboxes, the example controllers, attacks.

Every attack ends as an error with the reason, and the next trial is unaffected.
"""

from __future__ import annotations

import asyncio
import json
import shutil
import socket
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rosbags.highlevel import AnyReader

from labd.graph.graph import Side
from labd.recorder import data_digest, read_channels, read_messages
from labd.replay import replay
from repository.trial import Order, Outcome
from sandbox.api import Limits, MiB
from scheduler.fetch import FetchPolicy
from scheduler.runner import RunOptions, run_trial
from tests.helpers.githttp import GitRepo
from tests.helpers.sandboxes import BACKENDS, make_backend
from tests.sandbox.test_isolation import host_addresses

pytestmark = pytest.mark.integration
ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "controllers" / "examples"
ATTACKS = Path(__file__).resolve().parent / "attacks"


def run(backend, cache, host, tmp_path, source, **kwargs):
    options = kwargs.pop("options", RunOptions())
    order = Order(repository=str(source), **kwargs)
    out = tmp_path / f"run-{len(list(tmp_path.glob('run-*')))}"
    return asyncio.run(
        run_trial(order, backend=backend, host=host, out=out, cache=cache, options=options)
    )


@pytest.mark.parametrize("example", ["icreate-maze", "icreate-maze-js", "pr2-pick-place"])
def test_examples_succeed_and_reproduce(backend, cache, host, tmp_path, example):
    """Each example controller succeeds at its task, and a second run gives the same data."""
    first = run(backend, cache, host, tmp_path, EXAMPLES / example, seed=1)
    assert first.outcome is Outcome.SUCCESS, first.reason
    assert first.metrics["success"] is True
    second = run(backend, cache, host, tmp_path, EXAMPLES / example, seed=1)
    assert (second.data_digest, second.manifest_digest) == (
        first.data_digest,
        first.manifest_digest,
    )
    other_seed = run(backend, cache, host, tmp_path, EXAMPLES / example, seed=2)
    assert other_seed.data_digest != first.data_digest
    assert replay(first.mcap).verified  # its actions alone give its observations back


def test_both_backends_give_the_same_data(cache, host, tmp_path):
    """The same trial under bubblewrap and under Docker records the same data digest."""
    digests = set()
    for name in BACKENDS:
        backend = make_backend(name, cache)
        result = run(backend, cache, host, tmp_path, EXAMPLES / "icreate-maze", seed=4)
        assert result.outcome is Outcome.SUCCESS, result.reason
        digests.add(result.data_digest)
    assert len(digests) == 1


def test_the_record_opens_with_rosbags_and_the_mcap_decoder(backend, cache, host, tmp_path):
    """The MCAP holds every topic of the trial and opens with rosbags and with mcap_ros2."""
    result = run(backend, cache, host, tmp_path, EXAMPLES / "icreate-maze", seed=1)
    with result.mcap.open("rb") as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        topics = {channel.topic for _, channel, _, _ in reader.iter_decoded_messages()}
        stream.seek(0)
        attachments = {a.name for a in make_reader(stream).iter_attachments()}
    assert {
        "/odom",
        "/bumper",
        "/cmd_vel",
        "/ar_tags",
        "/clock",
        "/lab/episode",
        "/tf",
        "/goal",
    } <= topics
    assert {
        "manifest.json",
        "outcome.json",
        "lab.toml",
        "model.xml",
        "controller.stdout.log",
        "controller.stderr.log",
    } <= attachments
    with AnyReader([result.folder]) as bag:
        connections = [c for c in bag.connections if c.topic == "/odom"]
        odometry = [bag.deserialize(raw, c.msgtype) for c, _, raw in bag.messages(connections)]
    assert len(odometry) == result.metrics["ticks"] + 1
    manifest = json.loads((result.folder / "manifest.json").read_text())
    assert manifest["task"]["name"] == "icreate-maze" and manifest["runtime"]


def attack(name, tmp_path, target=None):
    folder = tmp_path / name
    folder.parent.mkdir(exist_ok=True)
    shutil.copytree(ATTACKS / name, folder)
    if target is not None:
        (folder / "target.json").write_text(json.dumps(target))
    folder.chmod(0o755)
    return folder


@pytest.fixture
def host_listener():
    """A TCP server on each of the host's addresses, loopback and every interface's.

    Listening is enough: the kernel completes a connection into the backlog unasked.
    (A thread blocked in accept() raised EINVAL when the socket closed, failing
    whichever test ran next.)
    """
    addresses = host_addresses()
    assert len(addresses) > 1, "only loopback here: the host's own address is not tried"
    servers = [socket.create_server((address, 0)) for address in addresses]
    yield [s.getsockname() for s in servers]
    for server in servers:
        server.close()


LIMITS = Limits(memory=256 * MiB, processes=32, output=2 * MiB, wall=60.0)


@pytest.mark.parametrize(
    ("name", "reasons"),
    [
        ("no-lab-toml", ["has no lab.toml"]),
        ("broken-lab-toml", ["not valid TOML"]),
        ("exits-at-once", ["the controller exited with 2 at tick 0"]),
        ("exits-zero-at-once", ["exited with 0 before its first /lab/step"]),
        (
            "raises",
            ["exited with 1 at tick 0: ValueError: the controller has a bug (/code/controller.py"],
        ),
        ("hangs", ["stalled at tick 0: no /lab/step for 3 s"]),
        ("prints-gigabytes", ["printed more than 2 MiB"]),
        # held to its processes, the fork bomb leaves the lab free to see it never step;
        # its 32 processes may also reach the memory limit first (seen on a loaded machine)
        ("forks-without-end", ["stalled at tick 0: no /lab/step for 3 s", "out of memory"]),
        ("allocates-without-end", ["out of memory", "MemoryError"]),
        ("resolves-a-name", ["gaierror"]),
        ("writes-outside", ["Read-only file system", "Permission denied"]),
    ],
)
def test_attacks_end_as_errors_with_a_reason(backend, cache, host, tmp_path, name, reasons):
    """Each misbehaving controller ends as an error saying why."""
    limits = Limits(
        memory=256 * MiB,
        processes=32,
        output=2 * MiB,
        wall=20.0 if name == "forks-without-end" else 60.0,
    )
    options = RunOptions(limits=limits, first_step=3.0, stall=3.0)
    result = run(backend, cache, host, tmp_path, attack(name, tmp_path), options=options)
    assert result.outcome is Outcome.ERROR
    assert any(reason in result.reason for reason in reasons), result.reason


def attempts(result):
    """What the attack printed: one outcome per target, in the order given."""
    assert "the controller exited with 3 at tick 0" in result.reason, result.reason
    return json.loads((result.folder / "controller.stdout.log").read_text())


def test_no_connection_leaves_the_sandbox(backend, cache, host, tmp_path, host_listener):
    """TCP to the host's loopback or any of its own addresses fails inside the sandbox."""
    folder = attack("opens-tcp", tmp_path, target=host_listener)
    result = run(backend, cache, host, tmp_path, folder)
    assert result.outcome is Outcome.ERROR
    tried = list(zip(host_listener, attempts(result), strict=True))
    assert all(outcome in ("ECONNREFUSED", "ENETUNREACH") for _, outcome in tried), tried


def test_the_labs_files_cannot_be_read(backend, cache, host, tmp_path):
    """Files of the lab's on the host do not exist inside the sandbox."""
    secret = tmp_path / "secret" / "lab-token.txt"
    secret.parent.mkdir()
    secret.write_text("the lab's secret\n")
    folder = attack("reads-lab-files", tmp_path, target=[str(secret), str(ROOT / "pyproject.toml")])
    result = run(backend, cache, host, tmp_path, folder)
    assert result.outcome is Outcome.ERROR
    assert attempts(result) == ["FileNotFoundError"] * 2


def test_the_lab_carries_on_after_attacks(backend, cache, host, tmp_path):
    """After a controller that forks without end, the next trial runs and succeeds."""
    options = RunOptions(limits=Limits(processes=32, wall=10.0), first_step=3.0, stall=3.0)
    bad = run(
        backend, cache, host, tmp_path, attack("forks-without-end", tmp_path), options=options
    )
    assert bad.outcome is Outcome.ERROR
    good = run(backend, cache, host, tmp_path, EXAMPLES / "icreate-maze", seed=1)
    assert good.outcome is Outcome.SUCCESS, good.reason


def test_a_maze_run_out_of_time_is_a_fail(backend, cache, host, tmp_path):
    """The maze example given too little time runs to its end without reaching the goal:
    a fail, never a success, with the task's reason."""
    result = run(
        backend,
        cache,
        host,
        tmp_path,
        EXAMPLES / "icreate-maze",
        seed=1,
        params={"time_limit": 2.0},
    )
    assert result.outcome is Outcome.FAIL, result.reason
    assert result.reason.startswith("the episode ended at tick 20 without success: truncated")
    assert result.metrics["success"] is False
    assert result.mcap is not None and result.data_digest


def test_a_controller_cannot_forge_the_robots_data(backend, cache, host, tmp_path):
    """Forged /odom and /clock and an advertised /lab/step are refused with statuses naming them;
    the record holds none of it, and its data digest equals an honest run's."""
    forged = run(
        backend,
        cache,
        host,
        tmp_path,
        attack("forges-observations", tmp_path / "forge", {"forge": True}),
        seed=3,
    )
    honest = run(
        backend,
        cache,
        host,
        tmp_path,
        attack("forges-observations", tmp_path / "honest", {"forge": False}),
        seed=3,
    )
    # each steps five times and exits: the goal is not reached, a fail either way
    assert forged.outcome is honest.outcome is Outcome.FAIL, (forged.reason, honest.reason)
    assert forged.metrics["ticks"] == honest.metrics["ticks"] == 5
    assert forged.data_digest == honest.data_digest
    assert forged.data_digest == data_digest(forged.folder, forged.digest_topics)

    statuses = json.loads((forged.folder / "controller.stdout.log").read_text())["statuses"]
    refused = {s["id"]: s["msg"] for s in statuses}
    assert refused["adv-odom"].startswith("advertise: topic /odom belongs to the lab")
    for n in range(3):
        assert refused[f"odom-{n}"].startswith("publish: topic /odom belongs to the lab")
        assert refused[f"clock-{n}"].startswith("publish: topic /clock belongs to the lab")
    assert refused["adv-step"].startswith("advertise_service: service /lab/step belongs to the lab")
    assert json.loads((honest.folder / "controller.stdout.log").read_text())["statuses"] == []

    assert {c.topic for c in read_channels(forged.folder) if c.side is Side.CLIENT} == {"/cmd_vel"}
    decode = DecoderFactory().decoder_for
    odom = [
        decode("cdr", m.schema)(m.data).pose.pose.position.x
        for m in read_messages(forged.folder, topics=["/odom"])
    ]
    clocks = [m.log_time for m in read_messages(forged.folder, topics=["/clock"])]
    assert len(odom) == len(clocks) == 6 and 42.0 not in odom  # ticks 0 to 5, the robot's only
    assert clocks == [tick * 100_000_000 for tick in range(6)]
    lab_log = [
        decode("cdr", m.schema)(m.data).msg
        for m in read_messages(forged.folder, topics=["/rosout"], side=Side.LAB)
    ]
    assert sum("/odom belongs to the lab" in line for line in lab_log) == 4  # the attempts, as logs


def test_a_commit_over_the_checkout_limit_ends_as_an_error(cache, host, tmp_path):
    """A trial whose commit checks out past the worker's limit (8 paths sharing a 512 KiB
    blob, 4 MiB against 1 MiB) ends as an error naming the commit and the limit."""
    files = {"lab.toml": '[controller]\ncommand = ["python", "c.py"]\n', "c.py": "print(1)\n"}
    repo = GitRepo.create(tmp_path / "copies", files)
    repo.commit({f"copy-{n}.bin": bytes(512 * 1024) for n in range(8)}, "4 MiB of copies")
    policy = FetchPolicy(schemes=frozenset({"file"}), max_checkout_bytes=1 * MiB)
    result = run(
        make_backend("bwrap", cache), cache, host, tmp_path, repo.path,
        task="icreate-maze", options=RunOptions(fetch=policy),
    )  # fmt: skip
    assert result.outcome is Outcome.ERROR, result.reason
    assert "checks out to more than this lab's limit of 1.0 MiB" in result.reason
    assert f"commit {repo.rev()[:12]}" in result.reason
