"""Real git repositories in a folder, and a real smart-HTTP git server for them.

Make a repository (a real ``git init``, real commits with a fixed author):

    repo = GitRepo.create(tmp_path / "served" / "robot", {"lab.toml": "...", "c.py": "..."})
    first = repo.commit({"c.py": "print(2)\\n"}, "second")   # returns the full commit id
    repo.tag("v1")                   # at HEAD, or tag("v1", at=first)
    repo.branch("dev", at=first)     # force=True to move an existing branch
    repo.commit({"c.py": None})      # None deletes a file; bytes are written as they are
    repo.commit({"data": Link("/mnt/x")})   # a symbolic link, committed as git keeps one
    repo.add_submodule("lib", "../lib", commit)   # a gitlink and .gitmodules, no clone
    repo.rev("v1"), repo.path, repo.url  # full commit id; the folder; a file:// URL
    repo.git("log", "--oneline")     # any git command in it (input= its stdin); returns stdout

Serve a folder of repositories over HTTP (``git http-backend`` as CGI, protocol v2,
on 127.0.0.1 and a free port):

    with GitHttpServer(tmp_path / "served") as server:
        server.url("robot")          # http://127.0.0.1:PORT/robot
    server = GitHttpServer(root, users={"bot": "s3cret"}, private={"secret-robot"})
    server.start(); ...; server.close()

Repositories named in ``private`` answer 401 without HTTP Basic credentials from
``users``. ``server.requests`` lists what was asked (method, path, user, whether an
Authorization header came). ``stalled_url()`` gives a URL of a server that accepts
connections and never answers, for time limits; close it with ``close()`` as well.
"""

from __future__ import annotations

import base64
import binascii
import contextlib
import os
import shutil
import socket
import subprocess
import threading
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from types import TracebackType
from typing import BinaryIO
from urllib.parse import unquote

GIT_ENV = {
    "GIT_AUTHOR_NAME": "Test",
    "GIT_AUTHOR_EMAIL": "test@example.org",
    "GIT_COMMITTER_NAME": "Test",
    "GIT_COMMITTER_EMAIL": "test@example.org",
    "GIT_CONFIG_GLOBAL": "/dev/null",
    "GIT_CONFIG_NOSYSTEM": "1",
}


@dataclass(frozen=True)
class Link:
    """A symbolic link for ``GitRepo.commit`` to make: ``{"data": Link("/mnt/x")}``."""

    target: str


class GitRepo:
    """A git work tree made for a test."""

    def __init__(self, path: Path) -> None:
        self.path = path

    @classmethod
    def create(
        cls,
        path: Path,
        files: Mapping[str, str | bytes | Link | None] | None = None,
        message: str = "first",
        *,
        branch: str = "main",
    ) -> GitRepo:
        """``git init`` in ``path`` (made if missing), and a first commit of ``files``."""
        path.mkdir(parents=True, exist_ok=True)
        repo = cls(path)
        repo.git("init", "-q", "-b", branch)
        if files is not None:
            repo.commit(files, message)
        return repo

    @property
    def url(self) -> str:
        return f"file://{self.path.resolve()}"

    def git(self, *args: str, input: str | None = None) -> str:
        env = {k: v for k, v in os.environ.items() if not k.startswith("GIT_")} | GIT_ENV
        done = subprocess.run(
            ["git", "-C", str(self.path), *args],
            check=True,
            capture_output=True,
            text=True,
            env=env,
            input=input,
        )
        return done.stdout.strip()

    def commit(
        self, files: Mapping[str, str | bytes | Link | None], message: str = "change"
    ) -> str:
        """Write (str or bytes), link (Link) or delete (None) files, commit all, return
        the commit id."""
        for name, content in files.items():
            target = self.path / name
            if content is None:
                target.unlink()
                continue
            target.parent.mkdir(parents=True, exist_ok=True)
            if isinstance(content, Link):
                target.unlink(missing_ok=True)
                target.symlink_to(content.target)
            elif isinstance(content, bytes):
                target.write_bytes(content)
            else:
                target.write_text(content)
        self.git("add", "-A")
        self.git("commit", "-q", "--allow-empty", "-m", message)
        return self.rev()

    def add_submodule(self, path: str, url: str, commit: str, message: str = "submodule") -> str:
        """Record a submodule at ``path`` pinned to ``commit`` (no clone), and commit."""
        self.git("config", "-f", ".gitmodules", f"submodule.{path}.path", path)
        self.git("config", "-f", ".gitmodules", f"submodule.{path}.url", url)
        self.git("update-index", "--add", "--cacheinfo", f"160000,{commit},{path}")
        self.git("add", ".gitmodules")
        self.git("commit", "-q", "-m", message)
        return self.rev()

    def tag(self, name: str, at: str = "HEAD") -> None:
        self.git("tag", name, at)

    def branch(self, name: str, at: str = "HEAD", *, force: bool = False) -> None:
        self.git("branch", *(["-f"] if force else []), name, at)

    def switch(self, name: str) -> None:
        self.git("switch", "-q", name)

    def rev(self, ref: str = "HEAD") -> str:
        return self.git("rev-parse", "--verify", f"{ref}^{{commit}}")


@dataclass(frozen=True)
class Request:
    method: str
    path: str  # without the query
    user: str | None  # the authenticated user
    authorization: bool  # whether an Authorization header came at all


