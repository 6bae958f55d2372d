"""Repositories by URL: the operator's fetch policy, the mirror cache, refs to commits.

``resolve`` is what a submission calls. It checks the repository against the policy,
fetches it into a bare mirror under ``cache/mirrors`` and resolves the ref (a branch, a
tag, a full or abbreviated commit; HEAD by default) to the full commit the trial will
run and nothing else, all within ``resolve_timeout`` (the submitter is waiting).
``fetch_commit`` is what a trial's checkout calls: the same, except that a commit
already in the mirror is used without going to the network, so a rerun of an old
commit works after its branch has moved on.

The mirror cache:

- one bare mirror per repository (branches and tags only), named by a hash of the URL;
  a local repository path is mirrored too, so a trial does not depend on the folder;
- a new mirror is cloned into ``<mirror>.partial`` and renamed when complete, so a
  failed fetch leaves nothing behind; an update that fails leaves the old mirror as it
  was (git moves refs only at the end; its temporary packs and locks are removed);
- each resolved commit is pinned (``refs/pins/<commit>``) and git never collects
  garbage here, so a commit once resolved stays for reruns;
- no hooks run, and git follows no submodules: ``.gitmodules`` is read here, each URL
  checked against the allow-list, and each submodule fetched into its own mirror.

The policy is one object the operator builds at start-up. Git is told to speak only
the allowed protocols (``protocol.allow``), so a redirect to another scheme fails too.
Local paths and ``file://`` URLs (``file``) are off unless the operator allows them: a
submitter would otherwise reach the lab's host. Even then the lab's own folders
(``lab_folders``: its mirrors, keys, records...) are refused, whatever path leads there.
Hosts are public ones only unless the operator allows private ones (``private_hosts``):
every address a host's name resolves to is checked, and git connects to the one checked,
following no redirect (``scheduler.hosts``); the lab's own repositories (``hosted``) are
fetched wherever the lab serves them: recorded under its public URL, from where this
process reaches it (``hosted_at``: a worker's ``--server``, the lab's own port), so a
record names the same repository whichever worker ran it. A repository's URL takes no
user name, password, query or fragment: the lab records it, and shows it to anyone who
reads the archive.
Fetching a repository and its submodules runs under one deadline (waiting for another
fetch of the same mirror included) and a size watch: git and everything it started are
killed past either.

How a credential travels: only in the environment of the one git process that fetches
(``http.<url>.extraHeader`` given through GIT_CONFIG_COUNT/KEY/VALUE, or an ssh key in
GIT_SSH_COMMAND). It is never written to the mirror, the URL that is recorded, a
message or log, or anything the controller sees. A fetch is first tried without it;
``public`` says whether that worked. Over ssh there is no anonymous access, so an ssh
repository is never public. The operator's own git configuration (credential helpers,
URL rewrites) is not read unless ``user_config`` is set, as for ``labd run``.

Errors are scheduler.errors.RepositoryError and its subclasses SchemeNotAllowed,
HostNotAllowed, Unreachable, RefNotFound, TooLarge, FetchTimeout and SubmoduleNotAllowed.
Every network failure of git is one ``Unreachable``, in the same words whatever git said:
git's words tell a closed port from an HTTP, TLS or WebSocket one, so they go to the log.
(``max_checkout_bytes`` and ``max_checkout_files`` are for scheduler.source, which
expands commits.)
"""

from __future__ import annotations

import base64
import contextlib
import fcntl
import hashlib
import ipaddress
import logging
import os
import posixpath
import re
import shlex
import shutil
import signal
import subprocess
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from urllib.parse import unquote, urljoin, urlsplit

import git

from repository.masking import mask_text, mask_url
from repository.units import MiB
from scheduler.errors import (
    FetchTimeout,
    RefNotFound,
    RepositoryError,
    SchemeNotAllowed,
    SubmoduleNotAllowed,
    TooLarge,
    Unreachable,
)
from scheduler.hosts import Pinned, endpoint, pin

