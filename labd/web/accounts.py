"""The pages of a person's account: signing up (when the operator allows it) and their
API tokens.

    GET  /signup                 the sign-up form (``labd serve --signup``), else a page
                                 saying who makes accounts here
    POST /signup                 a new account with a password; signed in at once
    GET  /tokens                 my API tokens: labels and dates, never the tokens
    POST /tokens                 a new token, shown on the page once
    POST /tokens/{id}/revoke     revoke one; it stops working at once
"""

from __future__ import annotations

import logging
from typing import Annotated, Any

from fastapi import APIRouter, Form, Request
from fastapi.responses import HTMLResponse, RedirectResponse
from pydantic import BaseModel

from labd.api.common import Lab
from labd.api.errors import TooMany
from labd.api.models import Id
from labd.api.throttle import Throttle
from labd.web.forms import local, signed_in
from labd.web.render import page
from labd.web.session import CsrfChecked, Viewer
from repository.errors import ArchiveError, RecordNotFound

router = APIRouter(include_in_schema=False)
log = logging.getLogger("labd.web")


def _closed(request: Request, viewer: Viewer) -> HTMLResponse:
    return page(
        request,
        "error.html",
        {
            "title": "Sign-up is closed here",
            "message": "The lab's operator makes the accounts of this lab"
            " (labd users add NAME --password): ask them for one.",
            "back": "/session",
            "back_text": "Sign in",
        },
        user=viewer,
        status_code=404,
    )


@router.get("/signup", response_class=HTMLResponse)
def signup_form(request: Request, service: Lab, viewer: Viewer, then: str = "/") -> HTMLResponse:
    if not service.config.signup:
        return _closed(request, viewer)
    context = {"then": local(then), "problem": None, "name": ""}
    return page(request, "signup.html", context, user=viewer)


class SignupForm(BaseModel):
    name: str = ""
    password: str = ""
    again: str = ""
    then: str = "/reservations"


@router.post("/signup", response_class=HTMLResponse, dependencies=[CsrfChecked])
def signup(
    request: Request, service: Lab, viewer: Viewer, sent: Annotated[SignupForm, Form()]
) -> Any:
    if not service.config.signup:
        return _closed(request, viewer)
    name, password, again, then = sent.name.strip(), sent.password, sent.again, sent.then
    address = request.client.host if request.client else "unknown"
    throttle: Throttle = request.app.state.throttle
    problem = None
    try:
        throttle.check("address", address, "sign-ups from your address")
        if password != again:
            problem = "the two passwords differ; type the same one twice"
        else:
            user = service.accounts.sign_up(name, password)
            log.info("%s signed up from %s", user.name, address)
            return signed_in(request, service, user, then)
    except TooMany as err:
        problem = err.message
    except ArchiveError as err:
        throttle.fail("address", address)  # many names tried from one address
        problem = str(err)
    context = {"then": local(then), "problem": problem, "name": name}
    return page(request, "signup.html", context, user=viewer, status_code=422)


def _tokens(
    request: Request,
    service: Lab,
    viewer: Viewer,
    *,
    new: str | None = None,
    problem: str | None = None,
    status: int = 200,
) -> Any:
    if viewer is None:
        return RedirectResponse("/session?then=/tokens", status_code=303)
    context = {"tokens": service.accounts.tokens(viewer.name), "new": new, "problem": problem}
    return page(request, "tokens.html", context, user=viewer, status_code=status)


@router.get("/tokens", response_class=HTMLResponse)
def tokens(request: Request, service: Lab, viewer: Viewer) -> Any:
    return _tokens(request, service, viewer)


@router.post("/tokens", response_class=HTMLResponse, dependencies=[CsrfChecked])
def new_token(
    request: Request, service: Lab, viewer: Viewer, label: Annotated[str, Form()] = ""
) -> Any:
    if viewer is None:
        return RedirectResponse("/session?then=/tokens", status_code=303)
    _, token = service.accounts.new_token(viewer.name, label)
    response = _tokens(request, service, viewer, new=token, status=201)
    response.headers["Cache-Control"] = "no-store"
    return response


@router.post("/tokens/{token_id}/revoke", dependencies=[CsrfChecked])
def revoke(request: Request, token_id: Id, service: Lab, viewer: Viewer) -> Any:
    if viewer is None:
        return RedirectResponse("/session?then=/tokens", status_code=303)
    try:
        service.accounts.revoke_token(viewer.name, token_id)
    except RecordNotFound:
        return _tokens(request, service, viewer, problem="you have no such token", status=404)
    return RedirectResponse("/tokens", status_code=303)
