"""What the API's routers share: errors, the service, tokens, serving blobs."""

from __future__ import annotations

import logging
from collections.abc import Iterator
from typing import Annotated

from fastapi import Depends, Request
from fastapi.responses import StreamingResponse
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from labd.service import Service
from repository.errors import BlobError, BlobNotFound
from repository.index import User

log = logging.getLogger("labd.api")
bearer = HTTPBearer(auto_error=False, description="a token from `labd users add NAME`")


class ApiError(Exception):
    def __init__(self, status: int, message: str) -> None:
        self.status = status
        self.message = message
        super().__init__(message)


def _service(request: Request) -> Service:
    service: Service = request.app.state.service
    return service


Lab = Annotated[Service, Depends(_service)]


def _writer(
    service: Lab,
    credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)],
) -> User:
    if credentials is None:
        raise ApiError(
            401,
            "this needs a token: send Authorization: Bearer TOKEN "
            "(the operator makes one with `labd users add NAME`; "
            "labd commands take --token or LABD_TOKEN)",
        )
    user = service.index.user_by_token(credentials.credentials)
    if user is None:
        raise ApiError(401, "the token is not valid here; ask the operator for a new one")
    return user


Writer = Annotated[User, Depends(_writer)]


def blob_response(
    service: Service, digest: str, media_type: str, filename: str | None
) -> StreamingResponse:
    store = service.store
    try:
        store.verify(digest)
    except BlobError as err:
        log.error("%s", err)
        status = 404 if isinstance(err, BlobNotFound) else 500  # 500: the store is damaged
        raise ApiError(status, str(err)) from None

    def chunks() -> Iterator[bytes]:
        yield from store.iter_chunks(digest)

    headers = {"ETag": f'"{digest}"', "Cache-Control": "public, max-age=31536000, immutable"}
    if filename:
        headers["Content-Disposition"] = f'attachment; filename="{filename}"'
    headers["Content-Length"] = str(store.size(digest))
    return StreamingResponse(chunks(), media_type=media_type, headers=headers)
