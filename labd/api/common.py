"""What the API's routers share: the service, tokens, serving blobs."""

from __future__ import annotations

import logging
from collections.abc import Iterator
from typing import Annotated

from fastapi import Depends, Request
from fastapi.responses import StreamingResponse
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from labd.api.errors import Unauthorized
from labd.service import Service
from repository.index import User

log = logging.getLogger("labd.api")
bearer = HTTPBearer(auto_error=False, description="a token from `labd users add NAME`")


def _service(request: Request) -> Service:
    service: Service = request.app.state.service
    return service


Lab = Annotated[Service, Depends(_service)]


def _writer(
    service: Lab,
    credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)],
) -> User:
    if credentials is None:
        raise Unauthorized(
            "this needs a token: send Authorization: Bearer TOKEN "
            "(the operator makes one with `labd users add NAME`; "
            "labd commands take --token or LABD_TOKEN)",
        )
    user = service.index.user_by_token(credentials.credentials)
    if user is None:
        raise Unauthorized("the token is not valid here; ask the operator for a new one")
    return user


Writer = Annotated[User, Depends(_writer)]


def blob_response(
    service: Service, digest: str, media_type: str, filename: str | None
) -> StreamingResponse:
    """Stream a blob, checked against its digest first (a damaged one is never sent)."""
    store = service.store
    store.verify(digest)  # BlobNotFound: 404; BlobCorrupt: 500, logged (labd.api.errors)

    def chunks() -> Iterator[bytes]:
        yield from store.iter_chunks(digest)

    headers = {"ETag": f'"{digest}"', "Cache-Control": "public, max-age=31536000, immutable"}
    if filename:
        headers["Content-Disposition"] = f'attachment; filename="{filename}"'
    headers["Content-Length"] = str(store.size(digest))
    return StreamingResponse(chunks(), media_type=media_type, headers=headers)
