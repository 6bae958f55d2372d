"""``labd users`` (the operator's, on the database) and ``labd reserve`` (a person's,
through a running lab's API), as a user runs them: what they print and their exits."""

from __future__ import annotations

import io
import json

import pytest

from labd.cli import main
from repository.accounts import Accounts
from repository.index import Index
from tests.helpers.labs import lab_config, running

pytestmark = pytest.mark.integration
PASSWORD = "correct horse battery"


def run(capsys, *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def test_users_add_list_password_revoke_rotate(tmp_path, capsys, monkeypatch):
    """The operator adds a user with a password, lists users with their tokens, revokes
    one token, then all, and rotates: each says what it did; bad input exits 2."""
    data = ["--data", str(tmp_path)]
    monkeypatch.setattr("sys.stdin", io.StringIO(PASSWORD + "\n"))
    code, out, _ = run(capsys, "users", "add", "alice", "--password-stdin", "--json", *data)
    assert code == 0
    first = json.loads(out)
    assert first["name"] == "alice" and first["password"] is True
    code, out, _ = run(capsys, "users", "list", *data)
    assert code == 0
    assert "alice                password, 1 of 1 tokens working" in out
    assert "token #1 made by the operator (labd users add)" in out and first["token"] not in out
    code, out, err = run(capsys, "users", "rotate", "alice", *data)
    assert code == 0 and out.startswith("labd_") and "every other token revoked" in err
    new = out.strip()
    index = Index.open(f"sqlite:///{tmp_path / 'index.sqlite'}")
    try:
        assert index.user_by_token(first["token"]) is None
        assert index.user_by_token(new).name == "alice"
        assert Accounts(index).check_password("alice", PASSWORD).name == "alice"
    finally:
        index.close()
    code, out, _ = run(capsys, "users", "revoke", "alice", "--token", "2", *data)
    assert (code, out.strip()) == (
        0,
        "alice: token #2 (rotated by the operator (labd users rotate)) revoked",
    )
    code, out, _ = run(capsys, "users", "revoke", "alice", *data)
    assert out.strip() == (
        "alice: 0 tokens revoked, every sign-in ended, and the keys of their booked slots replaced"
    )
    monkeypatch.setattr("sys.stdin", io.StringIO("short\n"))
    code, _, err = run(capsys, "users", "password", "alice", "--password-stdin", *data)
    assert code == 2 and "at least 10 characters" in err
    code, _, err = run(capsys, "users", "revoke", "nobody", *data)
    assert code == 2 and "no user 'nobody'" in err
    monkeypatch.setattr("sys.stdin", io.StringIO(""))
    code, _, err = run(capsys, "users", "add", "bob", "--password", *data)
    assert code == 2 and "give --password-stdin" in err


@pytest.fixture
def server(tmp_path):
    """A lab whose live maze robot is driven only in a reserved slot."""
    with running(lab_config(tmp_path / "data", reservations=True)) as server:
        yield server


def test_reserve_book_list_extend_key_release(server, capsys, monkeypatch):
    """A person books, lists, extends, reads the key of, and releases a slot with
    labd reserve; a refused booking exits 2 with the lab's message."""
    service = server.lab.service
    monkeypatch.setenv("LABD_SERVER", server.lab.http.url())
    monkeypatch.setenv("LABD_TOKEN", service.index.add_user("alice"))
    code, out, _ = run(capsys, "reserve", "book", "icreate-1", "--minutes", "20", "--json")
    assert code == 0, out
    made = json.loads(out)
    slot, key = made["reservation"]["id"], made["key"]["key"]
    assert service.reservations.authorize(key, "icreate-1").reservation.user == "alice"
    code, out, _ = run(capsys, "reserve", "list", "--robot", "icreate-1")
    assert code == 0 and f"#{slot:<5} icreate-1" in out and "(20 min) alice [current]" in out
    code, out, _ = run(capsys, "reserve", "extend", str(slot), "--minutes", "10")
    assert code == 0 and "(30 min) alice [current]" in out
    code, out, _ = run(capsys, "reserve", "key", str(slot))
    assert (code, out.strip()) == (0, key)
    code, _, err = run(capsys, "reserve", "book", "icreate-1", "--minutes", "10")
    assert code == 2 and "icreate-1 is booked from" in err and "by alice" in err
    code, out, _ = run(capsys, "reserve", "release", str(slot))
    assert code == 0 and "alice [released]" in out
    code, _, err = run(
        capsys, "reserve", "book", "icreate-1", "--start", "yesterday", "--minutes", "5"
    )
    assert code == 2 and "'yesterday' is not a time" in err
