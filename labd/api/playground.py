"""The playground's API: check a script, commit it and run it as a trial, read it back.

    POST /api/playground/check          does the script parse? (at which line, if not)
    POST /api/playground/trials         commit the script to the writer's repository
                                        USER/NAME and queue a trial of that commit
    POST /api/playground/evaluations    the same, then evaluate it on a suite
    GET  /api/playground/{user}/{name}  a playground repository's script (?commit=)

A playground trial is an ordinary trial: the lab commits the script as a controller
repository (``labd.playground.files``) to a repository it hosts (``labd.hosted``),
readable by anyone at ``PUBLIC/git/USER/NAME.git`` (``labd.api.git``), and submits
that URL at that commit, so it is resolved, fetched, run, rerun and cloned like any
repository's. Nothing is committed unless the script parses.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Request
from fastapi.responses import JSONResponse
from pydantic import BaseModel, ConfigDict, Field
from starlette.concurrency import run_in_threadpool

from labd.api.common import Lab, Writer
from labd.api.errors import ApiError, responses
from labd.api.evaluations import view as evaluation_view
from labd.api.models import EvaluationView, TrialDetail, trial_detail
from labd.api.state import App
from labd.playground import MAX_SCRIPT, Script, ScriptError, check, files, script_of
from labd.service import Service
from labd.sim import registry
from repository.evaluation import EvaluationRequest
from repository.index import NAME, User
from repository.trial import Seed as SeedField
from repository.trial import TrialRequest

router = APIRouter(tags=["playground"])

Name = Annotated[
    str,
    Field(
        pattern=NAME.pattern,
        description="the repository's name (letters, digits, '.', '_', '-'; at most 64)",
    ),
]


class ScriptBody(BaseModel):
    """A script to check."""

    model_config = ConfigDict(extra="forbid")
    script: str = Field(max_length=MAX_SCRIPT, description="the script (an ES module)")


class ScriptCheck(BaseModel):
    """Whether a script parses, and Node's message at its line and column if not."""

    ok: bool
    error: str | None = None
    line: int | None = None
    column: int | None = None


class ScriptCommit(BaseModel):
    """A script to commit as ``USER/NAME``, for ``task``."""

    model_config = ConfigDict(extra="forbid")
    name: Name
    task: str = Field(min_length=1, max_length=64, description="a task from /api/tasks")
    script: str = Field(max_length=MAX_SCRIPT, description="the script (an ES module)")
    message: str = Field("", max_length=200, description="the commit's message")


class PlaygroundRequest(ScriptCommit):
    """A script to commit as ``USER/NAME`` and run as a trial of ``task``."""

    seed: SeedField = 0


class PlaygroundEvaluationRequest(ScriptCommit):
    """A script to commit as ``USER/NAME`` and evaluate on a suite of ``task``."""

    suite: str = Field("dev", min_length=1, max_length=32, description="a suite of the task")


class PlaygroundRun(BaseModel):
    """What a script became: its commit in the lab's repository, and the trial."""

    repository: str  # the hosted repository's URL: git clone it
    commit: str
    playground: str  # the page that shows the script at this commit
    trial: TrialDetail


class PlaygroundEvaluation(BaseModel):
    """What a script became: its commit in the lab's repository, and the evaluation."""

    repository: str
    commit: str
    playground: str
    evaluation: EvaluationView


class PlaygroundScript(BaseModel):
    """A playground repository's script at one commit."""

    user: str
    name: str
    repository: str
    commit: str
    task: str
    script: str


@router.post("/api/playground/check", responses=responses(401, 403, 413, 422, 503))
async def check_script(body: ScriptBody, user: Writer) -> ScriptCheck:
    """Parse the script with the lab's Node.js (nothing runs): ``ok``, or Node's
    message and where. A writer's: the parser runs on the lab's machine."""
    try:
        await run_in_threadpool(check, body.script)
    except ScriptError as err:
        return ScriptCheck(ok=False, error=err.message, line=err.line, column=err.column)
    return ScriptCheck(ok=True)


