"""The HTTP API of matches: submit one, follow it, cancel it, and a task's ladder.

A match is two commits playing a task teams play (``repository.match``); its legs are
trials like any other, each seed played twice with the sides swapped. Reading is
public; submitting and cancelling need a token or a signed-in session.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Query, Request
from fastapi.responses import JSONResponse
from pydantic import BaseModel, Field
from starlette.concurrency import run_in_threadpool

from labd.api.common import Lab, Writer
from labd.api.errors import ApiError, responses
from labd.api.models import Id
from labd.api.state import App
from labd.sim import registry
from repository.match import LadderRow, Match
from repository.match_index import MatchFilters
from scheduler.matches import Joined, MatchRequest, TeamRequest

router = APIRouter(tags=["matches"])


class MatchView(Match):
    """A match, with where to find it."""

    url: str = Field(description="this match in the API")
    page: str = Field(description="its web page")


class MatchPage(BaseModel):
    matches: list[MatchView]
    next: int | None = Field(description="`before` for the next page; null on the last")


class Ladder(BaseModel):
    """A task's ladder: every commit that played a finished match of it whose legs all
    verified, rated (Bradley-Terry, with 95 % bootstrap intervals), best first."""

    task: str
    rows: list[LadderRow]


@dataclass(frozen=True)
class MatchQuery:
    """The filters of GET /api/matches."""

    task: str | None = None
    repository: Annotated[str | None, Query(description="either team's repository")] = None
    commit: Annotated[
        str | None,
        Query(
            pattern=r"^[0-9a-fA-F]{4,40}$",
            description="either team's commit, or its first 4+ digits",
        ),
    ] = None
    submitter: Annotated[str | None, Query(description="who submitted it")] = None
    limit: Annotated[int, Query(ge=1, le=200)] = 50
    before: Annotated[Id | None, Query(description="the `next` of the page before")] = None


def view(match: Match, base: str) -> MatchView:
    return MatchView(
        **dict(match), url=f"{base}/api/matches/{match.id}", page=f"{base}/matches/{match.id}"
    )


def _base(request: Request) -> str:
    return str(request.base_url).rstrip("/")


def _created(service: Lab, match_id: int, request: Request) -> JSONResponse:
    body = view(service.matches.get(match_id), _base(request))
    return JSONResponse(
        body.model_dump(mode="json"), status_code=201, headers={"Location": body.url}
    )


@router.post(
    "/api/matches",
    status_code=201,
    response_model=MatchView,
    responses=responses(400, 401, 403, 404, 413, 422, 429, 503),
)
async def submit(
    body: MatchRequest, request: Request, service: Lab, app: App, user: Writer
) -> JSONResponse:
    """Resolve both refs to commits now, and queue every leg: each seed twice, A at home
    then B at home (each leg counts towards the daily limit)."""
    match_id = await service.submissions.in_pool(service.matchmaker.submit, user, body)
    app.on_submit()
    return await run_in_threadpool(_created, service, match_id, request)


@router.get("/api/matches", responses=responses(422))
def list_matches(request: Request, service: Lab, q: Annotated[MatchQuery, Depends()]) -> MatchPage:
    """Matches, newest first, a page at a time."""
    filters = MatchFilters(
        task=q.task, repository=q.repository, commit=q.commit, submitter=q.submitter
    )
    page = service.matches.find(filters, limit=q.limit, before=q.before)
    base = _base(request)
    return MatchPage(matches=[view(m, base) for m in page.items], next=page.next)


@router.get("/api/matches/{match_id}", responses=responses(404, 422))
def show(match_id: Id, request: Request, service: Lab) -> MatchView:
    """One match: its legs (who played home, the goals, who won and how), its score and
    whether every leg verified."""
    return view(service.matches.get(match_id), _base(request))


@router.post("/api/matches/{match_id}/cancel", responses=responses(401, 403, 404, 422))
def cancel(match_id: Id, request: Request, service: Lab, user: Writer) -> MatchView:
    """Cancel the legs still queued and stop those running; a cancelled match counts
    for no one on the ladder."""
    return view(service.matchmaker.cancel(user, match_id), _base(request))


@router.get("/api/ladders/{task}", responses=responses(404, 422))
def ladder(task: str, service: Lab) -> Ladder:
    """The task's ladder: each commit's rating from every leg of every finished match
    of it whose legs all verified (a draw half a win to each), with its 95 % interval
    from a bootstrap over matches, and its match count."""
    spec = registry.get(task)
    if len(spec.sides) != 2:
        raise ApiError(404, f"{spec.name} is not played by two teams: it has no ladder")
    return Ladder(task=spec.name, rows=service.matches.ladder(spec.name))


class JoinRequest(TeamRequest):
    """A commit to enter on the ladder: a repository at a ref."""


class JoinedView(BaseModel):
    """A commit entered on a ladder, and the matches the lab queued for it."""

    entry: int
    matches: list[MatchView]


@router.post(
    "/api/ladders/{task}/entries",
    status_code=201,
    responses=responses(400, 401, 403, 404, 413, 422, 429, 503),
)
async def join(
    task: str, body: JoinRequest, *, request: Request, service: Lab, app: App, user: Writer
) -> JoinedView:
    """Enter a commit (the ref resolved now) on the task's ladder: the lab queues its
    matches against commits entered before, in turn those with the fewest matches and
    those rated nearest it (each leg counts towards the daily limit; a few entries a day)."""
    joined = await service.submissions.in_pool(_join, service, user, task, body)
    app.on_submit()
    base = _base(request)
    matches = [view(service.matches.get(m), base) for m in joined.matches]
    return JoinedView(entry=joined.entry, matches=matches)


def _join(service: Lab, user: Any, task: str, body: JoinRequest) -> Joined:
    return service.matchmaker.join(user, registry.get(task).name, body)
