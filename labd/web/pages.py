"""The archive's pages: the lab, trials, one trial, a commit, a task.

    GET /                   the lab: what runs and waits, recent trials, the latest
                            evaluations and the leaderboards, live robots, the tasks
    GET /trials             filters (repository, commit, task, outcome, user, time),
                            sorted by time (pages by cursor) or reward (pages by number)
    GET /trials/{id}        outcome and reason, what ran, metrics, logs, downloads, the
                            record's plots and camera, the rerun verdict, a rerun button;
                            a leg of a match links its match
    GET /commits/{sha}      every trial of a commit with its reruns and verdicts
    GET /tasks/{name}       the task's documentation, parameters, suites, the leaderboard
                            of a suite's evaluations (``?suite=``, by default ``dev``:
                            ``labd.web.evaluations``), a link to its ladder when
                            teams play it (``labd.web.matches``), and its recent trials

They read the same typed records as the API (``repository.trial.Trial``), server-side;
an unknown id or sha is a page saying so, with the API's status and words, never JSON
(``labd.web.problems``).
"""

from __future__ import annotations

import datetime as dt
import json
import re
from dataclasses import dataclass
from typing import Annotated, Any
from urllib.parse import urlsplit

from fastapi import APIRouter, Depends, Query, Request
from fastapi.responses import HTMLResponse

from labd.api.common import Lab
from labd.api.errors import Invalid
from labd.api.models import Id, trial_detail
from labd.api.state import App
from labd.errors import LabError
from labd.sim import registry
from labd.web.evaluations import Listed, rate_words, task_board
from labd.web.problems import PageRoute, on_form
from labd.web.render import page
from labd.web.session import Viewer
from repository.errors import BlobError, ManifestError
from repository.evaluation_index import EvaluationFilters
from repository.index import Derived, Filters, Sort
from repository.manifest import Driver, Manifest
from repository.trial import Kind, Outcome, Status, Trial
from repository.units import KiB
from repository.well_known import REPLAY, SUMMARY, VIDEO
from scheduler.states import State

router = APIRouter(include_in_schema=False, route_class=PageRoute)
PAGE = 50
# The home page fits a 1280x800 screen: the recent trials, the running trials it names
# (it counts them all), the latest evaluations, and how many evaluations back it looks
# for the suites whose leaderboards it links.
HOME_TRIALS = 8
HOME_RUNNING = 5
HOME_EVALUATIONS = 6
HOME_EVALUATED = 20
LOG_SHOWN = 64 * KiB  # bytes of a log shown on its trial's page (the end of it)
# What the outcome menu also offers: the states of a trial that has no outcome.
WITHOUT_OUTCOME = tuple(s for s in Status if s is not Status.FINISHED)


@router.get("/", response_class=HTMLResponse)
def home(request: Request, service: Lab, app: App, viewer: Viewer) -> HTMLResponse:
    """What a person looks for first, in a screen's height: what runs and waits, the
    recent trials, the latest evaluations with their rates and the leaderboards of the
    suites they ran; then the catalogue of tasks. Held-out episodes are left out of what
    runs and waits (when each starts and ends would time it); an evaluation of a
    held-out suite shows its aggregate alone, as its own page does."""
    tasks = [registry.get(name) for name in registry.names()]
    latest = service.evaluations.find(EvaluationFilters(), limit=HOME_EVALUATED).items
    robots: dict[str, list[str]] = {}
    for robot in app.site.robots:
        robots.setdefault(robot.task, []).append(robot.name)
    return page(
        request,
        "home.html",
        {
            "tasks": tasks,
            "robots": robots,
            "site": app.site,
            "recent": service.index.find(Filters(), limit=HOME_TRIALS).items,
            "running": service.queue.running(public=True),
            "running_shown": HOME_RUNNING,
            "queued": service.queue.queued(public=True),
            "unwell": [h for h in service.queue.health.values() if h.state is State.OUT],
            "evaluations": [
                Listed(e, rate_words(e.score, e.status.ended)) for e in latest[:HOME_EVALUATIONS]
            ],
            "boards": list(dict.fromkeys((e.task, e.suite) for e in latest)),
            "now": dt.datetime.now(dt.UTC),
        },
        user=viewer,
    )


