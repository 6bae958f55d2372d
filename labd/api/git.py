"""The lab's hosted repositories over git's smart HTTP, read-only (``git http-backend``).

    GET  /git/USER/NAME.git/info/refs?service=git-upload-pack   the refs (protocol v0),
                                                                 or v2's capabilities
    POST /git/USER/NAME.git/git-upload-pack                      a fetch: the pack

so ``git clone http://HOST:PORT/git/alice/robot.git`` clones ``alice``'s playground
repository ``robot`` (``labd.hosted``), over protocol v2 or v0. Reading is public, as
the archive is. Nothing is written over HTTP: a push (``info/refs?service=
git-receive-pack`` or ``POST .../git-receive-pack``) is answered 403, and the backend
runs with ``http.receivepack=false`` besides. Any other path under ``/git`` is a 404,
and so is a user or repository name outside the hosted rule: names are checked before a
path is made of them, so no request reaches a file outside ``DATA/git``.

Each request runs git's own CGI program, ``git http-backend``, as an asyncio
subprocess (the event loop never waits on it): the request's body streams to its
standard input, its CGI headers become the answer's status and headers, and the rest of
its output streams to the client; what it writes on its standard error goes to the log.
The whole body is in before the answer starts, so a body over its limit is still
answered 413. Limits:

- a fetch's body: 16 MiB (``MAX_UPLOAD``; ``labd.api.edges`` holds every POST under
  ``/git/`` to it, as git's own buffer of a request is);
- 8 backends at once (``GitLimits.backends``); beyond, 503 with ``Retry-After``;
- 300 s per request (``GitLimits.timeout``), after which its backend is killed, as it is
  when the client goes away.

Errors are the lab's error table's (``labd.api.errors``), in plain text: git shows a
``text/plain`` body to its user (``remote: ...``), where JSON would be dropped.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import re
import signal
from dataclasses import dataclass
from urllib.parse import parse_qs

from starlette.datastructures import Headers
from starlette.exceptions import HTTPException
from starlette.responses import PlainTextResponse
from starlette.types import Message, Receive, Scope, Send

from labd.api import errors
from labd.api.errors import ApiError
from labd.errors import HostedError, NotHosted
from labd.hosted import HostedRepos, check_name, check_user, git_environment
from repository.units import MiB

MAX_UPLOAD = 16 * MiB  # bytes: the body of a fetch's POST
UPLOAD = "git-upload-pack"
PUSH = "git-receive-pack"
PUSH_REFUSED = (
    "the playground's repositories are written only through the playground (/playground);"
    " they cannot be pushed to"
)
CHUNK = 64 * 1024  # bytes read from the backend at a time
MAX_HEAD = 64 * 1024  # bytes of the backend's CGI headers
STDERR_LINES = 20  # lines of a backend's standard error logged per request
PROTOCOL = re.compile(r"[A-Za-z0-9=:._,-]{1,256}", re.ASCII)  # Git-Protocol: version=2
HOP = {b"connection", b"transfer-encoding", b"keep-alive"}  # never passed on


@dataclass(frozen=True)
class GitLimits:
    """How much the git routes take on at once, and for how long."""

    backends: int = 8  # git http-backend processes at once; beyond, 503
    timeout: float = 300.0  # seconds a request's backend may run
    retry_after: int = 5  # seconds a 503 asks a client to wait


@dataclass(frozen=True)
class Call:
    """A request the backend answers: whose repository, and which of the two routes."""

    user: str
    name: str
    method: str  # GET (the refs) or POST (a fetch)
    route: str  # info/refs or git-upload-pack
    query: str  # passed to the backend, rebuilt from what was checked

    @property
    def path_info(self) -> str:
        return f"/{self.user}/{self.name}.git/{self.route}"


def route(method: str, path: str, query: str) -> Call:
    """What a ``method`` request to ``/git`` + ``path`` asks, or the ApiError that
    answers it: 404 for a bad name or another path, 403 for a push, 405 for a method."""
    parts = path.split("/")
    if len(parts) < 4 or parts[0] != "" or not parts[2].endswith(".git"):
        raise ApiError(404, f"no repository at /git{path}: clone /git/USER/NAME.git")
    user, name, rest = parts[1], parts[2].removesuffix(".git"), "/".join(parts[3:])
    try:
        check_user(user)
        check_name(name)
    except HostedError as err:
        raise ApiError(404, f"no repository at /git{path}: {err}") from err
    services = parse_qs(query).get("service", [])
    if rest == PUSH or (rest == "info/refs" and PUSH in services):
        raise ApiError(403, PUSH_REFUSED)
    if rest == "info/refs" and services == [UPLOAD]:
        allowed, query = "GET", f"service={UPLOAD}"
    elif rest == UPLOAD:
        allowed, query = "POST", ""
    else:
        raise ApiError(
            404, f"/git{path} is not served: the lab serves git's smart HTTP (clone, fetch) only"
        )
    if method != allowed:
        raise ApiError(405, f"/git{path} does not take {method}", headers={"Allow": allowed})
    return Call(user, name, method, rest, query)


class _ClientGone(Exception):
    """The client went away: its backend is killed, and nobody is answered."""


class GitHttp:
    """ASGI app: the hosted repositories, read-only over smart HTTP (module docstring)."""

    def __init__(self, hosted: HostedRepos, limits: GitLimits | None = None) -> None:
        self.hosted = hosted
        self.limits = limits or GitLimits()
        self.running = 0  # backends now (one event loop: a plain count)
        self.log = logging.getLogger("labd.api.git")

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            if scope["type"] == "websocket":
                await send({"type": "websocket.close", "code": 1008})
            return
        started = False

        async def sending(message: Message) -> None:
            nonlocal started
            started = started or message["type"] == "http.response.start"
            await send(message)

        query = scope.get("query_string", b"").decode("latin-1")
        try:
            call = route(scope["method"], _route_path(scope), query)
            repo = self.hosted.path(call.user, call.name)
            root = self.hosted.root.resolve()
            if not repo.is_dir() or not repo.resolve().is_relative_to(root):
                raise NotHosted(call.user, call.name)
            if self.running >= self.limits.backends:
                raise ApiError(
                    503,
                    f"the lab is serving {self.running} git requests already, as many as it"
                    f" takes at once; try again in {self.limits.retry_after} s",
                    headers={"Retry-After": str(self.limits.retry_after)},
                )
            self.running += 1
            try:
                await self._serve(call, scope, receive, sending)
            finally:
                self.running -= 1
        except _ClientGone:
            self.log.info("%s %s: the client went away", scope["method"], scope["path"])
        except (ApiError, HTTPException, HostedError) as err:
            if started:  # too late for another answer: the client sees it cut short
                self.log.warning("%s %s cut short: %s", scope["method"], scope["path"], err)
                return
            said = errors.problem(err, scope["method"], scope["path"])
            errors.told(err, said, scope["method"], scope["path"])
            refusal = PlainTextResponse(said.message + "\n", said.status, headers=said.headers)
            await refusal(scope, receive, send)

    async def _serve(self, call: Call, scope: Scope, receive: Receive, send: Send) -> None:
        """Run the backend for ``call``, within the time limit, and kill it after."""
        where = f"{call.user}/{call.name}"
        process = await asyncio.create_subprocess_exec(
            "git",
            "http-backend",
            stdin=asyncio.subprocess.PIPE,
            stdout=asyncio.subprocess.PIPE,
            stderr=asyncio.subprocess.PIPE,
            env=self._environment(call, scope),
            start_new_session=True,  # its own process group: upload-pack is killed with it
        )
        told = asyncio.create_task(self._stderr(process, where))
        try:
            async with asyncio.timeout(self.limits.timeout):
                await self._exchange(process, call, receive, send)
            status = await process.wait()
            if status != 0:
                self.log.warning("%s: git http-backend exited with status %d", where, status)
        except TimeoutError as err:
            raise ApiError(
                504, f"git took longer than this lab's limit of {self.limits.timeout:g} s"
            ) from err
        finally:
            if process.returncode is None:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(process.pid, signal.SIGKILL)
                await process.wait()
            await told

    async def _exchange(
        self, process: asyncio.subprocess.Process, call: Call, receive: Receive, send: Send
    ) -> None:
        """The body in, the answer out."""
        assert process.stdout is not None
        await self._feed(process, receive, call.method == "POST")
        status, headers = await self._head(process.stdout)
        await send({"type": "http.response.start", "status": status, "headers": headers})
        gone = asyncio.create_task(_disconnected(receive))
        try:
            while True:
                read = asyncio.create_task(process.stdout.read(CHUNK))
                await asyncio.wait({read, gone}, return_when=asyncio.FIRST_COMPLETED)
                if not read.done():
                    read.cancel()
                    raise _ClientGone
                chunk = read.result()
                if not chunk:
                    break
                await send({"type": "http.response.body", "body": chunk, "more_body": True})
            await send({"type": "http.response.body", "body": b"", "more_body": False})
        finally:
            gone.cancel()

    async def _feed(
        self, process: asyncio.subprocess.Process, receive: Receive, has_body: bool
    ) -> None:
        """Stream the request's body to the backend, then close its input. The body is
        read to its end even if the backend stops reading (it answered an error), so
        that its size limit holds and the connection stays whole."""
        stdin = process.stdin
        assert stdin is not None
        writing, more = has_body, has_body
        while more:
            message = await receive()  # raises BodyTooLarge past MAX_UPLOAD (edges)
            if message["type"] == "http.disconnect":
                raise _ClientGone
            more = bool(message.get("more_body", False))
            body = message.get("body", b"")
            if writing and body:
                try:
                    stdin.write(body)
                    await stdin.drain()
                except (BrokenPipeError, ConnectionResetError):
                    writing = False
        with contextlib.suppress(BrokenPipeError, ConnectionResetError):
            stdin.close()
            await stdin.wait_closed()

    async def _head(self, stdout: asyncio.StreamReader) -> tuple[int, list[tuple[bytes, bytes]]]:
        """The backend's CGI headers: the status (``Status: 404 Not Found``; else 200),
        and the rest to pass on."""
        status, size = 200, 0
        headers: list[tuple[bytes, bytes]] = []
        while True:
            try:
                line = await stdout.readline()
            except ValueError:  # a line over the stream's limit
                line = b""
            size += len(line)
            if not line or size > MAX_HEAD:
                raise ApiError(500, "the lab's git server gave no answer; its log says why")
            line = line.rstrip(b"\r\n")
            if not line:
                return status, headers
            name, colon, value = line.partition(b":")
            name, value = name.strip().lower(), value.strip()
            if not colon:
                raise ApiError(500, "the lab's git server answered malformed headers")
            if name == b"status":
                code = value.split(b" ")[0]
                if not (code.isdigit() and 100 <= int(code) <= 599):
                    raise ApiError(500, "the lab's git server answered a malformed status")
                status = int(code)
            elif name not in HOP:
                headers.append((name, value))

    async def _stderr(self, process: asyncio.subprocess.Process, where: str) -> None:
        """Log what the backend says on its standard error (its first lines)."""
        assert process.stderr is not None
        logged = 0
        while chunk := await process.stderr.read(CHUNK):
            for line in chunk.decode(errors="replace").splitlines():
                if line.strip() and logged < STDERR_LINES:
                    self.log.warning("%s: git http-backend: %s", where, line.rstrip())
                    logged += 1

    def _environment(self, call: Call, scope: Scope) -> dict[str, str]:
        """The backend's CGI environment: the checked path, never the request's own."""
        headers = Headers(scope=scope)
        client = scope.get("client")
        env = {
            "GIT_PROJECT_ROOT": str(self.hosted.root),
            "GIT_HTTP_EXPORT_ALL": "1",
            "GIT_HTTP_MAX_REQUEST_BUFFER": str(MAX_UPLOAD),
            "PATH_INFO": call.path_info,
            "REQUEST_METHOD": call.method,
            "QUERY_STRING": call.query,
            "REMOTE_ADDR": client[0] if client else "",
            "GIT_CONFIG_COUNT": "1",
            "GIT_CONFIG_KEY_0": "http.receivepack",
            "GIT_CONFIG_VALUE_0": "false",
        }
        if "content-type" in headers:
            env["CONTENT_TYPE"] = headers["content-type"]
        if headers.get("content-length", "").isdigit():
            env["CONTENT_LENGTH"] = headers["content-length"]
        if "content-encoding" in headers:  # git gzips a large negotiation
            env["HTTP_CONTENT_ENCODING"] = headers["content-encoding"]
        protocol = headers.get("git-protocol", "")
        if PROTOCOL.fullmatch(protocol):
            env["GIT_PROTOCOL"] = protocol
        return git_environment(env)


async def _disconnected(receive: Receive) -> None:
    """Return once the client has gone (the request's body is all read by then)."""
    while (await receive())["type"] != "http.disconnect":
        pass


def _route_path(scope: Scope) -> str:
    """The request's path under the mount (``/USER/NAME.git/...``)."""
    path: str = scope["path"]
    root: str = scope.get("root_path", "")
    return path[len(root) :] if root and path.startswith(root) else path