log = logging.getLogger("scheduler.fetch")
DEFAULT_SCHEMES = frozenset({"https", "ssh", "git"})  # file (local paths): the operator's call
ALL_SCHEMES = DEFAULT_SCHEMES | {"http", "file"}
MAX_DEPTH = 8  # submodules of submodules, at most this deep
POLL = 0.05  # seconds between looks at a running fetch's size
SCHEME = re.compile(r"^([A-Za-z][A-Za-z0-9+.-]*)://")
TRANSPORT = re.compile(r"^([A-Za-z][A-Za-z0-9+.-]*)::")  # git's <transport>::<address>
SCP = re.compile(r"^(?:[^@/\s]+@)?(?:\[[0-9A-Fa-f:.]+\]|[\w.-]+):(?!//)")  # user@host:path
CONTROL = re.compile(r"[\x00-\x1f\x7f]")
# What rev-parse would read as more than a name: ranges, ancestry, reflogs, searches.
NOT_A_NAME = re.compile(r"[\s~^:?*\[\\\x00-\x1f\x7f]|\.\.|@\{|^-|^/|/$|\.lock$|^@$")
HEX = re.compile(r"^[0-9a-fA-F]{4,40}$")
SHA = re.compile(r"^[0-9a-f]{40}$")
AUTH_FAILED = re.compile(
    r"Authentication failed|could not read (?:Username|Password)|terminal prompts disabled"
    r"|Permission denied \(|returned error: 40[13]|HTTP 40[13]",
    re.IGNORECASE,
)
# the rest of a hosted repository's URL: user and name as the lab's names go (index.NAME)
HOSTED_PATH = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}/[A-Za-z0-9][A-Za-z0-9._-]{0,63}\.git")
BRANCHES_AND_TAGS = ("+refs/heads/*:refs/heads/*", "+refs/tags/*:refs/tags/*")


@dataclass(frozen=True)
class Credential:
    """Access to private repositories whose URL starts with ``prefix``.

    ``token`` is sent over https as HTTP Basic ``username:token`` (GitHub and GitLab
    take a token with any user name); ``ssh_key`` is a private key file for ssh URLs.
    """

    prefix: str
    token: str | None = field(default=None, repr=False)
    username: str = "x-access-token"
    ssh_key: Path | None = None

    def serves(self, location: Location) -> bool:
        if not location.url.startswith(self.prefix):
            return False
        if location.scheme in ("https", "http"):
            return self.token is not None
        return location.scheme == "ssh" and self.ssh_key is not None


@dataclass(frozen=True)
class FetchPolicy:
    """What a lab fetches, and how: the operator's choice, built once at start-up.

    ``schemes``: https, http, ssh, git, file (local paths and file:// URLs).
    ``submodules``: URL prefixes of the submodules that may be followed (end a prefix
    with ``/`` to mean a folder); ``("",)`` follows any.
    ``lab_folders``: folders of the lab itself (its cache of mirrors, its keys...), never
    taken as a repository even when local paths are allowed.
    ``hosted``: URL prefixes of the repositories the lab hosts itself (the playground's,
    ``http://LAB/git/``), fetched whatever ``schemes`` says of their scheme: they are the
    lab's own, served read-only by git's smart HTTP, so at whatever address it has.
    ``hosted_at``: the prefix they are fetched from, when that is not the one they are
    recorded under (``PUBLIC/git/``, where people reach the lab): a worker fetches them
    from its own ``--server``, whatever a lab's public URL says, so it never contacts
    another host for them; the mirror and the record keep the recorded URL.
    ``private_hosts``: hosts at addresses that are not public (loopback, the lab's own
    network...) are fetched from too; otherwise refused before any connection.
    """

    schemes: frozenset[str] = DEFAULT_SCHEMES
    max_bytes: int = 512 * MiB  # a mirror: all branches and tags, as git stores them
    max_checkout_bytes: int = 512 * MiB  # a commit's files, expanded (scheduler.source)
    max_checkout_files: int = 100_000  # and how many files and links they are
    timeout: float = 300.0  # seconds for fetching a repository and its submodules
    resolve_timeout: float = 60.0  # the same at submit time, when the submitter waits
    submodules: tuple[str, ...] = ()
    credentials: tuple[Credential, ...] = ()
    user_config: bool = False  # read ~/.gitconfig (helpers, rewrites): one's own machine only
    lab_folders: tuple[Path, ...] = ()
    hosted: tuple[str, ...] = ()
    hosted_at: str | None = None  # None: fetched where recorded
    private_hosts: bool = False  # fetch from loopback, link-local and private addresses too

    def credential_for(self, location: Location) -> Credential | None:
        """The credential for this URL: the one with the longest matching prefix."""
        usable = [c for c in self.credentials if c.serves(location)]
        return max(usable, key=lambda c: len(c.prefix)) if usable else None

    def secrets(self) -> list[str]:
        """What must never appear in a message: the tokens, and their Basic encodings."""
        found = []
        for credential in self.credentials:
            if credential.token:
                found += [credential.token, _basic(credential)]
        return found


