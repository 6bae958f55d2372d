"""The pages' forms: signing in and out, submitting a trial, rerunning one.

    GET  /session               the sign-in form: name and password, or a token pasted once
    POST /session               sign in: a new session, its id in an HttpOnly cookie
    POST /session/end           sign out: the session ends
    GET  /submit                the submission form (repository URL, ref, task, params, seed)
    POST /submit                submit; on success, to the new trial's page
    POST /trials/{id}/rerun     rerun a trial; to the rerun's page

A submission goes through the same checks as ``POST /api/trials`` (the same request
model, the same submissions object), and a refusal is shown on the form with what the
person typed kept, so they can correct it, under the status the API gives it
(``labd.web.problems.on_form``). Every form that changes something carries the CSRF
token (``labd.web.session``). Failed sign-ins are counted per name and address, and per
address (``labd.api.throttle``): past the limit they are refused unchecked for a while;
a guesser elsewhere never locks the owner out.
"""

from __future__ import annotations

import logging
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Form, Request
from fastapi.responses import HTMLResponse, RedirectResponse
from pydantic import BaseModel, ValidationError

from labd.api.common import SESSION_COOKIE, Caller, Lab
from labd.api.errors import Invalid, Unauthorized, invalid
from labd.api.models import Id
from labd.api.state import App
from labd.config import assignment
from labd.sim import registry
from labd.web.problems import PageRoute, on_form
from labd.web.render import page
from labd.web.session import CsrfChecked, Person, SignedIn, Viewer, set_session_cookie
from repository.errors import BadCredentials
from repository.index import User
from repository.trial import TrialRequest, Value

router = APIRouter(include_in_schema=False, route_class=PageRoute)


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
            "providers": service.config.oidc.providers,  # OpenID Connect (labd.web.oidc)
            "signup_oidc": not service.config.oidc.domains and not service.config.oidc.invited,
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
    request: Request,
    service: Lab,
    caller: Caller,
    viewer: Viewer,
    sent: Annotated[SigninForm, Form()],
) -> Any:
    name, token, then = sent.name.strip(), sent.token.strip(), sent.then
    with on_form(
        request,
        lambda problem, status: _signin(
            request, service, viewer, then, problem, status=status, name=name
        ),
    ):
        caller.check("address", "failed sign-ins from your address")
        if token:
            user = service.index.user_by_token(token)
            if user is None:
                caller.fail("address")
                log.info("sign-in with an unknown token from %s", caller.address)
                raise Unauthorized("the lab does not know that token")
        else:
            caller.check(
                "password",
                f"failed sign-ins for {name or 'that name'} from your address",
                name=name,
            )
            try:
                user = service.accounts.check_password(name, sent.password)
            except BadCredentials:
                caller.fail("password", name=name)
                caller.fail("address")
                log.info("failed sign-in for %r from %s", name, caller.address)
                raise
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

    def request(self) -> TrialRequest:
        """The submission these fields ask for (``Invalid`` saying which is wrong)."""
        try:
            return TrialRequest(
                repository=self.repository.strip(),
                ref=self.ref.strip() or None,
                task=self.task or None,
                params=_params(self.params),
                seed=int(self.seed or 0),
            )
        except ValidationError as err:
            raise Invalid(invalid(err.errors())) from None
        except ValueError as err:  # the seed or a parameter line
            raise Invalid(str(err)) from None


@router.post("/submit", response_class=HTMLResponse, dependencies=[CsrfChecked])
async def submit(
    request: Request, service: Lab, app: App, person: Person, sent: Annotated[SubmitForm, Form()]
) -> Any:
    """Submit from the form; resolved in the submissions' own threads, as the API's are."""
    form = sent.model_dump()
    with on_form(request, lambda problem, status: _form(request, person, form, problem, status)):
        trial_id = await service.submissions.submit_async(person, sent.request())
    app.on_submit()
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
def rerun(
    trial_id: Id,
    service: Lab,
    app: App,
    person: Annotated[User, Depends(SignedIn("/trials/{trial_id}"))],
) -> RedirectResponse:
    new_id = service.submissions.rerun(person, trial_id)
    app.on_submit()
    return RedirectResponse(f"/trials/{new_id}", status_code=303)


def local(path: str) -> str:
    """Where to go after signing in: a path of this lab only (never another site)."""
    return path if path.startswith("/") and not path.startswith("//") else "/"