@dataclass(frozen=True)
class TrialsQuery:
    """The form of /trials: filters, the order, and where the page starts."""

    repository: str = ""
    commit: str = ""
    task: str = ""
    outcome: str = ""
    user: str = ""
    since: str = ""
    until: str = ""
    kind: str = ""
    order: str = "time"
    before: Id | None = None
    page: Annotated[int, Query(ge=1)] = 1


@router.get("/trials", response_class=HTMLResponse)
def trials(
    request: Request, service: Lab, viewer: Viewer, q: Annotated[TrialsQuery, Depends()]
) -> HTMLResponse:
    form = {
        "repository": q.repository,
        "commit": q.commit,
        "task": q.task,
        "outcome": q.outcome,
        "user": q.user,
        "since": q.since,
        "until": q.until,
        "kind": q.kind,
        "order": Sort(q.order) if q.order in set(Sort) else Sort.TIME,
    }
    repository, commit, task, outcome, user = q.repository, q.commit, q.task, q.outcome, q.user
    since, until, kind, before, page_number = q.since, q.until, q.kind, q.before, q.page
    query = {k: v for k, v in form.items() if v and not (k == "order" and v is Sort.TIME)}

    def shown(
        items: list[Trial], next_cursor: int | None, problem: str | None, status: int
    ) -> HTMLResponse:
        return page(
            request,
            "trials.html",
            {
                "trials": items,
                "form": form,
                "problem": problem,
                "tasks": registry.names(),
                "outcomes": [o.value for o in (*Outcome, *WITHOUT_OUTCOME)],
                "next_cursor": next_cursor,
                "page_number": page_number,
                "query": query,
            },
            user=viewer,
            status_code=status,
        )

    with on_form(request, lambda problem, status: shown([], None, problem, status)):
        filters = Filters(
            repository=repository or None,
            commit=commit or None,
            task=task or None,
            outcome=_enum(Outcome, outcome, "outcome"),
            status=_status(outcome),
            kind=_enum(Kind, kind, "kind"),
            submitter=user or None,
            since=_day(since, "since"),
            until=_day(until, "until", end=True),
        )
        if form["order"] is Sort.REWARD:
            found = service.index.find(
                filters, limit=PAGE, order=Sort.REWARD, offset=(page_number - 1) * PAGE
            )
        else:
            found = service.index.find(filters, limit=PAGE, before=before)
    return shown(found.items, found.next, None, 200)


def _enum(kind: Any, value: str | None, name: str) -> Any:
    if not value or (kind is Outcome and value in WITHOUT_OUTCOME):
        return None
    try:
        return kind(value)
    except ValueError:
        raise Invalid(f"{name} {value!r}: choose one of the list") from None


def _status(outcome: str | None) -> Status | None:
    """The outcome menu also offers the states a trial without one is in."""
    return Status(outcome) if outcome in WITHOUT_OUTCOME else None


def _day(text: str | None, name: str, *, end: bool = False) -> float | None:
    if not text:
        return None
    try:
        day = dt.date.fromisoformat(text)
    except ValueError:
        raise Invalid(f"{name} {text!r}: give a date as YYYY-MM-DD") from None
    moment = dt.datetime.combine(day, dt.time(), dt.UTC)
    return (moment + dt.timedelta(days=1 if end else 0)).timestamp()