# labd run on one's own machine: any scheme, any submodule, any host, one's own git
# configuration (whoever runs it reaches that machine's network already).
PREFLIGHT = FetchPolicy(schemes=ALL_SCHEMES, submodules=("",), user_config=True, private_hosts=True)


@dataclass(frozen=True)
class Location:
    """Where a repository is: the URL git fetches from and the lab records (a local
    repository's absolute path for a local one), and its scheme."""

    url: str
    scheme: str


@dataclass(frozen=True)
class Resolved:
    """A submission's repository (as recorded) and ref, pinned to one commit."""

    repository: str
    ref: str | None
    commit: str
    public: bool  # fetched without any credential of the lab's


@dataclass(frozen=True)
class Submodule:
    path: str  # where its files go, relative to the top repository's root
    repository: str
    commit: str
    mirror: Path


@dataclass(frozen=True)
class Fetched:
    """A commit in the mirror cache, ready to export, with its submodules (outer first)."""

    repository: str
    commit: str
    mirror: Path
    public: bool | None  # None when nothing was fetched (the commit was in the mirror)
    submodules: tuple[Submodule, ...] = ()


def resolve(repository: str, ref: str | None, cache: Path, policy: FetchPolicy) -> Resolved:
    """Fetch ``repository`` under ``policy`` and pin ``ref`` (None: HEAD) to a commit,
    within the policy's ``resolve_timeout`` (or its ``timeout``, if shorter)."""
    fetched = fetch_commit(repository, ref, cache, submitting(policy), refresh=True)
    return Resolved(fetched.repository, ref, fetched.commit, fetched.public is True)


def submitting(policy: FetchPolicy) -> FetchPolicy:
    """The policy for what a submission does while its submitter waits: the same, with
    the shorter of the two deadlines."""
    return replace(policy, timeout=min(policy.timeout, policy.resolve_timeout))


def fetch_commit(
    repository: str, ref: str | None, cache: Path, policy: FetchPolicy, *, refresh: bool = False
) -> Fetched:
    """The commit ``ref`` of ``repository`` in the mirror cache, and its submodules'.

    Without ``refresh``, a full commit id already in the mirror is taken from there.
    Everything (waiting for the mirror, fetching, submodules) ends within ``policy.timeout``.
    """
    deadline = time.monotonic() + policy.timeout
    return _fetch_commit(
        repository, ref, cache, policy, refresh=refresh, depth=0, deadline=deadline
    )


