"""`labd serve` as a service, used through the `labd` command as users use it.

A real server process (HTTP API, queue, one worker with bubblewrap), real git
repositories, the real CLI: submit, list, show, download, rerun by commit and read
"reproduced"; and a SIGKILL in the middle of a trial, after which nothing is lost.
"""

from __future__ import annotations

import json
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pyarrow.parquet as pq
import pytest
import s3fs
from mcap.reader import make_reader
from moto.server import ThreadedMotoServer

from scheduler.remote import PROTOCOL, PROTOCOL_HEADER
from tests.faults.conftest import wait_for
from tests.helpers.githttp import GitHttpServer, GitRepo

pytestmark = pytest.mark.integration
ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "controllers" / "examples"

SLOW = '''\
"""Steps slowly, so a test can kill the lab in the middle of the trial."""
import time
from controllers.client import Lab, EpisodeOver

with Lab.connect() as lab:
    for _ in range(200):
        lab.publish("/cmd_vel", "geometry_msgs/msg/Twist", {"angular": {"z": 0.5}})
        try:
            lab.step()
        except EpisodeOver:
            break
        time.sleep(0.05)
'''


def make_repo(path: Path, files: dict[str, str] | None = None, copy: Path | None = None) -> Path:
    """A git repository at ``path`` with one commit: ``files``, or the files of ``copy``."""
    if copy is not None:
        files = {p.name: p.read_text() for p in copy.iterdir() if p.is_file()}
    return GitRepo.create(path, files, "a controller").path


@pytest.fixture
def served_lab(make_served_lab):
    return make_served_lab()


