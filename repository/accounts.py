"""People's accounts on the index: passwords, API tokens, browser sessions.

A user (``repository.index.users``) signs in on the pages with a password, kept as an
argon2id hash (argon2-cffi, its recommended parameters; an older hash is re-hashed at
the next sign-in). A signed-in browser holds a random session id in a cookie; only its
sha256 is kept here, with the session's CSRF token (the one its forms carry) and when it
expires. Scripts use API tokens: a user has any number, each with a label, and lists and
revokes their own; the operator revokes or rotates anyone's (``labd users``).

Revoking a user (every token) also ends their browser sessions and re-keys their booked
slots, so no key they held opens a robot any more. A new password (their own change, or
the operator's reset) ends every other browser session of theirs: whoever signed in
with the old one is signed out. API tokens survive a new password: they are revoked on
their own (the tokens page, ``labd users revoke``).

A person may also sign in through an OpenID provider (``labd.web.oidc``): the provider
vouches for them by its issuer and a subject of its own, and that pair (an *identity*)
names their account, never the e-mail (an address may be given to someone else). The
first sign-in makes the account, named after what the provider calls them, made unique;
a person signed in with a password may link an identity to their account.

Nothing here can tell a token or a session id back: only hashes are stored.
"""

from __future__ import annotations

import hmac
import logging
import re
import secrets
from dataclasses import dataclass

import sqlalchemy as sa
from argon2 import PasswordHasher
from argon2.exceptions import InvalidHashError, VerificationError
from sqlalchemy.engine import Connection

from repository.errors import AccountError, BadCredentials, RecordNotFound
from repository.index import USER_LIMITS, Index, User, check_name, lock_users, token_hash
from repository.reservations import rekey
from repository.tables import identities, passwords, tokens, users, web_sessions

log = logging.getLogger("repository.accounts")
MIN_PASSWORD = 10
MAX_PASSWORD = 1024
SESSION_AGE = 14 * 24 * 3600.0  # seconds a browser stays signed in


@dataclass(frozen=True)
class Token:
    """An API token as its owner sees it listed: never the token itself."""

    id: int
    user: str
    label: str
    created: float
    revoked: float | None


@dataclass(frozen=True)
class Identity:
    """An OpenID provider's person, and the account they sign in to."""

    issuer: str
    subject: str
    user: str
    email: str
    created: float
    last: float


@dataclass(frozen=True)
class WebSession:
    """A signed-in browser: whose it is, the CSRF token its forms carry, its end."""

    user: User
    csrf: str
    expires: float