def locate(repository: str, policy: FetchPolicy) -> Location:
    """Check a repository against the policy's schemes and normalize it."""
    text = repository.strip()
    if not text:
        raise RepositoryError(repository, "give a git repository's URL or path")
    if CONTROL.search(text):
        raise RepositoryError(repr(text), "has control characters in it; give a plain URL")
    if match := TRANSPORT.match(text):
        raise SchemeNotAllowed(text, match.group(1).lower(), policy.schemes)
    if match := SCHEME.match(text):
        scheme = match.group(1).lower()
        scheme = {"git+ssh": "ssh", "ssh+git": "ssh"}.get(scheme, scheme)
        stripped = text.rstrip("/")
        url = text if stripped.endswith(":") else stripped
        try:
            parts = urlsplit(url)
            user, password = parts.username, parts.password
        except ValueError:
            raise RepositoryError(url, "is not a valid URL") from None
        if password is not None or (user is not None and scheme in ("http", "https")):
            raise RepositoryError(
                url,
                "has a user name or password in it; give the URL without them (the lab's"
                " operator sets up access to private repositories)",
            )
        if scheme not in policy.schemes and not _hosted(url, policy):
            raise SchemeNotAllowed(url, scheme, policy.schemes)
        if "?" in url or "#" in url:
            raise RepositoryError(
                url,
                "has a query or fragment in it; give the repository's URL without them (the"
                " lab records it, and shows it to anyone)",
            )
        if scheme == "file" and parts.netloc in ("", "localhost"):
            # file:///home/me/ctl is the folder /home/me/ctl: one repository, one name
            return _local(url, Path(unquote(parts.path)), policy)
        return Location(url, scheme)
    if SCP.match(text):
        if "ssh" not in policy.schemes:
            raise SchemeNotAllowed(text, "ssh", policy.schemes)
        return Location(text.rstrip("/"), "ssh")
    if "file" not in policy.schemes:
        raise SchemeNotAllowed(text, "file", policy.schemes)
    return _local(text, Path(text).expanduser(), policy)


def _hosted(url: str, policy: FetchPolicy) -> bool:
    """Whether ``url`` names one of the lab's own repositories: a hosted prefix, then
    ``USER/NAME.git`` and nothing more (no query, no ``..``)."""
    return hosted_source(url, policy) is not None


def hosted_source(url: str, policy: FetchPolicy) -> str | None:
    """Where git fetches ``url`` from if it names one of the lab's own repositories
    (``hosted_at`` + ``USER/NAME.git``, or ``url`` itself without ``hosted_at``); None
    for any other URL."""
    for prefix in policy.hosted:
        rest = url[len(prefix) :]
        if url.startswith(prefix) and HOSTED_PATH.fullmatch(rest) is not None:
            return f"{policy.hosted_at}{rest}" if policy.hosted_at is not None else url
    return None


def _local(given: str, path: Path, policy: FetchPolicy) -> Location:
    """A local repository's location: its real path, which must not be the lab's own."""
    real = path.resolve()
    for folder in policy.lab_folders:
        if real.is_relative_to(folder.resolve()):
            raise RepositoryError(
                given,
                "is in the lab's own folders (its mirrors of repositories, caches, keys,"
                " records or trials at work); give a repository of your own",
            )
    return Location(str(real), "file")


def _check_folder(location: Location) -> None:
    """A local path must be a repository's own folder (the lab runs whole repositories)."""
    if SCHEME.match(location.url):
        return
    path = Path(location.url)
    if not path.is_dir():
        raise Unreachable(str(path), "no such folder on the lab's machine", local=True)
    try:
        git.Repo(path).close()
    except git.InvalidGitRepositoryError:
        try:
            with git.Repo(path, search_parent_directories=True) as outer:
                root = outer.working_tree_dir
        except git.InvalidGitRepositoryError:
            raise RepositoryError(
                str(path), "is not a git repository; the lab runs commits, so commit the code"
            ) from None
        raise RepositoryError(
            str(path), f"is a folder inside the git repository {root}; give {root} itself"
        ) from None


def mirror_path(cache: Path, url: str) -> Path:
    return cache / "mirrors" / hashlib.sha256(url.encode()).hexdigest()[:24]


