"""One HTTP client for a lab's API, used by the ``labd`` commands and by remote workers.

It reads errors one way (the API answers ``{"error": "..."}`` with a 4xx or 5xx; a
proxy in between may answer anything), and it retries a connection that was refused
or could not be made, with a growing pause, since no request reached the lab then: a
lab restarting for a moment does not stop a worker or a waiting command. Any other
failure is reported at once.
"""

from __future__ import annotations

import hashlib
import logging
import time
from collections.abc import Callable, Mapping
from importlib import metadata
from pathlib import Path
from typing import Any, TypeVar

import httpx
from pydantic import BaseModel, ValidationError

from repository.masking import mask_url
from repository.units import MiB
from scheduler.errors import ApiRefused, LabUnreachable, RemoteError

log = logging.getLogger("scheduler.client")
DEFAULT_SERVER = "http://127.0.0.1:8080"
CHUNK = MiB
M = TypeVar("M", bound=BaseModel)


def version() -> str:
    """This labd's version, as installed."""
    try:
        return metadata.version("labd")
    except metadata.PackageNotFoundError:
        return "unknown"


class ApiClient:
    """A client of one lab's HTTP API; thread-safe (httpx.Client is)."""

    def __init__(
        self,
        server: str,
        token: str | None = None,
        *,
        timeout: float = 60.0,
        connect_attempts: int = 5,
        backoff: float = 0.25,
        headers: Mapping[str, str] | None = None,
        sleep: Callable[[float], None] = time.sleep,
        transport: httpx.BaseTransport | None = None,
    ) -> None:
        self.server = server.rstrip("/")
        sent = {"User-Agent": f"labd/{version()}", **(headers or {})}
        if token:
            sent["Authorization"] = f"Bearer {token}"
        self.http = httpx.Client(
            base_url=self.server, headers=sent, timeout=timeout, transport=transport
        )
        self.connect_attempts = max(1, connect_attempts)
        self.backoff = backoff
        self.sleep = sleep

    def close(self) -> None:
        self.http.close()

    def __enter__(self) -> ApiClient:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    # -- requests -------------------------------------------------------------------------

    def request(self, method: str, path: str, **kwargs: Any) -> httpx.Response:
        """Send a request; the response if its status is below 400 (else ApiRefused)."""
        response = self._send(lambda: self.http.request(method, path, **kwargs))
        if response.status_code >= 400:
            raise refusal(response)
        return response

    def get(self, path: str, model: type[M], **kwargs: Any) -> M:
        return self.parse(self.request("GET", path, **kwargs), model)

    def post(self, path: str, model: type[M], **kwargs: Any) -> M:
        return self.parse(self.request("POST", path, **kwargs), model)

    def parse(self, response: httpx.Response, model: type[M]) -> M:
        try:
            return model.model_validate_json(response.content)
        except ValidationError as err:
            raise RemoteError(
                f"the lab at {mask_url(self.server)} answered {response.request.url.path} with a"
                f" body this labd {version()} does not understand; are both the same version?"
                f" ({err.error_count()} problems, the first: {err.errors()[0]['msg']})"
            ) from None

    def _send(self, send: Callable[[], httpx.Response]) -> httpx.Response:
        pause = self.backoff
        for attempt in range(1, self.connect_attempts + 1):
            try:
                return send()
            except httpx.ConnectError as err:  # nothing reached the lab: safe to retry
                if attempt == self.connect_attempts:
                    raise LabUnreachable(self.server, str(err) or type(err).__name__) from None
                shown = mask_url(self.server)
                log.debug("cannot reach %s (%s); again in %.2f s", shown, err, pause)
                self.sleep(pause)
                pause *= 2
            except httpx.HTTPError as err:
                raise LabUnreachable(self.server, str(err) or type(err).__name__) from None
        raise AssertionError("unreachable")

    # -- files ----------------------------------------------------------------------------

    def download(self, path: str, dest: Path, *, digest: str | None = None) -> int:
        """Stream ``path`` into ``dest`` (via a ``.partial`` file); its size in bytes.

        With ``digest`` (``sha256:HEX``) the bytes must hash to it, or nothing is kept.
        """
        partial = dest.with_name(dest.name + ".partial")
        sha = hashlib.sha256()
        size = 0
        try:
            with self.http.stream("GET", path) as response:
                if response.status_code >= 400:
                    response.read()
                    raise refusal(response)
                with partial.open("wb") as out:
                    for chunk in response.iter_bytes(CHUNK):
                        sha.update(chunk)
                        out.write(chunk)
                        size += len(chunk)
            if digest is not None and f"sha256:{sha.hexdigest()}" != digest:
                raise RemoteError(f"{path}: the bytes received do not match {digest}")
            partial.rename(dest)
        except httpx.HTTPError as err:
            raise RemoteError(
                f"the download of {path} from {mask_url(self.server)} broke off: {err}"
            ) from None
        finally:
            partial.unlink(missing_ok=True)
        return size

    def upload(self, path: Path) -> str:
        """PUT a file to ``/api/blobs/sha256:HEX``; its digest."""
        sha = hashlib.sha256()
        with path.open("rb") as stream:
            while chunk := stream.read(CHUNK):
                sha.update(chunk)
        digest = f"sha256:{sha.hexdigest()}"

        def send() -> httpx.Response:
            with path.open("rb") as stream:
                return self.http.put(
                    f"/api/blobs/{digest}",
                    content=stream,
                    headers={"Content-Type": "application/octet-stream"},
                )

        response = self._send(send)
        if response.status_code >= 400:
            raise refusal(response)
        return digest


def refusal(response: httpx.Response) -> ApiRefused:
    """The error a lab (or whatever answered in its place) sent, as one exception."""
    text = ""
    try:
        body = response.json()
        if isinstance(body, dict):
            text = str(body.get("error") or body.get("detail") or "")
    except ValueError:
        pass
    if not text:
        text = response.text.strip()[:300] or response.reason_phrase
    return ApiRefused(
        response.status_code, text, response.request.method, response.request.url.path
    )
