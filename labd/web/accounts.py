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

from fastapi import APIRouter, Depends, Form, Request
from fastapi.responses import HTMLResponse, RedirectResponse
from pydantic import BaseModel

from labd.api.common import SESSION_COOKIE, Caller, Lab
from labd.api.errors import ApiError, Invalid, Unauthorized
from labd.api.models import Id
from labd.web.forms import local, signed_in
from labd.web.problems import PageRoute, on_form
from labd.web.render import page
from labd.web.session import CsrfChecked, Person, SignedIn, Viewer
from repository.errors import ArchiveError, BadCredentials
from repository.index import User

router = APIRouter(include_in_schema=False, route_class=PageRoute)
log = logging.getLogger("labd.web")
# The tokens' forms post to addresses of their own, and come back to the tokens page.
TokenOwner = Annotated[User, Depends(SignedIn("/tokens"))]


def _open(service: Lab) -> None:
    """Refuse (404) signing up where the operator makes the accounts."""
    if not service.config.signup:
        raise ApiError(
            404,
            "The lab's operator makes the accounts of this lab"
            " (labd users add NAME --password): ask them for one.",
            title="Sign-up is closed here",
        )


@router.get("/signup", response_class=HTMLResponse)
def signup_form(request: Request, service: Lab, viewer: Viewer, then: str = "/") -> HTMLResponse:
    _open(service)
    context = {"then": local(then), "problem": None, "name": ""}
    return page(request, "signup.html", context, user=viewer)


class SignupForm(BaseModel):
    name: str = ""
    password: str = ""
    again: str = ""
    then: str = "/reservations"


@router.post("/signup", response_class=HTMLResponse, dependencies=[CsrfChecked])
def signup(
    request: Request,
    service: Lab,
    caller: Caller,
    viewer: Viewer,
    sent: Annotated[SignupForm, Form()],
) -> Any:
    _open(service)
    name, then = sent.name.strip(), sent.then

    def shown(problem: str, status: int) -> HTMLResponse:
        context = {"then": local(then), "problem": problem, "name": name}
        return page(request, "signup.html", context, user=viewer, status_code=status)

    with on_form(request, shown):
        caller.check("address", "failed sign-ups from your address")
        caller.check("signup", "sign-ups from your address")
        if sent.password != sent.again:
            raise Invalid("the two passwords differ; type the same one twice")
        try:
            user = service.accounts.sign_up(name, sent.password)
        except ArchiveError as err:
            caller.fail("address")  # many names tried from one address
            log.info("sign-up as %r from %s refused: %s", name, caller.address, err)
            raise
    caller.fail("signup")  # every account made counts
    log.info("%s signed up from %s", user.name, caller.address)
    return signed_in(request, service, user, then)


def _password_page(
    request: Request,
    person: User,
    *,
    problem: str | None = None,
    done: str | None = None,
    status: int = 200,
) -> HTMLResponse:
    context = {"problem": problem, "done": done}
    return page(request, "password.html", context, user=person, status_code=status)


@router.get("/password", response_class=HTMLResponse)
def password_form(request: Request, person: Person, done: str = "") -> HTMLResponse:
    ended = (
        f"; your other sign-ins ({done}) have ended" if done.isascii() and done.isdigit() else ""
    )
    return _password_page(
        request, person, done=f"Your password is changed{ended}." if done else None
    )


class PasswordForm(BaseModel):
    current: str = ""
    password: str = ""
    again: str = ""


@router.post("/password", response_class=HTMLResponse, dependencies=[CsrfChecked])
def change_password(
    request: Request,
    service: Lab,
    caller: Caller,
    person: Person,
    sent: Annotated[PasswordForm, Form()],
) -> Any:
    """Change my password: my other sessions end (whoever signed in with the old one is
    signed out), this one stays; my API tokens stay (revoke them on /tokens)."""
    with on_form(
        request,
        lambda problem, status: _password_page(request, person, problem=problem, status=status),
    ):
        if sent.password != sent.again:
            raise Invalid("the two new passwords differ; type the same one twice")
        caller.check("password", "failed passwords from your address", name=person.name)
        try:
            ended = service.accounts.change_password(
                person.name, sent.current, sent.password, keep=request.cookies.get(SESSION_COOKIE)
            )
        except BadCredentials:
            caller.fail("password", name=person.name)
            raise Unauthorized("that is not your current password") from None
    log.info(
        "%s changed their password from %s; %d other sessions ended",
        person.name,
        caller.address,
        ended,
    )
    return RedirectResponse(f"/password?done={ended}", status_code=303)


def _tokens(
    request: Request,
    service: Lab,
    person: User,
    *,
    new: str | None = None,
    problem: str | None = None,
    status: int = 200,
) -> HTMLResponse:
    context = {
        "tokens": service.accounts.tokens(person.name),
        "new": new,
        "problem": problem,
        "providers": service.config.oidc.providers,  # linking one (labd.web.oidc)
        "identities": service.accounts.identities(person.name),
    }
    return page(request, "tokens.html", context, user=person, status_code=status)


@router.get("/tokens", response_class=HTMLResponse)
def tokens(request: Request, service: Lab, person: Person) -> HTMLResponse:
    return _tokens(request, service, person)


@router.post("/tokens", response_class=HTMLResponse, dependencies=[CsrfChecked])
def new_token(
    request: Request, service: Lab, person: TokenOwner, label: Annotated[str, Form()] = ""
) -> HTMLResponse:
    _, token = service.accounts.new_token(person.name, label)
    response = _tokens(request, service, person, new=token, status=201)
    response.headers["Cache-Control"] = "no-store"
    return response


@router.post("/tokens/{token_id}/revoke", dependencies=[CsrfChecked])
def revoke(request: Request, token_id: Id, service: Lab, person: TokenOwner) -> Any:
    with on_form(
        request,
        lambda problem, status: _tokens(request, service, person, problem=problem, status=status),
    ):
        service.accounts.revoke_token(person.name, token_id)
    return RedirectResponse("/tokens", status_code=303)