class GitHttpServer:
    """``git http-backend`` over HTTP for the repositories in ``root`` (see the module)."""

    def __init__(
        self,
        root: Path,
        *,
        users: Mapping[str, str] | None = None,
        private: Iterable[str] = (),
    ) -> None:
        self.root = root
        self.users = dict(users or {})
        self.private = set(private)
        self.requests: list[Request] = []
        self._httpd: ThreadingHTTPServer | None = None
        self._thread: threading.Thread | None = None
        self._stalls: list[socket.socket] = []

    @property
    def port(self) -> int:
        assert self._httpd is not None, "start() the server first"
        return int(self._httpd.server_address[1])

    def url(self, name: str) -> str:
        return f"http://127.0.0.1:{self.port}/{name}"

    def start(self) -> GitHttpServer:
        httpd = _Server(("127.0.0.1", 0), _Handler)
        httpd.git = self
        self._httpd = httpd
        self._thread = threading.Thread(
            target=httpd.serve_forever, args=(0.05,), name="git-http", daemon=True
        )
        self._thread.start()
        return self

    def stalled_url(self, name: str = "stalled") -> str:
        """A URL whose server accepts the connection and never says a word."""
        listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        listener.bind(("127.0.0.1", 0))
        listener.listen(8)  # the kernel completes connections; nobody ever reads them
        self._stalls.append(listener)
        return f"http://127.0.0.1:{listener.getsockname()[1]}/{name}"

    def close(self) -> None:
        for listener in self._stalls:
            listener.close()
        self._stalls.clear()
        if self._httpd is not None:
            self._httpd.shutdown()
            self._httpd.server_close()
            self._httpd = None
        if self._thread is not None:
            self._thread.join()
            self._thread = None

    def __enter__(self) -> GitHttpServer:
        return self.start()

    def __exit__(
        self,
        kind: type[BaseException] | None,
        error: BaseException | None,
        trace: TracebackType | None,
    ) -> None:
        self.close()

    def _user(self, header: str | None) -> str | None:
        if not header or not header.startswith("Basic "):
            return None
        try:
            user, _, password = base64.b64decode(header[6:]).decode().partition(":")
        except (binascii.Error, UnicodeDecodeError):
            return None
        return user if user in self.users and self.users[user] == password else None


class _Server(ThreadingHTTPServer):
    daemon_threads = True
    git: GitHttpServer


class _Handler(BaseHTTPRequestHandler):
    server: _Server

    def do_GET(self) -> None:
        self._serve()

    def do_POST(self) -> None:
        self._serve()

    def log_message(self, format: str, *args: object) -> None:
        pass  # quiet: a test reads server.requests instead

    def _serve(self) -> None:
        git = self.server.git
        path, _, query = self.path.partition("?")
        header = self.headers.get("Authorization")
        user = git._user(header)
        git.requests.append(Request(self.command, path, user, header is not None))
        name = unquote(path).lstrip("/").split("/", 1)[0]
        if name in git.private and user is None:
            self.send_response(401)
            self.send_header("WWW-Authenticate", 'Basic realm="git"')
            self.send_header("Content-Length", "0")
            self.end_headers()
            return
        env = {
            "PATH": os.environ.get("PATH", "/usr/bin:/bin"),
            "HOME": str(git.root),
            "GIT_CONFIG_NOSYSTEM": "1",
            "GIT_CONFIG_GLOBAL": "/dev/null",
            "GIT_PROJECT_ROOT": str(git.root),
            "GIT_HTTP_EXPORT_ALL": "1",
            "PATH_INFO": unquote(path),
            "QUERY_STRING": query,
            "REQUEST_METHOD": self.command,
            "CONTENT_TYPE": self.headers.get("Content-Type", ""),
            "REMOTE_ADDR": self.client_address[0],
        }
        if user is not None:
            env["REMOTE_USER"] = user
        if length := self.headers.get("Content-Length"):
            env["CONTENT_LENGTH"] = length
        if protocol := self.headers.get("Git-Protocol"):
            env["GIT_PROTOCOL"] = protocol
        if encoding := self.headers.get("Content-Encoding"):
            env["HTTP_CONTENT_ENCODING"] = encoding
        backend = subprocess.Popen(
            ["git", "http-backend"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            env=env,
        )
        assert backend.stdin is not None and backend.stdout is not None
        chunked = self.headers.get("Transfer-Encoding", "").lower() == "chunked"
        feeder = threading.Thread(
            target=_feed, args=(self.rfile, backend.stdin, length, chunked), daemon=True
        )
        feeder.start()
        try:
            status, headers = _cgi_headers(backend.stdout)
            self.send_response(status)
            for key, value in headers:
                self.send_header(key, value)
            self.end_headers()  # HTTP/1.0: the body ends when the connection closes
            shutil.copyfileobj(backend.stdout, self.wfile)
        except (BrokenPipeError, ConnectionResetError):
            pass  # the client went away (a fetch stopped at a limit)
        finally:
            backend.stdout.close()
            backend.wait()
            feeder.join()


def _feed(source: BinaryIO, sink: BinaryIO, length: str | None, chunked: bool) -> None:
    """Stream a request body into the CGI's stdin (Content-Length or chunked)."""
    try:
        if chunked:
            while size := int(source.readline().split(b";")[0].strip() or b"0", 16):
                sink.write(source.read(size))
                source.readline()
            source.readline()
        else:
            left = int(length or 0)
            while left > 0 and (block := source.read(min(left, 65536))):
                sink.write(block)
                left -= len(block)
    except (BrokenPipeError, ValueError):
        pass  # the backend stopped reading: its answer says why
    finally:
        with contextlib.suppress(BrokenPipeError):
            sink.close()


def _cgi_headers(stdout: BinaryIO) -> tuple[int, list[tuple[str, str]]]:
    status, headers = 200, []
    while line := stdout.readline().rstrip(b"\r\n"):
        key, _, value = line.decode("latin-1").partition(":")
        if key.lower() == "status":
            status = int(value.split()[0])
        else:
            headers.append((key.strip(), value.strip()))
    return status, headers
