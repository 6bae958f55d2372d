"""A worker on another machine: the queue and the blob store through a lab's HTTP API.

``labd worker --server URL --token TOKEN`` runs the same ``Worker`` as ``labd serve``
does, with these two in place of the database and the store. The token must be a
worker's (``labd users add NAME --worker``). The worker fetches repositories itself,
with its own mirror cache and its own credentials; what it uploads is checked against
its digest by the server before it is stored.
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

import httpx

from scheduler.errors import RemoteError
from scheduler.queue import Claim

CHUNK = 1 << 20


class RemoteLab:
    """``Jobs`` and ``Blobs`` over a lab's HTTP API (thread-safe: httpx.Client is)."""

    def __init__(self, server: str, token: str, *, timeout: float = 60.0) -> None:
        self.server = server.rstrip("/")
        self.http = httpx.Client(
            base_url=self.server,
            headers={"Authorization": f"Bearer {token}"},
            timeout=timeout,
        )

    def close(self) -> None:
        self.http.close()

    def _call(self, method: str, path: str, **kwargs: Any) -> httpx.Response:
        try:
            response = self.http.request(method, path, **kwargs)
        except httpx.HTTPError as err:
            raise RemoteError(f"cannot reach the lab at {self.server}: {err}") from None
        if response.status_code >= 400:
            try:
                message = response.json().get("error", response.text)
            except ValueError:
                message = response.text
            raise RemoteError(f"{method} {path}: {message} (HTTP {response.status_code})")
        return response

    # -- Jobs -------------------------------------------------------------------------

    def claim(self, worker: str) -> Claim | None:
        response = self._call("POST", "/api/workers/claim", json={"worker": worker})
        if response.status_code == 204:
            return None
        return Claim(**response.json())

    def heartbeat(self, trial_id: int, worker: str) -> bool:
        path = f"/api/workers/trials/{trial_id}/heartbeat"
        return bool(self._call("POST", path, json={"worker": worker}).json()["keep"])

    def finish(self, trial_id: int, worker: str, **record: Any) -> bool:
        path = f"/api/workers/trials/{trial_id}/finish"
        reply = self._call("POST", path, json={"worker": worker, "record": record})
        return bool(reply.json()["filed"])

    def trial(self, trial_id: int) -> dict[str, Any]:
        reply: dict[str, Any] = self._call("GET", f"/api/trials/{trial_id}").json()
        mcap = reply.get("mcap")
        reply["mcap"] = mcap["digest"] if mcap else None  # as the index keeps it
        return reply

    # -- Blobs ------------------------------------------------------------------------

    def put_file(self, path: str | Path) -> str:
        sha = hashlib.sha256()
        with Path(path).open("rb") as stream:
            while chunk := stream.read(CHUNK):
                sha.update(chunk)
        digest = f"sha256:{sha.hexdigest()}"
        with Path(path).open("rb") as stream:
            self._call(
                "PUT",
                f"/api/blobs/{digest}",
                content=stream,
                headers={"Content-Type": "application/octet-stream"},
            )
        return digest

    def copy_to(self, digest: str, dest: str | Path) -> Path:
        dest = Path(dest)
        partial = dest.with_name(dest.name + ".partial")
        sha = hashlib.sha256()
        try:
            with self.http.stream("GET", f"/api/blobs/{digest}") as response:
                if response.status_code >= 400:
                    response.read()
                    raise RemoteError(f"blob {digest}: HTTP {response.status_code}")
                with partial.open("wb") as out:
                    for chunk in response.iter_bytes(CHUNK):
                        sha.update(chunk)
                        out.write(chunk)
            if f"sha256:{sha.hexdigest()}" != digest:
                raise RemoteError(f"blob {digest}: the bytes received do not match it")
            partial.rename(dest)
        except httpx.HTTPError as err:
            raise RemoteError(f"blob {digest}: {err}") from None
        finally:
            partial.unlink(missing_ok=True)
        return dest
