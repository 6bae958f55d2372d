"""How the pages answer an error: the API's table (``labd.api.errors``), as a page.

A page's handler, and its dependencies, raise what went wrong, as the API's do: the
route (``PageRoute``) answers an expected error with the page ``error.html``, under the
status, words and headers the API gives the same exception, and a redirect (a 3xx,
such as ``SignInFirst``) as a redirect. A bug is not an expected error: it goes on to
the table's 500, logged with its traceback.

A form that shows its refusals on itself, with what was typed kept (signing in with a
wrong password, a booking that clashes), says so with ``on_form``: an expected error
raised inside it is the form again, with the problem and the table's status.
"""

from __future__ import annotations

from collections.abc import Callable, Coroutine, Iterator
from contextlib import contextmanager
from typing import Any
from urllib.parse import urlsplit

from fastapi import Request
from fastapi.exceptions import RequestValidationError
from fastapi.routing import APIRoute
from starlette.responses import Response

from labd.api import errors
from labd.api.errors import ApiError, Problem
from labd.web.render import page
from repository.errors import RecordNotFound

# The heading of an error's page, by status, unless the error has its own.
TITLES = {
    400: "Not understood",
    401: "Not signed in",
    403: "Not allowed",
    404: "Not found",
    409: "Taken already",
    413: "Too large",
    422: "Not accepted",
    429: "Too many, too often",
    500: "The lab failed",
    503: "Not now",
    507: "The lab's storage is full",
}


class Shown(Exception):
    """A refusal shown on its form (``on_form``): ``response`` is the form again."""

    def __init__(self, response: Response) -> None:
        self.response = response
        super().__init__("shown on its form")


@contextmanager
def on_form(request: Request, show: Callable[[str, int], Response]) -> Iterator[None]:
    """Show an expected refusal of ``request`` raised inside on the form it came from:
    ``show(problem, status)`` renders the form again, with what was typed; the status
    and headers are those the API gives the same error. A refusal is a 4xx, or a 503
    (the lab cannot take it now: try again later); a redirect, any other fault of the
    lab or a bug goes on to the error page or the table's 500."""
    try:
        yield
    except Exception as err:
        if not errors.expected(err):
            raise
        said = errors.problem(err, request.method, request.url.path)
        if not (400 <= said.status < 500 or said.status == 503):
            raise
        errors.told(err, said, request.method, request.url.path)
        response = show(said.message, said.status)
        response.headers.update(said.headers)
        raise Shown(response) from err


class PageRoute(APIRoute):
    """A page's route: an expected error raised by its handler or its dependencies is
    answered as a page (module docstring), a refusal shown on its form is that form."""

    def get_route_handler(self) -> Callable[[Request], Coroutine[Any, Any, Response]]:
        handle = super().get_route_handler()

        async def page_handler(request: Request) -> Response:
            try:
                return await handle(request)
            except Shown as shown:
                return shown.response
            except Exception as err:
                if not errors.expected(err):
                    raise
                said = errors.problem(err, request.method, request.url.path)
                if _unnamable(err):  # /trials/abc: no page is at such a URL
                    said = Problem(404, f"no such page: {request.url.path}")
                errors.told(err, said, request.method, request.url.path)
                return error_page(request, err, said)

        return page_handler


def _unnamable(err: Exception) -> bool:
    """Whether ``err`` refuses only the URL's own path (a trial id that is no number)."""
    if not isinstance(err, RequestValidationError):
        return False
    return all(tuple(p.get("loc", ()))[:1] == ("path",) for p in err.errors())


def error_page(request: Request, err: Exception, said: Problem) -> Response:
    """The page of an expected error (a redirect for a 3xx), with a way back to the
    page the person came from, when it is one of the lab's."""
    if 300 <= said.status < 400:
        return Response(status_code=said.status, headers=said.headers)
    if isinstance(err, ApiError) and err.title:
        title = err.title
    elif isinstance(err, RecordNotFound):
        title = f"No {err.kind} {err.name}"
    else:
        title = TITLES.get(said.status, "Refused")
    context = {"title": title, "message": said.message}
    back = _came_from(request)
    if back is not None:
        context.update(back=back, back_text="Back to where you were")
    response = page(
        request,
        "error.html",
        context,
        user=getattr(request.state, "viewer", None),  # when the page got as far as asking
        status_code=said.status,
    )
    response.headers.update(said.headers)
    return response


def _came_from(request: Request) -> str | None:
    """The lab's page that sent the person here (its ``Referer``), if there was one
    other than the page that failed."""
    referer = urlsplit(request.headers.get("referer", ""))
    if (referer.scheme, referer.netloc) != (request.url.scheme, request.url.netloc):
        return None
    back = referer.path + (f"?{referer.query}" if referer.query else "")
    here = request.url.path + (f"?{request.url.query}" if request.url.query else "")
    if not back.startswith("/") or (request.method == "GET" and back == here):
        return None
    return back
