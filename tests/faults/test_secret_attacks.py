"""Secrets in the operator's settings, read back from what the lab prints (issue 32).

An operator's credentials hide in more places than the settings named after them: a
database URL's ``?password=``, an authorizer's ``?token=``, an object store's
``endpoint_url=http://user:PW@host`` or ``aws_session_token=``. Each test puts one
in and reads everything the lab prints about it (``labd config show``, the error of a
command that cannot reach the index or the lab, a fetch's error): no secret may be
there, while the message still says where (scheme, host, port, path).
"""

from __future__ import annotations

import json
import logging
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from repository.blobs import BlobStore
from scheduler.errors import LabUnreachable, RepositoryError
from scheduler.fetch import FetchPolicy, resolve
from scheduler.remote import RemoteLab
from tests.helpers.githttp import GitHttpServer, GitRepo

SECRETS = {
    "database": "db-pw-7e1c",
    "authorizer": "auth-tok-5a9d",
    "endpoint": "s3-pw-40b2",
    "session": "s3-session-91fe",
    "fragment": "frag-tok-c3d8",
}


def labd(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "labd", *args],
        capture_output=True,
        text=True,
        check=False,
        cwd=cwd,
        timeout=120,
        # the settings are the file's alone (and ./labd.toml is the test's)
        env={k: v for k, v in os.environ.items() if not k.startswith("LABD_")},
    )


def closed_port() -> int:
    """A loopback port nothing listens on (bound, then let go)."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def leaked(text: str) -> list[str]:
    return [name for name, secret in SECRETS.items() if secret in text]


def test_config_show_masks_query_values_and_options_that_hold_urls(tmp_path):
    """`labd config show`, as text and as JSON, prints no password or token from a URL's
    query or fragment, from an option whose value is a URL with a password, or from an
    option named for a credential; the hosts and paths are still shown."""
    (tmp_path / "labd.toml").write_text(
        "[serve]\n"
        f'database = "postgresql+psycopg://lab@db:5432/lab?password={SECRETS["database"]}"\n'
        f'authorizer = "https://auth.example.org/check?token={SECRETS["authorizer"]}'
        f'#access_token={SECRETS["fragment"]}"\n'
        'blobs = "s3://lab-archive/records"\n'
        "blobs_option = ["
        f'"endpoint_url=http://minio:{SECRETS["endpoint"]}@s3.example.org:9000",'
        f' "aws_session_token={SECRETS["session"]}", "region_name=eu-west-1"]\n'
    )
    shown = labd("config", "show", cwd=tmp_path)
    as_json = labd("config", "show", "--json", cwd=tmp_path)
    assert shown.returncode == 0 and as_json.returncode == 0, shown.stderr + as_json.stderr
    assert leaked(shown.stdout + shown.stderr) == []
    assert leaked(as_json.stdout + as_json.stderr) == []
    settings = json.loads(as_json.stdout)["settings"]
    assert settings["database"] == "postgresql+psycopg://lab@db:5432/lab?password=***"
    assert settings["authorizer"] == "https://auth.example.org/check?token=***#access_token=***"
    assert settings["blobs_option"] == [
        "endpoint_url=http://minio:***@s3.example.org:9000",
        "aws_session_token=***",
        "region_name=eu-west-1",
    ]


def test_an_unreachable_index_is_named_without_its_password(tmp_path):
    """A command that cannot reach the index says which one, without the password its
    URL carries in the query (libpq's ``?password=``)."""
    url = f"postgresql+psycopg://lab@127.0.0.1:{closed_port()}/lab?password={SECRETS['database']}"
    done = labd("users", "list", "--data", str(tmp_path / "data"), "--database", url, cwd=tmp_path)
    assert done.returncode != 0
    assert "cannot reach the index at postgresql+psycopg://lab@127.0.0.1:" in done.stderr
    assert leaked(done.stdout + done.stderr) == []


def test_a_worker_that_cannot_reach_its_lab_hides_the_servers_token():
    """A remote worker (``labd worker --server URL`` says this error as it is) that
    cannot reach its lab names the URL without the token in its query."""
    server = f"http://127.0.0.1:{closed_port()}/?token={SECRETS['authorizer']}"
    lab = RemoteLab(server, "t")
    try:
        with pytest.raises(LabUnreachable) as caught:
            lab.hello()
    finally:
        lab.close()
    assert "cannot reach the lab at http://127.0.0.1:" in str(caught.value)
    assert leaked(str(caught.value)) == []


def test_a_blob_store_is_shown_without_its_credentials(tmp_path):
    """A blob store, as logs show it, names its URL without the password in it."""
    store = BlobStore(f"memory://minio:{SECRETS['endpoint']}@lab-archive/records")
    assert leaked(repr(store)) == []
    assert "lab-archive/records" in repr(store)


@pytest.mark.integration
def test_a_repository_url_with_a_token_in_its_query_is_refused_unechoed(tmp_path, caplog):
    """A repository URL with a token in its query is refused (the lab would record it,
    and show it to anyone) before any fetch, and the token is neither in the answer nor
    in the lab's log."""
    caplog.set_level(logging.DEBUG)
    served = tmp_path / "served"
    GitRepo.create(served / "robot", {"lab.toml": "[controller]\n"})
    policy = FetchPolicy(schemes=frozenset({"http"}), private_hosts=True)
    with GitHttpServer(served) as server:
        urls = [
            f"{server.url('robot')}?token={SECRETS['authorizer']}",
            f"{server.url('nothing-here')}?token={SECRETS['authorizer']}",
            f"http://127.0.0.1:{closed_port()}/robot#access_token={SECRETS['fragment']}",
        ]
        for url in urls:
            with pytest.raises(RepositoryError) as caught:
                resolve(url, None, tmp_path / "cache", policy)
            assert leaked(str(caught.value)) == [], str(caught.value)
            assert "has a query or fragment in it" in str(caught.value)
        assert server.requests == []
    assert leaked(caplog.text) == []
