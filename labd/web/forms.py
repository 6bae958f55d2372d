"""The pages' forms: signing in and out, submitting a trial, rerunning one.

    GET  /session               the sign-in form: name and password, or a token pasted once
    POST /session               sign in: a new session, its id in an HttpOnly cookie
    POST /session/end           sign out: the session ends
    GET  /submit                the submission form (repository URL, ref, task, params, seed)
    POST /submit                submit; on success, to the new trial's page
    POST /trials/{id}/rerun     rerun a trial; to the rerun's page

A submission goes through the same checks as ``POST /api/trials`` (the same request
model, the same submissions object), and a refusal is shown on the form with what the
person typed kept, so they can correct it. Every form that changes something carries
the CSRF token (``labd.web.session``). Failed sign-ins are counted per name and address,
and per address (``labd.api.throttle``): past the limit they are refused unchecked for a
while; a guesser elsewhere never locks the owner out.
"""

from __future__ import annotations

import logging
from typing import Annotated, Any

from fastapi import APIRouter, Form, Request
from fastapi.responses import HTMLResponse, RedirectResponse
from pydantic import BaseModel, ValidationError

from labd.api.common import SESSION_COOKIE, Lab, client_address
from labd.api.errors import TooMany
from labd.api.models import Id
from labd.api.throttle import Throttle, name_at
from labd.config import assignment
from labd.sim import registry
from labd.web.render import page
from labd.web.session import CsrfChecked, Viewer, set_session_cookie
from repository.errors import BadCredentials, RecordNotFound
from repository.index import User
from repository.trial import TrialRequest, Value
from scheduler.errors import QueueError, TrialError

router = APIRouter(include_in_schema=False)


log = logging.getLogger("labd.web")


@router.get("/session", response_class=HTMLResponse)
def signin_form(request: Request, service: Lab, viewer: Viewer, then: str = "/") -> HTMLResponse:
    return _signin(request, service, viewer, then, None)


def _signin(
    request: Request,
    service: Lab,
    viewer: User | None,
    then: str,
    problem: str | None,
    *,
    status: int = 200,
    name: str = "",
) -> HTMLResponse:
    return page(
        request,
        "signin.html",
        {
            "then": local(then),
            "problem": problem,
            "name": name,
            "signup": service.config.signup,
        },
        user=viewer,
        status_code=status,
    )


class SigninForm(BaseModel):
    """The sign-in forms' fields: a name and password, or a token."""

    name: str = ""
    password: str = ""
    token: str = ""
    then: str = "/"


@router.post("/session", response_class=HTMLResponse, dependencies=[CsrfChecked])
def signin(
    request: Request, service: Lab, viewer: Viewer, sent: Annotated[SigninForm, Form()]
) -> Any:
    address = client_address(request)
    throttle: Throttle = request.app.state.throttle
    name, password, token, then = sent.name.strip(), sent.password, sent.token, sent.then
    try:
        throttle.check("address", address, "failed sign-ins from your address")
        if token.strip():
            user = service.index.user_by_token(token.strip())
            if user is None:
                throttle.fail("address", address)
                log.info("sign-in with an unknown token from %s", address)
                return _signin(
                    request, service, viewer, then, "the lab does not know that token", status=401
                )
        else:
            throttle.check(
                "password",
                name_at(name, address),
                f"failed sign-ins for {name or 'that name'} from your address",
            )
            try:
                user = service.accounts.check_password(name, password)
            except BadCredentials as err:
                throttle.fail("password", name_at(name, address))
                throttle.fail("address", address)
                log.info("failed sign-in for %r from %s", name, address)
                return _signin(request, service, viewer, then, str(err), status=401, name=name)
    except TooMany as err:
        return _signin(request, service, viewer, then, err.message, status=429, name=name)
    return signed_in(request, service, user, then)