@router.get("/trials/{trial_id}", response_class=HTMLResponse)
def trial(request: Request, trial_id: Id, service: Lab, viewer: Viewer) -> HTMLResponse:
    record = service.index.readable(trial_id)
    base = str(request.base_url).rstrip("/")
    reruns = service.index.find(Filters(rerun_of=trial_id), limit=20).items
    logs = {stream: _log(service, getattr(record, stream)) for stream in ("stdout", "stderr")}
    derived = service.index.derived(trial_id)
    replayed = _replayed(service, derived.get(REPLAY))
    return page(
        request,
        "trial.html",
        {
            "t": record,
            "view": trial_detail(record, base),
            "reruns": reruns,
            "logs": logs,
            "summary": derived.get(SUMMARY),
            "replayed": replayed,
            "video": derived.get(VIDEO),
            # a replayed record's video is rendered when first played, if not made yet
            "renderable": bool(record.mcap) and bool(replayed and replayed.get("ticks")),
            "ended": record.status.ended,
            "evaluation": service.evaluations.of_trial(trial_id),
            "match": service.matches.of_trial(trial_id),
            "playground": _playground(service, record),
            "driver": _driver(record),
        },
        user=viewer,
    )


def _driver(record: Trial) -> Driver | None:
    """Who drove a demonstration, as its manifest says (None for a trial, or a manifest
    that cannot be read: the page shows the rest)."""
    try:
        return Manifest.from_json(record.manifest).driver if record.manifest else None
    except ManifestError:
        return None


HOSTED = re.compile(r"^/git/([^/]+)/([^/]+)\.git$")  # the path of one of the lab's own


def _playground(service: Lab, record: Trial) -> str | None:
    """The playground page of a trial's script, when the trial ran a commit of one of
    this lab's own repositories (found by its commit there, whatever address the lab had
    when it ran)."""
    found = HOSTED.match(urlsplit(record.repository).path)
    if found is None or not record.commit:
        return None
    user, name = found.groups()
    try:  # which checks the names, before any path is made of them
        service.hosted.read(user, name, record.commit)
    except LabError:
        return None
    return f"/playground?repo={user}/{name}&commit={record.commit}"


def _replayed(service: Lab, item: Derived | None) -> dict[str, Any] | None:
    """The replay's verdict, for the page (None: not replayed yet)."""
    if item is None:
        return None
    try:
        verdict: dict[str, Any] = json.loads(service.store.read_bytes(item.digest))
    except (BlobError, ValueError) as err:
        return {"verified": False, "said": f"the verdict cannot be read: {err}"}
    return verdict


def _log(service: Lab, digest: str | None) -> dict[str, Any] | None:
    """A log for the page: its end, if it is long, and its size (None: there is none)."""
    if not digest:
        return None
    try:
        data = service.store.read_bytes(digest)
    except BlobError as err:
        return {"text": "", "size": 0, "cut": False, "problem": str(err)}
    cut = len(data) > LOG_SHOWN
    shown = data[-LOG_SHOWN:] if cut else data
    return {
        "text": shown.decode("utf-8", "replace"),
        "size": len(data),
        "cut": cut,
        "problem": None,
    }


@router.get("/commits/{sha}", response_class=HTMLResponse)
def commit(request: Request, sha: str, service: Lab, viewer: Viewer) -> HTMLResponse:
    found = service.index.commit_page(sha)
    return page(request, "commit.html", {"c": found}, user=viewer)


@router.get("/tasks/{name}", response_class=HTMLResponse)
def task(
    request: Request,
    name: str,
    service: Lab,
    viewer: Viewer,
    suite: Annotated[str | None, Query(max_length=32, description="a suite of the task")] = None,
) -> HTMLResponse:
    spec = registry.get(name)
    observations, commands = spec.topics()
    return page(
        request,
        "task.html",
        {
            "spec": spec,
            "params": list(spec.params.declared.values()),
            "observations": observations,
            "commands": commands,
            **task_board(service, spec.name, suite),
            "ladder": len(spec.sides) == 2,
            "recent": service.index.find(Filters(task=name), limit=10).items,
        },
        user=viewer,
    )
