"""The pages' static files, sent gzip'd where ``web/build.mjs`` made a gzip'd twin.

``NAME.js.gz`` beside ``NAME.js`` holds the same bytes compressed: a browser that accepts
gzip gets it with ``Content-Encoding: gzip`` (as nginx's ``gzip_static`` does), others
get the plain file. Nothing is compressed while serving.
"""

from __future__ import annotations

from pathlib import Path

from starlette.datastructures import Headers
from starlette.responses import FileResponse, Response
from starlette.staticfiles import StaticFiles
from starlette.types import Scope


class Precompressed(StaticFiles):
    """``StaticFiles`` that prefers a file's ``.gz`` twin for browsers that take gzip."""

    async def get_response(self, path: str, scope: Scope) -> Response:
        response = await super().get_response(path, scope)
        if response.status_code != 200 or not isinstance(response, FileResponse):
            return response
        if "gzip" not in Headers(scope=scope).get("accept-encoding", ""):
            return response
        twin = Path(f"{response.path}.gz")
        if not twin.is_file():
            return response
        return FileResponse(
            twin,
            media_type=response.media_type,
            headers={"Content-Encoding": "gzip", "Vary": "Accept-Encoding"},
        )
