"""Accounts on both databases: passwords (argon2), API tokens their owners list and
revoke, the operator's revoke and rotate, browser sessions with a CSRF token."""

from __future__ import annotations

import pytest
import sqlalchemy as sa
from argon2 import PasswordHasher

from repository.accounts import Accounts
from repository.errors import AccountError, ArchiveError, BadCredentials, RecordNotFound
from repository.index import Index, connect, passwords, web_sessions


class Clock:
    def __init__(self) -> None:
        self.now = 1_900_000_000.0

    def __call__(self) -> float:
        return self.now


@pytest.fixture
def clock():
    return Clock()


@pytest.fixture
def index(database_url, clock):
    index = Index(connect(database_url), clock=clock)
    index.create()
    yield index
    index.close()


@pytest.fixture
def accounts(index):
    # cheap parameters: these tests check the logic, not argon2's cost
    return Accounts(index, hasher=PasswordHasher(time_cost=1, memory_cost=1024), session_age=60)


def test_sign_up_and_password_checks(accounts, index):
    """A signed-up person signs in with their password only; the database keeps an
    argon2id hash; a wrong name and a wrong password are the same refusal."""
    accounts.sign_up("carol", "correct horse battery")
    assert accounts.check_password("carol", "correct horse battery").name == "carol"
    for name, password in (("carol", "wrong password!"), ("nobody", "correct horse battery")):
        with pytest.raises(BadCredentials, match="the user name or the password is wrong"):
            accounts.check_password(name, password)
    with index.engine.connect() as db:
        stored = db.execute(sa.select(passwords.c.hash)).scalar()
    assert stored.startswith("$argon2id$") and "correct horse" not in stored
    with pytest.raises(AccountError, match="at least 10 characters"):
        accounts.sign_up("dave", "short")
    with pytest.raises(ArchiveError, match="exists already"):
        accounts.sign_up("carol", "another long password")
    assert accounts.tokens("carol") == []  # no token until they make one


def test_an_old_hash_is_upgraded_at_sign_in(index):
    """A hash made with weaker parameters is replaced at the next good sign-in."""
    weak = Accounts(index, hasher=PasswordHasher(time_cost=1, memory_cost=1024))
    weak.sign_up("carol", "correct horse battery")
    strong = Accounts(index, hasher=PasswordHasher(time_cost=2, memory_cost=2048))
    strong.check_password("carol", "correct horse battery")
    with index.engine.connect() as db:
        stored = db.execute(sa.select(passwords.c.hash)).scalar()
    assert "m=2048,t=2" in stored


def test_tokens_are_listed_made_and_revoked_by_their_owner(accounts, index):
    """A user lists their tokens (labels, never the tokens), makes more, revokes one:
    it stops working at once, the others go on; nobody revokes another's token."""
    first = index.add_user("alice")
    listed = accounts.tokens("alice")
    assert [t.label for t in listed] == ["made by the operator (labd users add)"]
    made, second = accounts.new_token("alice", "  my laptop\n")
    assert made.label == "my laptop" and index.user_by_token(second).name == "alice"
    index.add_user("bob")
    with pytest.raises(RecordNotFound):
        accounts.revoke_token("bob", made.id)
    revoked = accounts.revoke_token("alice", made.id)
    assert revoked.revoked is not None
    assert index.user_by_token(second) is None
    assert index.user_by_token(first).name == "alice"
    assert [t.revoked is None for t in accounts.tokens("alice")] == [False, True]


def test_the_operator_revokes_every_token_or_rotates(accounts, index):
    """Revoking all of a user's tokens ends their browser sessions too; rotating leaves
    exactly one new token that works."""
    first = index.add_user("alice")
    _, second = accounts.new_token("alice", "ci")
    cookie, _ = accounts.open_session(index.user("alice"))
    assert accounts.revoke_all("alice") == 2
    assert index.user_by_token(first) is None and index.user_by_token(second) is None
    assert accounts.session(cookie) is None
    new = accounts.rotate("alice")
    assert index.user_by_token(new).name == "alice"
    assert [t.revoked is None for t in accounts.tokens("alice")] == [True, False, False]


def test_a_token_an_older_labd_made_still_works_until_revoked(accounts, index):
    """A user whose only token lives in the users table (an older labd's) still signs
    in with it; revoking all their tokens ends it too."""
    token = index.add_user("alice")
    with index.begin() as db:
        db.execute(sa.delete(index.tokens))
    assert index.user_by_token(token).name == "alice"
    accounts.revoke_all("alice")
    assert index.user_by_token(token) is None


def test_sessions_expire_and_end_and_keep_only_a_hash(accounts, index, clock):
    """A session names its user and CSRF token until it expires or is ended; the
    database holds only the cookie's hash."""
    index.add_user("alice", token=False)
    cookie, session = accounts.open_session(index.user("alice"))
    assert accounts.session(cookie).csrf == session.csrf and len(session.csrf) >= 24
    with index.engine.connect() as db:
        assert cookie not in str(db.execute(sa.select(web_sessions)).all())
    assert accounts.session(cookie + "x") is None
    clock.now += 61
    assert accounts.session(cookie) is None
    again, _ = accounts.open_session(index.user("alice"))
    accounts.end_session(again)
    assert accounts.session(again) is None
