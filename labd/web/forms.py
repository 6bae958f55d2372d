"""The pages' forms: signing in with a token, submitting a trial, rerunning one.

    GET  /session               the sign-in form (a token, pasted once)
    POST /session               sign in: the token, checked, kept in an HttpOnly cookie
    POST /session/end           sign out
    GET  /submit                the submission form (repository URL, ref, task, params, seed)
    POST /submit                submit; on success, to the new trial's page
    POST /trials/{id}/rerun     rerun a trial; to the rerun's page

A submission goes through the same checks as ``POST /api/trials`` (the same request
model, the same submissions object), and a refusal is shown on the form with what the
person typed kept, so they can correct it.
"""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Form, Request
from fastapi.responses import HTMLResponse, RedirectResponse
from pydantic import BaseModel, ValidationError

from labd.api.common import Lab
from labd.sim import registry
from labd.web.render import page
from labd.web.session import COOKIE, MAX_AGE, SameOrigin, Viewer
from repository.errors import RecordNotFound
from repository.trial import TrialRequest, Value
from scheduler.errors import QueueError, TrialError

router = APIRouter(include_in_schema=False)


@router.get("/session", response_class=HTMLResponse)
def signin_form(request: Request, viewer: Viewer, then: str = "/") -> HTMLResponse:
    return page(request, "signin.html", {"then": _local(then), "problem": None}, user=viewer)


@router.post("/session", response_class=HTMLResponse, dependencies=[SameOrigin])
def signin(
    request: Request,
    service: Lab,
    token: Annotated[str, Form()],
    then: Annotated[str, Form()] = "/",
) -> Any:
    user = service.index.user_by_token(token.strip())
    if user is None:
        return page(
            request,
            "signin.html",
            {"then": _local(then), "problem": "the lab does not know that token"},
            status_code=401,
        )
    response = RedirectResponse(_local(then), status_code=303)
    response.set_cookie(
        COOKIE,
        token.strip(),
        max_age=MAX_AGE,
        httponly=True,
        samesite="strict",
        secure=request.url.scheme == "https",
    )
    return response


@router.post("/session/end", dependencies=[SameOrigin])
def signout() -> RedirectResponse:
    response = RedirectResponse("/", status_code=303)
    response.delete_cookie(COOKIE)
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


@router.post("/submit", response_class=HTMLResponse, dependencies=[SameOrigin])
def submit(
    request: Request, service: Lab, viewer: Viewer, sent: Annotated[SubmitForm, Form()]
) -> Any:
    form = sent.model_dump()
    if viewer is None:
        return _form(request, viewer, form, "sign in first: submitting needs your token", 401)
    try:
        body = TrialRequest(
            repository=sent.repository.strip(),
            ref=sent.ref.strip() or None,
            task=sent.task or None,
            params=_params(sent.params),
            seed=int(sent.seed or 0),
        )
        trial_id = service.submissions.submit(viewer, body)
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
        name, sep, value = item.partition("=")
        if not sep or not name:
            raise ValueError(f"parameters: {item!r}: write NAME=VALUE")
        out[name] = value
    return out


@router.post("/trials/{trial_id}/rerun", dependencies=[SameOrigin])
def rerun(request: Request, trial_id: int, service: Lab, viewer: Viewer) -> Any:
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


def _local(path: str) -> str:
    """Where to go after signing in: a path of this lab only (never another site)."""
    return path if path.startswith("/") and not path.startswith("//") else "/"
