"""Accounts on both databases: passwords (argon2), API tokens their owners list and
revoke, the operator's revoke and rotate, browser sessions with a CSRF token."""

from __future__ import annotations

import pytest
import sqlalchemy as sa
from argon2 import PasswordHasher

from repository.accounts import Accounts, usable_name
from repository.errors import (
    AccountError,
    ArchiveError,
    BadCredentials,
    RecordNotFound,
    UnknownKey,
)
from repository.reservations import Reservations, Rules
from repository.tables import passwords, web_sessions
from tests.fakes import WallClock


@pytest.fixture
def clock() -> WallClock:
    return WallClock(1_900_000_000.0)


@pytest.fixture
def accounts(clocked_index):
    # cheap parameters: these tests check the logic, not argon2's cost
    return Accounts(
        clocked_index, hasher=PasswordHasher(time_cost=1, memory_cost=1024), session_age=60
    )


def test_sign_up_and_password_checks(accounts, clocked_index):
    """A signed-up person signs in with their password only; the database keeps an
    argon2id hash; a wrong name and a wrong password are the same refusal."""
    accounts.sign_up("carol", "correct horse battery")
    assert accounts.check_password("carol", "correct horse battery").name == "carol"
    for name, password in (("carol", "wrong password!"), ("nobody", "correct horse battery")):
        with pytest.raises(BadCredentials, match="the user name or the password is wrong"):
            accounts.check_password(name, password)
    with clocked_index.engine.connect() as db:
        stored = db.execute(sa.select(passwords.c.hash)).scalar()
    assert stored.startswith("$argon2id$") and "correct horse" not in stored
    with pytest.raises(AccountError, match="at least 10 characters"):
        accounts.sign_up("dave", "short")
    with pytest.raises(ArchiveError, match="exists already"):
        accounts.sign_up("carol", "another long password")
    assert accounts.tokens("carol") == []  # no token until they make one


def test_an_old_hash_is_upgraded_at_sign_in(clocked_index):
    """A hash made with weaker parameters is replaced at the next good sign-in."""
    weak = Accounts(clocked_index, hasher=PasswordHasher(time_cost=1, memory_cost=1024))
    weak.sign_up("carol", "correct horse battery")
    strong = Accounts(clocked_index, hasher=PasswordHasher(time_cost=2, memory_cost=2048))
    strong.check_password("carol", "correct horse battery")
    with clocked_index.engine.connect() as db:
        stored = db.execute(sa.select(passwords.c.hash)).scalar()
    assert "m=2048,t=2" in stored


def test_tokens_are_listed_made_and_revoked_by_their_owner(accounts, clocked_index):
    """A user lists their tokens (labels, never the tokens), makes more, revokes one:
    it stops working at once, the others go on; nobody revokes another's token."""
    first = clocked_index.add_user("alice")
    listed = accounts.tokens("alice")
    assert [t.label for t in listed] == ["made by the operator (labd users add)"]
    made, second = accounts.new_token("alice", "  my laptop\n")
    assert made.label == "my laptop" and clocked_index.user_by_token(second).name == "alice"
    clocked_index.add_user("bob")
    with pytest.raises(RecordNotFound):
        accounts.revoke_token("bob", made.id)
    revoked = accounts.revoke_token("alice", made.id)
    assert revoked.revoked is not None
    assert clocked_index.user_by_token(second) is None
    assert clocked_index.user_by_token(first).name == "alice"
    assert [t.revoked is None for t in accounts.tokens("alice")] == [False, True]


def test_the_operator_revokes_every_token_or_rotates(accounts, clocked_index):
    """Revoking all of a user's tokens ends their browser sessions too; rotating leaves
    exactly one new token that works."""
    first = clocked_index.add_user("alice")
    _, second = accounts.new_token("alice", "ci")
    cookie, _ = accounts.open_session(clocked_index.user("alice"))
    assert accounts.revoke_all("alice") == 2
    assert (
        clocked_index.user_by_token(first) is None and clocked_index.user_by_token(second) is None
    )
    assert accounts.session(cookie) is None
    new = accounts.rotate("alice")
    assert clocked_index.user_by_token(new).name == "alice"
    assert [t.revoked is None for t in accounts.tokens("alice")] == [True, False, False]


def test_a_token_an_older_labd_made_still_works_until_revoked(accounts, clocked_index):
    """A user whose only token lives in the users table (an older labd's) still signs
    in with it; revoking all their tokens ends it too."""
    token = clocked_index.add_user("alice")
    with clocked_index.begin() as db:
        db.execute(sa.delete(clocked_index.tokens))
    assert clocked_index.user_by_token(token).name == "alice"
    accounts.revoke_all("alice")
    assert clocked_index.user_by_token(token) is None


def test_sessions_expire_and_end_and_keep_only_a_hash(accounts, clocked_index, clock):
    """A session names its user and CSRF token until it expires or is ended; the
    database holds only the cookie's hash."""
    clocked_index.add_user("alice", token=False)
    cookie, session = accounts.open_session(clocked_index.user("alice"))
    assert accounts.session(cookie).csrf == session.csrf and len(session.csrf) >= 24
    with clocked_index.engine.connect() as db:
        assert cookie not in str(db.execute(sa.select(web_sessions)).all())
    assert accounts.session(cookie + "x") is None
    clock.now += 61
    assert accounts.session(cookie) is None
    again, _ = accounts.open_session(clocked_index.user("alice"))
    accounts.end_session(again)
    assert accounts.session(again) is None