class Accounts:
    """Passwords, tokens and sessions of the users on ``index``."""

    def __init__(
        self,
        index: Index,
        *,
        hasher: PasswordHasher | None = None,
        session_age: float = SESSION_AGE,
    ) -> None:
        self.index = index
        self.hasher = hasher or PasswordHasher()
        self.session_age = session_age
        # Checked against when the user does not exist, so that a wrong name takes as
        # long as a wrong password (no way to find out who has an account).
        self._decoy = self.hasher.hash(secrets.token_urlsafe(16))

    # -- passwords ----------------------------------------------------------------------

    def sign_up(self, name: str, password: str) -> User:
        """A new user with a password and no token yet (they make their own)."""
        check_password(password)
        self.index.add_user(name, token=False)
        self.set_password(name, password)
        return self.index.user(name)

    def set_password(self, name: str, password: str, *, keep: str | None = None) -> int:
        """Set ``name``'s password (the operator's reset, or their own change) and end
        their browser sessions but the one whose cookie is ``keep``; how many ended."""
        check_password(password)
        self.index.user(name)  # RecordNotFound if there is no such user
        digest = self.hasher.hash(password)
        with self.index.begin() as db:
            self._store(db, name, digest)
            ended = sa.delete(web_sessions).where(web_sessions.c.user == name)
            if keep is not None:
                ended = ended.where(web_sessions.c.sha256 != token_hash(keep))
            count = int(db.execute(ended).rowcount)
        log.info("user %s: password set; %d other sessions ended", name, count)
        return count

    def change_password(self, name: str, current: str, new: str, *, keep: str | None) -> int:
        """``name`` changes their own password, proving the current one (BadCredentials
        if wrong); their other sessions end (``set_password``)."""
        self.check_password(name, current)
        return self.set_password(name, new, keep=keep)

    def _store(self, db: Connection, name: str, digest: str) -> None:
        db.execute(sa.delete(passwords).where(passwords.c.user == name))
        db.execute(sa.insert(passwords).values(user=name, hash=digest, changed=self.index.clock()))

    def check_password(self, name: str, password: str) -> User:
        """The user, if the password is theirs (else BadCredentials, for either mistake)."""
        with self.index.engine.connect() as db:
            stored = db.execute(
                sa.select(passwords.c.hash).where(passwords.c.user == name)
            ).scalar()
        try:
            self.hasher.verify(stored or self._decoy, password)
        except (VerificationError, InvalidHashError):
            raise BadCredentials() from None
        if stored is None:
            raise BadCredentials()
        if self.hasher.check_needs_rehash(stored):  # the same password: sessions stay
            with self.index.begin() as db:
                self._store(db, name, self.hasher.hash(password))
        return self.index.user(name)

    def has_password(self, name: str) -> bool:
        with self.index.engine.connect() as db:
            found = db.execute(sa.select(passwords.c.user).where(passwords.c.user == name))
            return found.first() is not None

    # -- tokens -------------------------------------------------------------------------

    def new_token(self, name: str, label: str) -> tuple[Token, str]:
        """A new API token for ``name``: its listing and the token (shown once)."""
        label = " ".join(label.split())[:128] or "unnamed"
        self.index.user(name)
        secret = "labd_" + secrets.token_urlsafe(24)
        now = self.index.clock()
        with self.index.begin() as db:
            result = db.execute(
                sa.insert(tokens).values(
                    user=name, sha256=token_hash(secret), label=label, created=now
                )
            )
            key = result.inserted_primary_key
            assert key is not None
        log.info("user %s made token %d (%s)", name, key[0], label)
        return Token(int(key[0]), name, label, now, None), secret

    def tokens(self, name: str) -> list[Token]:
        """``name``'s tokens, newest first, revoked ones too (with when)."""
        with self.index.engine.connect() as db:
            rows = db.execute(
                sa.select(tokens).where(tokens.c.user == name).order_by(tokens.c.id.desc())
            ).all()
        return [Token(r.id, r.user, r.label, r.created, r.revoked) for r in rows]

    def revoke_token(self, name: str, token_id: int) -> Token:
        """Revoke one of ``name``'s tokens (RecordNotFound if it is not theirs)."""
        now = self.index.clock()
        with self.index.begin() as db:
            row = db.execute(
                sa.select(tokens).where(tokens.c.id == token_id, tokens.c.user == name)
            ).first()
            if row is None:
                raise RecordNotFound(f"token of {name}", str(token_id))
            if row.revoked is None:
                db.execute(sa.update(tokens).where(tokens.c.id == token_id).values(revoked=now))
        log.info("user %s: token %d revoked", name, token_id)
        return Token(row.id, row.user, row.label, row.created, row.revoked or now)

    def revoke_all(self, name: str) -> int:
        """Revoke every token of ``name``, end their browser sessions and re-key their
        booked slots (the keys they hold open nothing); how many tokens."""
        self.index.user(name)
        now = self.index.clock()
        with self.index.begin() as db:
            count = db.execute(
                sa.update(tokens)
                .where(tokens.c.user == name, tokens.c.revoked.is_(None))
                .values(revoked=now)
            ).rowcount
            # an older labd's token, kept only in users: replaced by one nobody holds
            db.execute(
                sa.update(users)
                .where(users.c.name == name)
                .values(token_sha256=token_hash(secrets.token_urlsafe(24)))
            )
            db.execute(sa.delete(web_sessions).where(web_sessions.c.user == name))
            slots = rekey(db, name, now)
        log.warning(
            "user %s: every token revoked (%d), sessions ended, keys of %d slots replaced",
            name,
            count,
            slots,
        )
        return int(count)

    def rotate(self, name: str) -> str:
        """Revoke every token of ``name`` and give them one new token (returned)."""
        self.revoke_all(name)
        _, secret = self.new_token(name, "rotated by the operator (labd users rotate)")
        return secret

    # -- browser sessions ---------------------------------------------------------------

    def open_session(self, user: User) -> tuple[str, WebSession]:
        """Sign ``user`` in: the cookie's value (kept only as a hash) and the session."""
        cookie = secrets.token_urlsafe(32)
        now = self.index.clock()
        session = WebSession(user, secrets.token_urlsafe(24), now + self.session_age)
        with self.index.begin() as db:
            db.execute(sa.delete(web_sessions).where(web_sessions.c.expires < now))
            db.execute(
                sa.insert(web_sessions).values(
                    sha256=token_hash(cookie),
                    user=user.name,
                    csrf=session.csrf,
                    created=now,
                    expires=session.expires,
                )
            )
        return cookie, session

    def session(self, cookie: str) -> WebSession | None:
        """The live session a cookie names; None if unknown, ended or expired."""
        with self.index.engine.connect() as db:
            row = db.execute(
                sa.select(web_sessions).where(web_sessions.c.sha256 == token_hash(cookie))
            ).first()
        if row is None or row.expires <= self.index.clock():
            return None
        try:
            user = self.index.user(row.user)
        except RecordNotFound:
            return None
        return WebSession(user, row.csrf, row.expires)

    def end_session(self, cookie: str) -> None:
        with self.index.begin() as db:
            db.execute(sa.delete(web_sessions).where(web_sessions.c.sha256 == token_hash(cookie)))

    # -- identities from OpenID providers ------------------------------------------------

    def identity(self, issuer: str, subject: str) -> User | None:
        """The account ``subject`` of ``issuer`` signs in to, noting the sign-in; None
        if it has none yet."""
        with self.index.begin() as db:
            row = db.execute(
                sa.select(identities.c.user).where(
                    identities.c.issuer == issuer, identities.c.subject == subject
                )
            ).first()
            if row is None:
                return None
            db.execute(
                sa.update(identities)
                .where(identities.c.issuer == issuer, identities.c.subject == subject)
                .values(last=self.index.clock())
            )
        return self.index.user(row.user)

    def sign_up_identity(self, issuer: str, subject: str, wanted: str, email: str) -> User:
        """A new account for a person ``issuer`` vouches for as ``subject``: named
        ``wanted`` made a valid name and unique (``ann``, else ``ann-2``...), with no
        password and no token yet. If a sign-in at the same moment made it first, that
        account."""
        now = self.index.clock()
        base = usable_name(wanted)
        with self.index.begin() as db:
            lock_users(db)
            found = db.execute(
                sa.select(identities.c.user).where(
                    identities.c.issuer == issuer, identities.c.subject == subject
                )
            ).scalar()
            if found is not None:
                return self.index.user(found)
            taken = {
                n.lower()
                for n in db.execute(
                    sa.select(users.c.name).where(
                        sa.func.lower(users.c.name).like(base.lower()[:60] + "%")
                    )
                ).scalars()
            }
            name = next(
                candidate
                for n in range(1, len(taken) + 2)
                if (candidate := base if n == 1 else f"{base[:60]}-{n}").lower() not in taken
            )
            check_name(name)
            db.execute(
                sa.insert(users).values(
                    name=name,
                    token_sha256=token_hash(secrets.token_urlsafe(24)),  # nobody holds it
                    created=now,
                    max_running=USER_LIMITS.max_running,
                    max_daily=USER_LIMITS.max_daily,
                    worker=False,
                )
            )
            self._add_identity(db, issuer, subject, name=name, email=email, now=now)
        log.info("user %s signed up through %s (subject %s)", name, issuer, subject)
        return self.index.user(name)

    def link_identity(self, name: str, issuer: str, subject: str, email: str) -> None:
        """Let ``subject`` of ``issuer`` sign in to ``name``'s account (AccountError if
        it signs in to another one already)."""
        self.index.user(name)
        with self.index.begin() as db:
            owner = db.execute(
                sa.select(identities.c.user).where(
                    identities.c.issuer == issuer, identities.c.subject == subject
                )
            ).scalar()
            if owner == name:
                return
            if owner is not None:
                raise AccountError(
                    f"that {issuer} account signs in to another account of this lab already"
                )
            self._add_identity(db, issuer, subject, name=name, email=email, now=self.index.clock())
        log.info("user %s linked their account to %s (subject %s)", name, issuer, subject)

    def identities(self, name: str) -> list[Identity]:
        """The providers' people who sign in to ``name``'s account, oldest first."""
        with self.index.engine.connect() as db:
            rows = db.execute(
                sa.select(identities)
                .where(identities.c.user == name)
                .order_by(identities.c.created)
            ).all()
        return [Identity(r.issuer, r.subject, r.user, r.email, r.created, r.last) for r in rows]

    @staticmethod
    def _add_identity(
        db: Connection, issuer: str, subject: str, *, name: str, email: str, now: float
    ) -> None:
        db.execute(
            sa.insert(identities).values(
                issuer=issuer, subject=subject, user=name, email=email, created=now, last=now
            )
        )


_UNUSABLE = re.compile(r"[^A-Za-z0-9._-]+")


def usable_name(wanted: str) -> str:
    """``wanted`` (a provider's ``preferred_username``, or an e-mail's local part) as a
    user name the lab accepts: ASCII letters, digits, '.', '-' and '_', starting with a
    letter or digit, at most 64; ``user`` when nothing is left."""
    name = _UNUSABLE.sub("", wanted).lstrip("._-")[:64].rstrip("._-")
    return name or "user"


def check_password(password: str) -> None:
    """A password the lab accepts (AccountError saying what is needed if not)."""
    if len(password) < MIN_PASSWORD:
        raise AccountError(f"the password is too short: use at least {MIN_PASSWORD} characters")
    if len(password) > MAX_PASSWORD:
        raise AccountError(f"the password is too long: use at most {MAX_PASSWORD} characters")


def same(a: str, b: str) -> bool:
    """Compare two secrets in constant time."""
    return hmac.compare_digest(a.encode(), b.encode())