def git_environment(
    location: Location,
    policy: FetchPolicy,
    credential: Credential | None,
    pinned: Pinned | None = None,
) -> dict[str, str]:
    """The environment of one fetching git process: the policy as git configuration.

    ``pinned``: the checked address git connects to for the host's name (curl and ssh
    are told it; a git:// URL carries it, ``fetch_url``), redirects not followed."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("GIT_")}
    env |= {"GIT_TERMINAL_PROMPT": "0", "GIT_ASKPASS": "true", "GIT_CONFIG_NOSYSTEM": "1"}
    if not policy.user_config:
        env["GIT_CONFIG_GLOBAL"] = "/dev/null"
    schemes = set(policy.schemes)
    source = hosted_source(location.url, policy)
    if source is not None:
        # the lab's own repository, over its own HTTP port (wherever this process reaches it)
        schemes |= {location.scheme, urlsplit(source).scheme}
    config = [
        ("core.hooksPath", "/dev/null"),
        ("protocol.allow", "never"),
        *((f"protocol.{scheme}.allow", "always") for scheme in sorted(schemes)),
        ("gc.auto", "0"),  # pinned commits stay
        ("maintenance.auto", "false"),
        ("transfer.unpackLimit", "1"),  # always a pack: few files, and watchable as it grows
        ("fetch.recurseSubmodules", "false"),
        ("submodule.recurse", "false"),
    ]
    if source is not None and _loopback(source):
        # the lab on this machine, never through the environment's proxy (whose own
        # loopback is not this one); empty, git sets no proxy for this URL
        config.append((f"http.{source}.proxy", ""))
    ssh = ["ssh", "-o", "BatchMode=yes"]
    if pinned is not None:
        config.append(("http.followRedirects", "false"))  # not to an address unchecked
    if pinned is not None and pinned.name:
        config.append(("http.curloptResolve", pinned.resolve))
        # the host key is still the name's (known_hosts says [name]:port off port 22)
        alias = pinned.host if pinned.port == 22 else f"[{pinned.host}]:{pinned.port}"
        ssh += ["-o", f"HostName={pinned.address}", "-o", f"HostKeyAlias={alias}"]
    if credential is not None and location.scheme in ("https", "http") and credential.token:
        # Keyed by this repository's URL: sent to it and below it, not after a redirect.
        config.append((f"http.{location.url}.extraHeader", f"Authorization: {_basic(credential)}"))
    if credential is not None and location.scheme == "ssh" and credential.ssh_key:
        ssh += ["-i", str(credential.ssh_key), "-o", "IdentitiesOnly=yes"]
    env["GIT_SSH_COMMAND"] = shlex.join(ssh)
    env["GIT_CONFIG_COUNT"] = str(len(config))
    for i, (key, value) in enumerate(config):
        env[f"GIT_CONFIG_KEY_{i}"] = key
        env[f"GIT_CONFIG_VALUE_{i}"] = value
    return env


def _fetch_commit(
    repository: str,
    ref: str | None,
    cache: Path,
    policy: FetchPolicy,
    *,
    refresh: bool,
    depth: int,
    deadline: float,
) -> Fetched:
    location = locate(repository, policy)
    if ref is not None and NOT_A_NAME.search(ref):
        raise RefNotFound(location.url, ref)
    mirror = mirror_path(cache, location.url)
    public: bool | None = None
    with _locked(cache, mirror.name, deadline, location.url, policy):
        pinned = ref is not None and SHA.match(ref.lower()) is not None
        if refresh or not (pinned and _has_commit(mirror, ref or "")):
            public = _fetch(location, mirror, policy, deadline)
            if pinned and not _has_commit(mirror, ref or ""):
                # Not on any branch or tag (any more): servers may still give it by id.
                with contextlib.suppress(Unreachable):
                    _fetch(location, mirror, policy, deadline, refspecs=(ref or "",))
        with git.Repo(mirror) as repo:
            commit = _commit(repo, location.url, ref)
            # A ref update would run the reference-transaction hook: none may run here.
            repo.git(c="core.hooksPath=/dev/null").update_ref(f"refs/pins/{commit}", commit)
            gitmodules = _gitmodules(repo, location, commit, policy)
    submodules: list[Submodule] = []
    for path, url, sub_commit in gitmodules:
        if depth >= MAX_DEPTH:
            raise RepositoryError(location.url, f"has submodules nested over {MAX_DEPTH} deep")
        inner = _fetch_commit(
            url, sub_commit, cache, policy, refresh=refresh, depth=depth + 1, deadline=deadline
        )
        public = public and inner.public
        submodules.append(Submodule(path, inner.repository, inner.commit, inner.mirror))
        submodules += [
            Submodule(f"{path}/{s.path}", s.repository, s.commit, s.mirror)
            for s in inner.submodules
        ]
    return Fetched(location.url, commit, mirror, public, tuple(submodules))


def _fetch(
    location: Location,
    mirror: Path,
    policy: FetchPolicy,
    deadline: float,
    refspecs: tuple[str, ...] = (),
) -> bool:
    """Clone or update ``mirror``; whether that worked without a credential."""
    if location.scheme == "file":
        _check_folder(location)
    pinned = check_host(location, policy)
    credential = policy.credential_for(location)
    attempts: list[Credential | None] = [None]
    if credential is not None:
        # Over ssh the key is the only way in; over https, try anonymously first.
        attempts = [credential] if location.scheme == "ssh" else [None, credential]
    started = time.monotonic()
    for attempt in attempts:
        try:
            _fetch_once(
                location, mirror, policy, attempt, pinned, deadline=deadline, refspecs=refspecs
            )
        except _GitFailed as failed:
            if attempt is attempts[-1]:
                detail = mask_text(_scrub(_reason(failed.stderr), policy))
                auth = bool(AUTH_FAILED.search(failed.stderr))
                # git's words for the operator only: told to the submitter, they map ports
                log.info("%s could not be fetched: %s", mask_url(location.url), detail)
                raise Unreachable(location.url, detail, auth=auth) from None
            continue
        how = (
            "without a lab credential"
            if attempt is None
            else f"with the credential for {attempt.prefix}"
        )
        log.info("%s fetched %s in %.2f s", mask_url(location.url), how, time.monotonic() - started)
        return attempt is None and location.scheme != "ssh"
    raise AssertionError("unreachable: the last attempt returns or raises")


def _fetch_once(
    location: Location,
    mirror: Path,
    policy: FetchPolicy,
    credential: Credential | None,
    pinned: Pinned | None,
    *,
    deadline: float,
    refspecs: tuple[str, ...],
) -> None:
    env = git_environment(location, policy, credential, pinned)
    url = hosted_source(location.url, policy) or fetch_url(location, pinned)
    if mirror.is_dir():
        command = ["-C", str(mirror), "fetch", "--quiet", "--no-write-fetch-head"]
        if not refspecs:
            command.append("--prune")
        command += ["--", url, *(refspecs or BRANCHES_AND_TAGS)]
        try:
            _run(command, env, mirror, deadline=deadline, policy=policy, source=location.url)
        except BaseException:
            _tidy(mirror)
            raise
        size = _size(mirror)
        if size > policy.max_bytes:
            raise TooLarge(location.url, policy.max_bytes, size)
        return
    partial = mirror.with_name(mirror.name + ".partial")
    shutil.rmtree(partial, ignore_errors=True)
    try:
        command = ["clone", "--bare", "--quiet", "--no-local", "--", url, str(partial)]
        _run(command, env, partial, deadline=deadline, policy=policy, source=location.url)
        size = _size(partial)
        if size > policy.max_bytes:
            raise TooLarge(location.url, policy.max_bytes, size)
        partial.rename(mirror)
    finally:
        shutil.rmtree(partial, ignore_errors=True)


def check_host(location: Location, policy: FetchPolicy) -> Pinned | None:
    """The checked address git is to connect to (``scheduler.hosts``); None when there is
    nothing to check: a local repository, one of the lab's own, or a lab that allows
    private hosts. ``HostNotAllowed`` (or ``Unreachable``) before any connection."""
    if policy.private_hosts or _hosted(location.url, policy):
        return None
    found = endpoint(location.url, location.scheme)
    if found is None:
        return None
    try:
        return pin(location.url, *found)
    except Unreachable as err:  # the resolver's words, like git's, for the log only
        log.info("%s could not be fetched: %s", mask_url(location.url), err.detail)
        raise


def _loopback(url: str) -> bool:
    """Whether ``url``'s host is this machine's loopback (``localhost`` or an address)."""
    host = urlsplit(url).hostname or ""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def fetch_url(location: Location, pinned: Pinned | None) -> str:
    """The URL git is given: the recorded one, except that git's own protocol (which
    has no option to pin a name's address) is given the checked address instead."""
    if pinned is None or not pinned.name or location.scheme != "git":
        return location.url
    parts = urlsplit(location.url)
    user = parts.netloc.rpartition("@")[0]
    netloc = f"{user}@" if user else ""
    netloc += pinned.bracketed + (f":{parts.port}" if parts.port else "")
    return parts._replace(netloc=netloc).geturl()