def test_a_new_password_ends_the_other_sessions_and_keeps_the_tokens(accounts, clocked_index):
    """Alice's own change keeps the session she changed it from and ends her others;
    the operator's reset ends them all; a wrong current password changes nothing; her
    tokens work throughout; an upgraded hash (the same password) ends nothing."""
    token = clocked_index.add_user("alice")
    accounts.set_password("alice", "correct horse battery")
    here, _ = accounts.open_session(clocked_index.user("alice"))
    there, _ = accounts.open_session(clocked_index.user("alice"))
    with pytest.raises(BadCredentials):
        accounts.change_password("alice", "not the password", "another long one", keep=here)
    assert accounts.session(there) is not None
    assert (
        accounts.change_password("alice", "correct horse battery", "another long one", keep=here)
        == 1
    )
    assert accounts.session(here) is not None and accounts.session(there) is None
    assert accounts.check_password("alice", "another long one").name == "alice"
    with pytest.raises(BadCredentials):
        accounts.check_password("alice", "correct horse battery")
    stronger = Accounts(clocked_index, hasher=PasswordHasher(time_cost=2, memory_cost=2048))
    stronger.check_password("alice", "another long one")  # re-hashed: the session stays
    assert accounts.session(here) is not None
    assert accounts.set_password("alice", "the operator's reset") == 1
    assert accounts.session(here) is None
    assert clocked_index.user_by_token(token).name == "alice"


def test_revoking_a_user_replaces_the_keys_of_their_slots(accounts, clocked_index, tmp_path):
    """``labd users revoke NAME`` (revoke_all) makes every reservation key of theirs open
    nothing, and leaves their slots booked and others' keys working."""
    clocked_index.add_user("alice")
    clocked_index.add_user("bob")
    desk = Reservations(clocked_index, Rules(), b"k" * 32)
    now = clocked_index.clock()
    alices = desk.book("alice", "icreate-1", now, now + 600)
    bobs = desk.book("bob", "pr2-1", now, now + 600)
    accounts.revoke_all("alice")
    with pytest.raises(UnknownKey):
        desk.authorize(alices.key)
    assert desk.authorize(bobs.key).reservation.user == "bob"
    assert [r.user for r in desk.find(robot="icreate-1")] == ["alice"]


@pytest.mark.parametrize(
    "name",
    ["\u0430lice", "\uff41lice", ".", "..", ".alice", "-x", "al ice", "alice\n", "a" * 65, ""],
)
def test_names_that_could_pass_for_others_are_refused(clocked_index, name):
    """A new name is ASCII letters, digits, '.', '-', '_', starting with a letter or a
    digit: look-alikes in other scripts and dot names are refused naming the rule."""
    with pytest.raises(ArchiveError, match="use 1 to 64 ASCII letters, digits"):
        clocked_index.add_user(name)


def test_names_are_unique_without_case_and_old_collisions_are_found(clocked_index):
    """'Alice' beside 'alice' is refused; names an older labd let collide are kept,
    listed by name_collisions, and no third spelling may join them."""
    clocked_index.add_user("alice")
    with pytest.raises(ArchiveError, match="'ALICE' is taken: names are told apart without case"):
        clocked_index.add_user("ALICE")
    with clocked_index.begin() as db:  # as an older labd could have made them
        for name in ("Bob", "bob"):
            db.execute(
                sa.insert(clocked_index.users).values(
                    name=name,
                    token_sha256=name,
                    created=0,
                    max_running=1,
                    max_daily=1,
                    worker=False,
                )
            )
    assert clocked_index.name_collisions() == [["Bob", "bob"]]
    with pytest.raises(ArchiveError, match="is taken"):
        clocked_index.add_user("BOB")
    assert clocked_index.user("Bob").name == "Bob" and clocked_index.user("bob").name == "bob"


# -- identities from OpenID providers ------------------------------------------------------------

ISSUER = "https://login.example.edu"


@pytest.mark.parametrize(
    ("wanted", "name"),
    [
        ("ann", "ann"),
        ("Ann Smith", "AnnSmith"),
        ("_ann.", "ann"),
        ("jérôme", "jrme"),
        ("名前", "user"),
        ("a" * 80, "a" * 64),
    ],
)
def test_a_provider_s_name_made_a_user_name(wanted, name):
    assert usable_name(wanted) == name


def test_the_first_sign_in_makes_the_account_and_later_ones_find_it(accounts, clocked_index, clock):
    """An identity's account is made once, named after what the provider calls the
    person (unique without case); later sign-ins find it by (issuer, subject) and note
    when; the same subject of another issuer is someone else."""
    assert accounts.identity(ISSUER, "s1") is None
    clocked_index.add_user("Ann")
    ann = accounts.sign_up_identity(ISSUER, "s1", "ann", "ann@example.edu")
    assert ann.name == "ann-2"
    assert accounts.sign_up_identity(ISSUER, "s1", "whoever", "x@y.z").name == "ann-2"
    clock.now += 60
    assert accounts.identity(ISSUER, "s1") == ann
    [identity] = accounts.identities("ann-2")
    assert (identity.email, identity.last - identity.created) == ("ann@example.edu", 60)
    other = accounts.sign_up_identity("https://accounts.other.test", "s1", "ann", "")
    assert other.name == "ann-3"
    assert not accounts.has_password("ann-2")
    assert accounts.tokens("ann-2") == []


def test_an_identity_links_to_one_account_only(accounts, clocked_index):
    clocked_index.add_user("carol", token=False)
    clocked_index.add_user("dave", token=False)
    accounts.link_identity("carol", ISSUER, "s-carol", "carol@example.edu")
    accounts.link_identity("carol", ISSUER, "s-carol", "carol@example.edu")  # again: nothing
    assert accounts.identity(ISSUER, "s-carol").name == "carol"
    with pytest.raises(AccountError, match="signs in to another account"):
        accounts.link_identity("dave", ISSUER, "s-carol", "")
    with pytest.raises(RecordNotFound):
        accounts.link_identity("nobody", ISSUER, "s-x", "")
