"""Key authorization: how long may the holder of a key stay connected?

The seam is ``Authorizer``: given a key and the robot (graph) it is presented to, a
``Grant`` (the seconds it may stay, and, when the authorizer knows, whose key it is), or
``AuthError`` saying why not. ``HttpAuthorizer`` asks an HTTP(S) URL, as the rosjs
paper's labs did: ``GET URL?key=KEY&robot=NAME`` answers JSON ``{"seconds": N}``, a
bare number, or JSONP (``callback({"seconds": N})``) for the paper's authorizers. The
lab's own reservations answer the same way under ``/api/auth``, and in process through
``labd.authorizer``.

Each graph of a bridge has a ``KeyPolicy``: no key needed; a key required (the first
frame, or ``?key=`` in the URL); or a key optional (anyone may connect and watch, a key
makes the client someone: a robot lets only such clients drive it).
"""

from __future__ import annotations

import enum
import re
from dataclasses import dataclass
from typing import Any, Protocol

import httpx
import orjson

from labd.errors import BridgeError

_JSONP = re.compile(r"^\s*[A-Za-z_$][\w$.]*\s*\((.*)\)\s*;?\s*$", re.DOTALL)


class AuthError(BridgeError):
    """The key was refused, or could not be checked."""

    def __init__(self, reason: str) -> None:
        self.reason = reason
        super().__init__(reason)


class AuthUnavailable(AuthError):
    """The key could not be checked (the authorizer is away or broken): a new client is
    refused, a connected one keeps the time it was granted."""


class KeyPolicy(enum.Enum):
    NONE = "none"  # no key is asked for
    REQUIRED = "required"  # the first frame (or the URL) must carry a valid key
    OPTIONAL = "optional"  # anyone may connect; a valid key makes the client someone


@dataclass(frozen=True)
class Grant:
    """What an authorizer says of a key it accepts."""

    seconds: float  # how long the key may stay connected
    user: str | None = None  # whose key it is, when the authorizer knows
    ref: str | None = None  # what it opens (``reservation:12``), to find it again later


class Authorizer(Protocol):
    async def authorize(self, key: str, graph: str) -> Grant:
        """What ``key`` may do on the graph named ``graph`` (seconds > 0), or AuthError."""
        ...


def parse_answer(text: str) -> float:
    """Seconds from an authorizer's answer (JSON object, number, or JSONP)."""
    match = _JSONP.match(text)
    body = match.group(1) if match else text
    try:
        value: Any = orjson.loads(body)
    except orjson.JSONDecodeError:
        raise AuthError("the authorizer's answer is not JSON") from None
    if isinstance(value, dict):
        value = value.get("seconds")
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise AuthError("the authorizer's answer has no number of seconds")
    if value <= 0:
        raise AuthError("the key is not valid now")
    return float(value)


class HttpAuthorizer:
    """Asks an HTTP(S) authorizer URL about each key."""

    def __init__(
        self,
        url: str,
        *,
        timeout: float = 5.0,
        verify: bool | str = True,
        transport: httpx.AsyncBaseTransport | None = None,
    ) -> None:
        self.url = url
        self._client = httpx.AsyncClient(
            timeout=timeout, verify=verify, transport=transport, follow_redirects=False
        )

    async def authorize(self, key: str, graph: str) -> Grant:
        try:
            response = await self._client.get(self.url, params={"key": key, "robot": graph})
        except httpx.HTTPError as err:
            raise AuthUnavailable(
                f"the authorizer could not be reached ({type(err).__name__})"
            ) from None
        if response.status_code in (401, 403, 404):
            raise AuthError("the key is not known")
        if response.status_code != 200:
            raise AuthUnavailable(f"the authorizer answered HTTP {response.status_code}")
        return Grant(parse_answer(response.text))

    async def aclose(self) -> None:
        await self._client.aclose()