class _GitFailed(Exception):
    def __init__(self, stderr: str) -> None:
        super().__init__(stderr)
        self.stderr = stderr


def _run(
    args: list[str],
    env: dict[str, str],
    watch: Path,
    *,
    deadline: float,
    policy: FetchPolicy,
    source: str,
) -> None:
    """Run one git command that fetches, killing it and all it started past the deadline
    or once ``watch`` grows over the size limit.

    subprocess rather than GitPython here: the size watch needs the running process, and
    stopping a fetch means stopping its process group (git-remote-https, index-pack...).
    """
    with tempfile.TemporaryFile() as stderr:
        process = subprocess.Popen(  # noqa: S603 - a fixed git command, the URL after --
            [_git_executable(), *args],
            env=env,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=stderr,
            start_new_session=True,
        )
        try:
            while True:
                try:
                    process.wait(timeout=max(0.0, min(POLL, deadline - time.monotonic())))
                    break
                except subprocess.TimeoutExpired:
                    pass
                size = _size(watch)
                if size > policy.max_bytes:
                    raise TooLarge(source, policy.max_bytes, size)
                if time.monotonic() >= deadline:
                    raise FetchTimeout(source, policy.timeout)
        finally:
            if process.returncode is None:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(process.pid, signal.SIGKILL)
                process.wait()
        if process.returncode != 0:
            stderr.seek(0)
            raise _GitFailed(stderr.read().decode(errors="replace"))


