"""Secrets kept out of what the lab prints: settings, log lines and error messages.

An operator's settings hold credentials in more places than the ones named after them:
a database URL's password (``postgresql://lab:PW@db/lab``), a query value
(``https://auth.example.org/check?token=T``, ``?password=``, a signed URL's
``X-Amz-Signature``), an object store's option (``endpoint_url=http://user:PW@host``,
``key=``, ``secret=``). Whatever prints one of them (``labd config show``, a log line, an
error a person reads) prints it through this module, so there is one rule:

- ``mask_url``: a URL's password, every query value and every fragment value become
  ``***``; over http(s) and ws(s) a user name without a password is hidden too (a token
  travels there as the user name). Scheme, host, port and path stay: they say where.
- ``mask_option``: the value of a ``NAME=VALUE`` option is masked whole when its name
  suggests a secret (``SECRET_NAMES``), masked as a URL when it is one, else kept.
- ``mask_text``: every URL inside a free text (git's own words, an exception's) masked.

Masking errs on the side of hiding: a value that looks like a secret and is not one
costs a reader a little; the other way round costs the lab its credentials.

``repository`` imports no other package of ours, so ``scheduler`` and ``labd`` take this
from here (as they take ``units``).
"""

from __future__ import annotations

import re

MASK = "***"
# Parts of an option's name that say its value may be a credential (matched in lower case).
SECRET_NAMES = (
    "key",
    "secret",
    "token",
    "pass",  # password, passwd, passphrase
    "pwd",
    "credential",
    "auth",
    "session",
    "cookie",
    "signature",
    "private",
)
SCHEME = re.compile(r"^([A-Za-z][A-Za-z0-9+.-]*)://")
# A URL inside a free text: a scheme, then anything up to white space or a quote.
IN_TEXT = re.compile(r"[A-Za-z][A-Za-z0-9+.-]*://[^\s'\"<>`]+")
# Schemes whose user name, alone, may be a token (GitHub takes one as the user name).
USER_IS_SECRET = frozenset({"http", "https", "ws", "wss"})


def secret_name(name: str) -> bool:
    """Whether an option named ``name`` may hold a credential (``aws_secret_access_key``,
    ``api_key``, ``password``...)."""
    lowered = name.lower()
    return any(word in lowered for word in SECRET_NAMES)


def mask_url(text: str) -> str:
    """``text`` with its password, query values and fragment values masked, when it is a
    URL (``scheme://...``); any other text as it is."""
    match = SCHEME.match(text)
    if match is None:
        return text
    scheme = match.group(1).lower()
    user, rest = _split_user(text[match.end() :])
    rest, hash_, fragment = rest.partition("#")
    rest, question, query = rest.partition("?")
    if question:
        rest += "?" + _mask_pairs(query)
    if hash_:
        rest += "#" + _mask_pairs(fragment)
    if user is not None:
        name, colon, _ = user.partition(":")
        if colon:
            user = f"{name}:{MASK}"
        elif scheme in USER_IS_SECRET:
            user = MASK
        rest = f"{user}@{rest}"
    return text[: match.end()] + rest


def mask_option(name: str, value: str) -> str:
    """The value of the option ``name=value`` as it may be shown: masked whole when the
    name suggests a secret, masked as a URL when it is one."""
    if secret_name(name):
        return MASK
    return mask_url(value)


def mask_text(text: str) -> str:
    """``text`` with every URL in it masked (``mask_url``)."""
    return IN_TEXT.sub(lambda found: mask_url(found.group(0)), text)


def _split_user(rest: str) -> tuple[str | None, str]:
    """A URL's user part (None without one) and what follows its ``@``; ``rest`` is the
    URL after ``scheme://``."""
    end = min((i for i in map(rest.find, "/?#") if i >= 0), default=len(rest))
    authority = rest[:end]
    if "@" in authority:  # the last "@" before the path: a password may hold an "@"
        user, _, host = authority.rpartition("@")
        return user, host + rest[end:]
    # A password may hold "/", "?" or "#" as it is (SQLAlchemy takes such URLs): a colon
    # followed by what is no port, and an "@" further on, is a user and a password.
    _, colon, after = authority.partition(":")
    if colon and after and not after.isdigit() and not authority.startswith("[") and "@" in rest:
        user, _, host = rest.partition("@")
        return user, host
    return None, rest


def _mask_pairs(query: str) -> str:
    """A query (or fragment) with each value masked: ``a=1&b`` → ``a=***&***``."""
    if not query:
        return query
    parts = re.split(r"([&;])", query)
    out = []
    for part in parts:
        if part in ("&", ";") or not part:
            out.append(part)
            continue
        name, equals, _ = part.partition("=")
        out.append(f"{name}={MASK}" if equals else MASK)
    return "".join(out)