@router.post(
    "/api/playground/trials",
    status_code=201,
    response_model=PlaygroundRun,
    responses=responses(400, 401, 403, 404, 413, 422, 429, 503),
)
async def run_as_trial(
    body: PlaygroundRequest, request: Request, service: Lab, app: App, user: Writer
) -> JSONResponse:
    """Commit the script to the writer's repository ``NAME`` (made on first use), then
    queue a trial of that commit, exactly as ``POST /api/trials`` would: 422 with the
    parser's message at its line when the script does not parse (nothing committed)."""
    url, sha = await _commit(service, user, body)
    request_ = TrialRequest(repository=url, ref=sha, task=body.task, seed=body.seed)
    trial_id = await service.submissions.submit_async(user, request_)
    app.on_submit()

    base = str(request.base_url).rstrip("/")
    trial = await run_in_threadpool(lambda: trial_detail(service.index.trial(trial_id), base))
    page = _page(base, user.name, body.name, sha)
    return _created(PlaygroundRun(repository=url, commit=sha, playground=page, trial=trial))


@router.post(
    "/api/playground/evaluations",
    status_code=201,
    response_model=PlaygroundEvaluation,
    responses=responses(400, 401, 403, 404, 413, 422, 429, 503),
)
async def run_as_evaluation(
    body: PlaygroundEvaluationRequest, request: Request, service: Lab, app: App, user: Writer
) -> JSONResponse:
    """Commit the script as ``POST /api/playground/trials`` does, then evaluate that
    commit on a suite of its task, exactly as ``POST /api/evaluations`` would."""
    if registry.get(body.task).suite(body.suite) is None:
        raise ApiError(404, f"{body.task} has no suite {body.suite!r}")
    url, sha = await _commit(service, user, body)
    asked = EvaluationRequest(repository=url, ref=sha, task=body.task, suite=body.suite)
    evaluation_id = await service.submissions.in_pool(service.evaluator.submit, user, asked)
    app.on_submit()

    base = str(request.base_url).rstrip("/")
    made = await run_in_threadpool(service.evaluations.get, evaluation_id)
    page = _page(base, user.name, body.name, sha)
    evaluation = evaluation_view(made, base)
    return _created(
        PlaygroundEvaluation(repository=url, commit=sha, playground=page, evaluation=evaluation)
    )


async def _commit(service: Service, user: User, body: ScriptCommit) -> tuple[str, str]:
    """Check the task, the name and the script, then commit the script: its
    repository's URL and the commit (nothing is written when a check fails)."""
    registry.get(body.task)  # an unknown task is refused before anything is written
    url = _repository(service, user.name, body.name)
    script = Script(body.script, body.task)

    def commit() -> str:
        check(body.script)
        message = body.message.strip() or f"playground: {body.task}"
        return service.hosted.commit(
            user.name,
            body.name,
            files(script, user.name, body.name),
            message,
            author=user.name,
            when=int(service.index.clock()),
        )

    return url, await run_in_threadpool(commit)


def _created(made: PlaygroundRun | PlaygroundEvaluation) -> JSONResponse:
    """201, with where the trial or evaluation is."""
    where = made.trial.url if isinstance(made, PlaygroundRun) else made.evaluation.url
    return JSONResponse(made.model_dump(mode="json"), status_code=201, headers={"Location": where})


def _page(base: str, user: str, name: str, sha: str) -> str:
    return f"{base}/playground?repo={user}/{name}&commit={sha}"


@router.get("/api/playground/{user}/{name}", responses=responses(404, 422))
def read_script(
    user: str,
    name: str,
    service: Lab,
    commit: Annotated[str | None, Query(pattern="^[0-9a-f]{40}$")] = None,
) -> PlaygroundScript:
    """The script of playground repository ``user/name`` at ``commit`` (default: its
    newest), and its task."""
    return playground_script(service, user, name, commit)


def playground_script(
    service: Service, user: str, name: str, commit: str | None
) -> PlaygroundScript:
    """The script of ``user/name`` at ``commit`` (404 if there is none)."""
    sha = commit or service.hosted.head(user, name)
    if sha is None:
        raise ApiError(404, f"{user} has no playground repository {name!r}")
    script = script_of(service.hosted.read(user, name, sha))
    if script is None:
        raise ApiError(404, f"{user}/{name} at {sha[:12]} holds no playground script")
    return PlaygroundScript(
        user=user,
        name=name,
        repository=_repository(service, user, name),
        commit=sha,
        task=script.task,
        script=script.text,
    )


def _repository(service: Service, user: str, name: str) -> str:
    """The URL of ``user``'s hosted repository ``name`` (503 before the lab serves)."""
    if service.git_url is None:
        raise ApiError(
            503,
            "this lab does not serve its repositories over HTTP (it runs without labd"
            " serve's HTTP port), so the playground cannot commit",
            headers={"Retry-After": "60"},
        )
    service.hosted.path(user, name)  # a bad name is refused here, with its rule
    return f"{service.git_url}/{user}/{name}.git"
