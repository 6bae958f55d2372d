"""The pages of a person's account: signing up (when the operator allows it), their
password and their API tokens.

    GET  /signup                 the sign-up form (``labd serve --signup``), else a page
                                 saying who makes accounts here
    POST /signup                 a new account with a password; signed in at once
    GET  /password               the form to change my password
    POST /password               change it (the current one, the new one twice): my
                                 other signed-in browsers are signed out
    GET  /tokens                 my API tokens: labels and dates, never the tokens
    POST /tokens                 a new token, shown on the page once
    POST /tokens/{id}/revoke     revoke one; it stops working at once

Sign-ups are limited per address (``labd.api.throttle``: ``signup``), and a name must
be ASCII and new without case (``repository.index.check_name``), so that nobody signs
up as a look-alike of someone else.
"""

from __future__ import annotations

import logging
from typing import Annotated, Any

from fastapi import APIRouter, Form, Request
from fastapi.responses import HTMLResponse, RedirectResponse
from pydantic import BaseModel

from labd.api.common import SESSION_COOKIE, Lab, client_address
from labd.api.errors import TooMany
from labd.api.models import Id
from labd.api.throttle import Throttle, name_at
from labd.web.forms import local, signed_in
from labd.web.render import page
from labd.web.session import CsrfChecked, Viewer
from repository.errors import AccountError, ArchiveError, BadCredentials, RecordNotFound

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
    address = client_address(request)
    throttle: Throttle = request.app.state.throttle
    problem = None
    status = 422
    try:
        throttle.check("address", address, "failed sign-ups from your address")
        throttle.check("signup", address, "sign-ups from your address")
        if password != again:
            problem = "the two passwords differ; type the same one twice"
        else:
            user = service.accounts.sign_up(name, password)
            throttle.fail("signup", address)  # every account made counts
            log.info("%s signed up from %s", user.name, address)
            return signed_in(request, service, user, then)
    except TooMany as err:
        problem, status = err.message, 429
    except ArchiveError as err:
        throttle.fail("address", address)  # many names tried from one address
        log.info("sign-up as %r from %s refused: %s", name, address, err)
        problem = str(err)
    context = {"then": local(then), "problem": problem, "name": name}
    return page(request, "signup.html", context, user=viewer, status_code=status)


def _password_page(
    request: Request,
    viewer: Viewer,
    *,
    problem: str | None = None,
    done: str | None = None,
    status: int = 200,
) -> HTMLResponse:
    context = {"problem": problem, "done": done}
    return page(request, "password.html", context, user=viewer, status_code=status)


@router.get("/password", response_class=HTMLResponse)
def password_form(request: Request, viewer: Viewer, done: str = "") -> Any:
    if viewer is None:
        return RedirectResponse("/session?then=/password", status_code=303)
    ended = (
        f"; your other sign-ins ({done}) have ended" if done.isascii() and done.isdigit() else ""
    )
    return _password_page(
        request, viewer, done=f"Your password is changed{ended}." if done else None
    )


class PasswordForm(BaseModel):
    current: str = ""
    password: str = ""
    again: str = ""


@router.post("/password", response_class=HTMLResponse, dependencies=[CsrfChecked])
def change_password(
    request: Request, service: Lab, viewer: Viewer, sent: Annotated[PasswordForm, Form()]
) -> Any:
    """Change my password: my other sessions end (whoever signed in with the old one is
    signed out), this one stays; my API tokens stay (revoke them on /tokens)."""
    if viewer is None:
        return RedirectResponse("/session?then=/password", status_code=303)
    address = client_address(request)
    throttle: Throttle = request.app.state.throttle
    who = name_at(viewer.name, address)
    if sent.password != sent.again:
        problem = "the two new passwords differ; type the same one twice"
        return _password_page(request, viewer, problem=problem, status=422)
    try:
        throttle.check("password", who, "failed passwords from your address")
        ended = service.accounts.change_password(
            viewer.name, sent.current, sent.password, keep=request.cookies.get(SESSION_COOKIE)
        )
    except TooMany as err:
        return _password_page(request, viewer, problem=err.message, status=429)
    except BadCredentials:
        throttle.fail("password", who)
        problem = "that is not your current password"
        return _password_page(request, viewer, problem=problem, status=401)
    except AccountError as err:
        return _password_page(request, viewer, problem=str(err), status=422)
    log.info(
        "%s changed their password from %s; %d other sessions ended", viewer.name, address, ended
    )
    return RedirectResponse(f"/password?done={ended}", status_code=303)


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