def signed_in(request: Request, service: Lab, user: User, then: str) -> RedirectResponse:
    """Open a session for ``user`` (a new id: nothing carried over) and go on."""
    cookie, _ = service.accounts.open_session(user)
    log.info("%s signed in", user.name)
    response = RedirectResponse(local(then), status_code=303)
    set_session_cookie(response, request, cookie, service.accounts.session_age)
    return response


@router.post("/session/end", dependencies=[CsrfChecked])
def signout(request: Request, service: Lab) -> RedirectResponse:
    cookie = request.cookies.get(SESSION_COOKIE)
    if cookie:
        service.accounts.end_session(cookie)
    response = RedirectResponse("/", status_code=303)
    response.delete_cookie(SESSION_COOKIE)
    return response


@router.get("/submit", response_class=HTMLResponse)
def submit_form(
    request: Request, viewer: Viewer, repository: str = "", task: str = ""
) -> HTMLResponse:
    form = {"repository": repository, "ref": "", "task": task, "params": "", "seed": "0"}
    return _form(request, viewer, form, None)


def _form(
    request: Request, viewer: Viewer, form: dict[str, str], problem: str | None, status: int = 200
) -> HTMLResponse:
    tasks = {name: registry.get(name) for name in registry.names()}
    return page(
        request,
        "submit.html",
        {"form": form, "problem": problem, "tasks": tasks},
        user=viewer,
        status_code=status,
    )


class SubmitForm(BaseModel):
    """The submission form's fields, as typed (checked by ``TrialRequest`` after)."""

    repository: str = ""
    ref: str = ""
    task: str = ""
    params: str = ""
    seed: str = "0"


@router.post("/submit", response_class=HTMLResponse, dependencies=[CsrfChecked])
async def submit(
    request: Request, service: Lab, viewer: Viewer, sent: Annotated[SubmitForm, Form()]
) -> Any:
    """Submit from the form; resolved in the submissions' own threads, as the API's are."""
    form = sent.model_dump()
    if viewer is None:
        return _form(request, viewer, form, "sign in first: submitting needs an account", 401)
    try:
        body = TrialRequest(
            repository=sent.repository.strip(),
            ref=sent.ref.strip() or None,
            task=sent.task or None,
            params=_params(sent.params),
            seed=int(sent.seed or 0),
        )
        trial_id = await service.submissions.submit_async(viewer, body)
    except ValidationError as err:
        problems = "; ".join(
            f"{'.'.join(str(x) for x in e['loc'])}: {e['msg']}" for e in err.errors()
        )
        return _form(request, viewer, form, problems, 422)
    except ValueError as err:  # the seed or a parameter line
        return _form(request, viewer, form, str(err), 422)
    except (TrialError, QueueError) as err:
        return _form(request, viewer, form, str(err), 422)
    request.app.state.on_submit()
    return RedirectResponse(f"/trials/{trial_id}", status_code=303)


def _params(text: str) -> dict[str, Value]:
    """``NAME=VALUE`` lines (or items separated by spaces) as a dict; ValueError if not."""
    out: dict[str, Value] = {}
    for item in text.split():
        try:
            name, value = assignment(item)
        except ValueError as err:
            raise ValueError(f"parameters: {err}") from None
        out[name] = value
    return out


@router.post("/trials/{trial_id}/rerun", dependencies=[CsrfChecked])
def rerun(request: Request, trial_id: Id, service: Lab, viewer: Viewer) -> Any:
    if viewer is None:
        return RedirectResponse(f"/session?then=/trials/{trial_id}", status_code=303)
    try:
        new_id = service.submissions.rerun(viewer, trial_id)
    except (RecordNotFound, QueueError) as err:
        return page(
            request,
            "error.html",
            {"title": "Not rerun", "message": str(err), "back": f"/trials/{trial_id}"},
            user=viewer,
            status_code=422,
        )
    request.app.state.on_submit()
    return RedirectResponse(f"/trials/{new_id}", status_code=303)


def local(path: str) -> str:
    """Where to go after signing in: a path of this lab only (never another site)."""
    return path if path.startswith("/") and not path.startswith("//") else "/"