def _commit(repo: git.Repo, source: str, ref: str | None) -> str:
    try:
        found = repo.git.rev_parse(
            "--verify", "--quiet", "--end-of-options", f"{ref or 'HEAD'}^{{commit}}"
        )
        return str(found).strip()
    except git.GitCommandError:
        pass
    if ref is not None and HEX.match(ref) and len(ref) < 40:
        with contextlib.suppress(git.GitCommandError):
            if len(str(repo.git.rev_parse(f"--disambiguate={ref.lower()}")).split()) > 1:
                raise RefNotFound(source, ref, ambiguous=True)
    raise RefNotFound(source, ref)


def _has_commit(mirror: Path, commit: str) -> bool:
    if not mirror.is_dir():
        return False
    with git.Repo(mirror) as repo:
        try:
            repo.git.cat_file("-e", f"{commit}^{{commit}}")
        except git.GitCommandError:
            return False
        return True


def _gitmodules(
    repo: git.Repo, location: Location, commit: str, policy: FetchPolicy
) -> list[tuple[str, str, str]]:
    """The submodules of ``commit`` as (path, URL, commit), each checked against the
    allow-list; only those with a gitlink in the tree (git ignores the others too)."""
    if not repo.git.ls_tree(commit, "--", ".gitmodules"):
        return []
    try:
        listed = str(repo.git.config("-z", "--blob", f"{commit}:.gitmodules", "--list"))
    except git.GitCommandError as err:
        raise RepositoryError(
            location.url, f"has a .gitmodules git cannot read: {_reason(str(err.stderr))}"
        ) from None
    paths: dict[str, str] = {}
    urls: dict[str, str] = {}
    for entry in listed.split("\0"):
        key, _, value = entry.partition("\n")
        name, _, field_ = key.removeprefix("submodule.").rpartition(".")
        if key.startswith("submodule.") and field_ == "path":
            paths[name] = value
        elif key.startswith("submodule.") and field_ == "url":
            urls[name] = value
    wanted = {paths[name]: urls[name] for name in paths if name in urls}
    if not wanted:
        return []
    gitlinks = {}
    for line in str(repo.git.ls_tree("-z", commit, "--", *sorted(wanted))).split("\0"):
        meta, _, path = line.partition("\t")
        mode, kind, sha = [*meta.split(), "", "", ""][:3]
        if mode == "160000" and kind == "commit":
            gitlinks[path] = sha
    found = []
    for path, sha in sorted(gitlinks.items()):
        url = _join(location, wanted[path])
        if not any(url.startswith(prefix) for prefix in policy.submodules):
            raise SubmoduleNotAllowed(location.url, path, url, policy.submodules)
        found.append((path, url, sha))
    return found


