"""Key authorization: how long may the holder of a key stay connected?

The seam is ``Authorizer``: given a key, the number of seconds it may stay, or
``AuthError`` saying why not. ``HttpAuthorizer`` asks an HTTP(S) URL, as the rosjs
paper's labs did: ``GET URL?key=KEY`` answers JSON ``{"seconds": N}``, a bare number,
or JSONP (``callback({"seconds": N})``) for the paper's authorizers. The lab's own
reservations will answer the same way under ``/api/auth``.
"""

from __future__ import annotations

import re
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


class Authorizer(Protocol):
    async def authorize(self, key: str) -> float:
        """Seconds the key may stay connected (> 0), or AuthError."""
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

    async def authorize(self, key: str) -> float:
        try:
            response = await self._client.get(self.url, params={"key": key})
        except httpx.HTTPError as err:
            raise AuthError(f"the authorizer could not be reached ({type(err).__name__})") from None
        if response.status_code in (401, 403, 404):
            raise AuthError("the key is not known")
        if response.status_code != 200:
            raise AuthError(f"the authorizer answered HTTP {response.status_code}")
        return parse_answer(response.text)

    async def aclose(self) -> None:
        await self._client.aclose()