def test_submit_list_download_and_rerun_by_commit(served_lab, tmp_path):
    """A newcomer's path: submit by path and ref, list, download the MCAP, rerun, reproduced."""
    repo = make_repo(tmp_path / "maze", copy=EXAMPLES / "icreate-maze")
    commit = GitRepo(repo).rev()
    trial = served_lab.json(
        "submit", str(repo), "--ref", "main", "--task", "icreate-maze", "--wait"
    )
    assert (trial["status"], trial["outcome"]) == ("finished", "success"), trial
    assert trial["commit"] == commit
    assert trial["metrics"]["success"] is True
    listed = served_lab.json("trials", "--commit", commit[:8])
    assert [t["id"] for t in listed["trials"]] == [trial["id"]]
    mcap = tmp_path / "record.mcap"
    served_lab.labd("download", str(trial["id"]), "-o", str(mcap))
    with mcap.open("rb") as stream:
        topics = {c.topic for c in make_reader(stream).get_summary().channels.values()}
    assert {"/odom", "/cmd_vel", "/clock"} <= topics
    text = served_lab.labd("rerun", commit[:10], "--wait").stdout
    assert re.search(r"trial \d+ \(rerun of \d+\): reproduced", text), text
    page = served_lab.json("show", str(trial["id"]))
    assert page["outcome"] == "success"
    table = served_lab.labd("trials").stdout
    assert re.search(rf"^\s*{trial['id']}\s+success\s+\S+\s+icreate-maze", table, re.M), table
    out = tmp_path / "lerobot"
    exported = served_lab.json("export", str(trial["id"]), "--format", "lerobot", "-o", str(out))
    assert exported["frames"] > 100
    info = json.loads((out / "meta" / "info.json").read_text())
    assert exported["frames"] == info["total_frames"] == trial["metrics"]["ticks"]  # every tick
    assert "observation.images.camera" in info["features"]  # rendered: the example never looked
    episodes = pq.read_table(out / "meta" / "episodes" / "chunk-000" / "file-000.parquet")
    provenance = json.loads(episodes.to_pylist()[0]["labd/provenance"])
    assert provenance["commit"] == commit
    assert provenance["manifest"] == page["manifest"]
    assert provenance["data_digest"] == trial["data_digest"]
    assert provenance["signature"] == page["signature"]

    # the three ways to check a record: rerun (above), and the lab's signature, offline
    keys = tmp_path / "lab-keys.json"
    keys.write_text(httpx.get(f"{served_lab.server}/api/keys").text)
    verified = served_lab.labd("verify", str(mcap), "--key", str(keys)).stdout
    assert f"verified: trial {trial['id']} (icreate-maze, success)" in verified
    assert served_lab.labd("verify", str(out), "--key", str(keys)).returncode == 0
    data = bytearray(mcap.read_bytes())
    data[len(data) // 2] ^= 0x01  # one bit, in the middle of the messages
    mcap.write_bytes(bytes(data))
    broken = served_lab.labd("verify", str(mcap), "--key", str(keys), check=False)
    assert broken.returncode == 6 and "was changed after the lab signed it" in broken.stderr
    info_file = out / "meta" / "info.json"
    info_file.write_text(info_file.read_text().replace('"total_frames"', '"total_frames" '))
    edited = served_lab.labd("verify", str(out), "--key", str(keys), check=False)
    assert edited.returncode == 6 and "changed: meta/info.json" in edited.stderr


def test_a_sigkill_mid_trial_loses_nothing(served_lab, tmp_path):
    """`labd serve` killed while a trial runs: after a restart every trial still ends."""
    repo = make_repo(
        tmp_path / "slow",
        {"lab.toml": '[controller]\ncommand = ["python", "slow.py"]\n', "slow.py": SLOW},
    )
    first = served_lab.json("submit", str(repo), "--task", "icreate-maze")
    second = served_lab.json("submit", str(repo), "--task", "icreate-maze", "--seed", "1")
    record = served_lab.data / "work" / f"trial-{first['id']}-1" / "trial.mcap"
    deadline = time.monotonic() + 120
    while not record.exists():  # the recording has begun: the trial is under way
        assert time.monotonic() < deadline, "".join(served_lab.output)
        time.sleep(0.05)
    assert httpx.get(f"{served_lab.server}/api/trials/{first['id']}").json()["status"] == "running"
    served_lab.kill()
    served_lab.start()
    deadline = time.monotonic() + 180
    while True:
        rows = [served_lab.json("show", str(t["id"])) for t in (first, second)]
        if all(r["status"] in ("finished", "cancelled") for r in rows):
            break
        assert time.monotonic() < deadline, rows
        time.sleep(0.5)
    # each ran its 200 slow steps to the end and exited, short of the goal: a fail
    assert [(r["status"], r["outcome"]) for r in rows] == [("finished", "fail")] * 2, [
        r["reason"] for r in rows
    ]
    assert rows[0]["attempts"] == 2
    assert rows[1]["attempts"] == 1
    assert all(r["mcap"] for r in rows)


TELLTALE = """\
import os, sys
from controllers.client import Lab
print("environment:", sorted(os.environ.items()))
with Lab.connect() as lab:
    for _ in range(5):
        lab.step()
"""


def test_public_and_private_repositories_over_smart_http(make_served_lab, tmp_path):
    """Over a real git smart-HTTP server: a public repository, and a private one fetched
    with the operator's token, which the controller never sees."""
    token = "tok-" + "s3cret" * 4
    served = tmp_path / "served"
    files = {"lab.toml": '[controller]\ncommand = ["python", "c.py"]\n', "c.py": TELLTALE}
    public = GitRepo.create(served / "open-bot", files)
    private = GitRepo.create(served / "secret-bot", files)
    with GitHttpServer(
        served, users={"x-access-token": token}, private={"secret-bot"}
    ) as git_server:
        token_file = tmp_path / "token"
        token_file.write_text(token + "\n")
        lab = make_served_lab(
            "--allow-scheme",
            "http",
            "--git-token",
            f"{git_server.url('secret-bot')}={token_file}",
            "--allow-private-hosts",  # the git server is on loopback
        )
        shown = {}
        for name, repo in (("open-bot", public), ("secret-bot", private)):
            trial = lab.json("submit", git_server.url(name), "--ref", "main", "--task",
                             "icreate-maze", "--wait", code=1)  # fmt: skip
            assert (trial["status"], trial["outcome"]) == ("finished", "fail"), trial
            assert trial["commit"] == repo.rev("main")
            shown[name] = trial
        assert shown["open-bot"]["public"] is True
        assert shown["secret-bot"]["public"] is False
        done = lab.labd("show", str(shown["secret-bot"]["id"]), "--json")
        logs = json.loads(done.stdout)["logs"]
        text = httpx.get(logs["stdout"]).text
        assert "environment:" in text
        assert token not in text
        refused = lab.labd(
            "submit", "ftp://example.org/x.git", "--task", "icreate-maze", check=False
        )
        assert refused.returncode == 2
        assert "not allowed" in refused.stderr


def test_a_worker_on_another_machine(make_served_lab, tmp_path, cache):
    """`labd worker --server` runs the queue's trials over the HTTP API and files them."""
    lab = make_served_lab("--workers", "0")
    made = lab.labd("users", "add", "w1", "--worker", "--data", str(lab.data), "--json")
    worker_token = json.loads(made.stdout)["token"]
    denied = httpx.post(
        f"{lab.server}/api/workers/claim",
        json={"worker": "x"},
        headers={"Authorization": f"Bearer {lab.token}", PROTOCOL_HEADER: str(PROTOCOL)},
    )
    assert denied.status_code == 403
    assert "not a worker" in denied.json()["error"]
    repo = make_repo(tmp_path / "maze", copy=EXAMPLES / "icreate-maze")
    first = lab.json("submit", str(repo), "--task", "icreate-maze")
    data = tmp_path / "worker-data"
    data.mkdir()
    (data / "cache").symlink_to(cache)
    worker = subprocess.Popen(
        [sys.executable, "-m", "labd", "worker", "--server", lab.server, "--token",
         worker_token, "--sandbox", "bwrap", "--data", str(data), "--poll", "0.2",
         "--allow-local-repos"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    try:
        text = lab.labd("rerun", str(first["id"]), "--wait").stdout
        done = lab.json("show", str(first["id"]))
    finally:
        worker.send_signal(signal.SIGTERM)
        output, _ = worker.communicate(timeout=60)
    assert done["outcome"] == "success", output
    assert done["worker"].startswith("w1@")
    assert "reproduced" in text, output
    # "verified" is the lab's word: the worker replays nothing, the lab replays its record
    replay = f"{lab.server}/api/trials/{first['id']}/replay"
    verdict = wait_for(
        "the lab's replay",
        lambda: (r := httpx.get(replay, timeout=30)).status_code == 200 and r.json(),
        120,
    )
    assert verdict["verified"] is True, verdict
    assert "replay" not in output, output


def test_cancel_a_running_trial(served_lab, tmp_path):
    """`labd cancel` stops a running trial at its worker's next heartbeat; it is filed as
    cancelled, and the queue goes on to the next trial."""
    slower = SLOW.replace("range(200)", "range(2000)")  # ends by the cancel, however loaded
    repo = make_repo(
        tmp_path / "slow",
        {"lab.toml": '[controller]\ncommand = ["python", "slow.py"]\n', "slow.py": slower},
    )
    first = served_lab.json("submit", str(repo), "--task", "icreate-maze")
    quick = make_repo(tmp_path / "quick", {"lab.toml": TELLTALE_TOML, "c.py": TELLTALE})
    second = served_lab.json("submit", str(quick), "--task", "icreate-maze")
    record = served_lab.data / "work" / f"trial-{first['id']}-1" / "trial.mcap"
    deadline = time.monotonic() + 120
    while not record.exists():
        assert time.monotonic() < deadline, "".join(served_lab.output)
        time.sleep(0.05)
    asked = served_lab.json("cancel", str(first["id"]))
    assert asked["status"] == "running" and asked["cancel_requested"] is True
    [cancelled, after] = lab_wait(served_lab, [first["id"], second["id"]])
    assert (cancelled["status"], cancelled["outcome"]) == ("cancelled", None)
    assert "cancelled while it ran" in cancelled["reason"]
    assert after["status"] == "finished"
    again = served_lab.labd("cancel", str(first["id"]), check=False)
    assert again.returncode == 2 and "had already ended" in again.stderr


def lab_wait(served_lab, ids, timeout=180):
    deadline = time.monotonic() + timeout
    while True:
        rows = [httpx.get(f"{served_lab.server}/api/trials/{i}").json() for i in ids]
        if all(r["status"] in ("finished", "cancelled") for r in rows):
            return rows
        assert time.monotonic() < deadline, rows
        time.sleep(0.2)


TELLTALE_TOML = '[controller]\ncommand = ["python", "c.py"]\n'


@pytest.fixture
def s3_bucket(monkeypatch):
    """A real S3-compatible server (moto) on 127.0.0.1, with a bucket for the archive."""
    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    host, port = server.get_host_and_port()
    endpoint = f"http://{host}:{port}"
    monkeypatch.setenv("AWS_ACCESS_KEY_ID", "testing")
    monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", "testing")
    fs = s3fs.S3FileSystem(endpoint_url=endpoint, key="testing", secret="testing")
    fs.mkdir("lab-archive")
    yield endpoint, fs
    server.stop()


def test_the_archive_in_an_s3_bucket(make_served_lab, s3_bucket, tmp_path):
    """With --blobs s3://..., records go to the bucket and come back checked."""
    endpoint, fs = s3_bucket
    lab = make_served_lab(
        "--blobs", "s3://lab-archive/records", "--blobs-option", f"endpoint_url={endpoint}"
    )
    repo = make_repo(tmp_path / "quick", {"lab.toml": TELLTALE_TOML, "c.py": TELLTALE})
    trial = lab.json("submit", str(repo), "--task", "icreate-maze", "--wait", code=1)
    assert trial["outcome"] == "fail", trial  # five steps, then it stops: not the goal
    digest = trial["mcap"]["digest"]
    fs.invalidate_cache()
    key = f"lab-archive/records/sha256/{digest[7:9]}/{digest[7:]}"
    assert fs.exists(key)
    mcap = tmp_path / "record.mcap"
    lab.labd("download", str(trial["id"]), "-o", str(mcap))
    assert mcap.read_bytes() == fs.cat_file(key)
    fs.pipe_file(key, b"damaged")  # the bucket's copy is altered behind the lab's back
    damaged = httpx.get(f"{lab.server}/api/trials/{trial['id']}/data.mcap")
    assert damaged.status_code == 500
    assert "damaged" in damaged.json()["error"]