def _join(base: Location, url: str) -> str:
    """A submodule URL, made absolute the way git does (relative to the superproject)."""
    if not url.startswith(("./", "../")):
        return url.rstrip("/")
    if SCHEME.match(base.url):
        return urljoin(base.url + "/", url).rstrip("/")
    if base.scheme == "file":
        return os.path.normpath(os.path.join(base.url, url))
    host, _, path = base.url.partition(":")
    return f"{host}:{posixpath.normpath(posixpath.join(path or '.', url))}"


@contextlib.contextmanager
def _locked(
    cache: Path, name: str, deadline: float, source: str, policy: FetchPolicy
) -> Iterator[None]:
    """One fetch of a mirror at a time, across threads and processes; waiting for the
    mirror counts against the deadline (many submissions of one silent server queue
    here, and each must end in time)."""
    locks = cache / "locks"
    locks.mkdir(parents=True, exist_ok=True)
    with (locks / name).open("a") as handle:
        while True:
            try:
                fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() >= deadline:
                    raise FetchTimeout(source, policy.timeout) from None
                time.sleep(POLL)  # flock has no timeout of its own
        yield


def _tidy(mirror: Path) -> None:
    """Remove what a stopped fetch leaves: temporary packs and lock files."""
    for root, _, names in os.walk(mirror):
        for name in names:
            if name.startswith("tmp_") or name.endswith(".lock"):
                with contextlib.suppress(OSError):
                    os.unlink(os.path.join(root, name))


def _size(folder: Path) -> int:
    total = 0
    for root, _, names in os.walk(folder):
        for name in names:
            with contextlib.suppress(OSError):
                total += os.lstat(os.path.join(root, name)).st_size
    return total


def _git_executable() -> str:
    return str(git.Git.GIT_PYTHON_GIT_EXECUTABLE or "git")


def _basic(credential: Credential) -> str:
    pair = f"{credential.username}:{credential.token}".encode()
    return "Basic " + base64.b64encode(pair).decode()


def _reason(stderr: str) -> str:
    """Git's own last words, without its ``fatal:`` prefix."""
    lines = [line.strip() for line in stderr.strip().splitlines() if line.strip()]
    if not lines:
        return "git failed"
    for prefix in ("fatal: ", "error: "):
        lines[-1] = lines[-1].removeprefix(prefix)
    return lines[-1]


def _scrub(text: str, policy: FetchPolicy) -> str:
    for secret in policy.secrets():
        text = text.replace(secret, "***")
    return text
