"""The build steps: a repository's requirements (pip) and npm packages, installed in the sandbox.

A step runs one installer in a sandbox like a controller's (the runtime read-only, no
code of the repository, its own uid), with larger limits and a writable target, and
with no network of its own: its only way out is the lab's proxy (``proxy.py``), served
for the step's duration on a unix socket bound into the sandbox and relayed by the
launcher to ``127.0.0.1:3128``, where the installer's proxy settings point. The proxy
reaches the configured registry, by host name and port, and nothing else:

- pip: the hosts of ``PIP_INDEX_URL`` (or pip's own default index) and of
  ``PIP_EXTRA_INDEX_URL``; when an index is pip's default one, also the host pip's
  default index serves its files from (both names read from the runtime's pip);
- npm: the host of ``npm_config_registry`` (or ``NPM_CONFIG_REGISTRY``, or npm's own
  default registry, read from the runtime's npm), which npm is then told explicitly.

So a lock file or a requirements file that names a URL on the lab machine (its loopback,
a link-local address, any other host) gets a 403 from the proxy, and the step's error
names what it could not reach. A registry the operator configured on the lab machine
itself (an index on 127.0.0.1) stays reachable: that is the operator's choice. The host's
own proxy settings are not given to the installer; the lab's proxy chains to them.

Nothing of the repository runs: pip takes wheels only (``--only-binary``, and direct
references must name wheels), npm runs no install scripts (``--ignore-scripts``).
"""

from __future__ import annotations

import errno
import functools
import os
import shutil
import stat
import subprocess
import tempfile
import urllib.request
from collections.abc import Awaitable, Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

from . import runtime as rt
from .api import PROXY_PORT, Exit, InstallError, Limits, MiB
from .jobs import Mount, Plan, environment, launcher_argv, open_socket
from .proxy import Destination, RegistryProxy

# pip with wheels only, npm without scripts; the registry is there, the repository's code is not.
INSTALL_LIMITS = Limits(
    cpus=2.0,
    cpu_seconds=1800,
    memory=2048 * MiB,
    processes=256,
    open_files=1024,
    output=8 * MiB,
    wall=900.0,
    scratch=2048 * MiB,
)
CERTIFICATES = f"{rt.MNT}/ca-certificates.crt"  # the host's trusted authorities
PROXY_URL = f"http://127.0.0.1:{PROXY_PORT}"  # inside: the launcher's relay to the proxy
# Options a requirements file may not use: they would build from source or run code.
_FORBIDDEN_OPTIONS = ("-e", "--editable", "--no-binary", "--use-pep517", "--no-build-isolation")
# Host settings pip inside the sandbox is told about (its indexes, how long to wait).
_PIP_PASSTHROUGH = (
    "PIP_INDEX_URL",
    "PIP_EXTRA_INDEX_URL",
    "PIP_TRUSTED_HOST",
    "PIP_DEFAULT_TIMEOUT",
)
# Where the host names npm's registry (npm reads either spelling).
_NPM_REGISTRY = ("npm_config_registry", "NPM_CONFIG_REGISTRY")
# Every spelling of the proxy settings pip (requests) and npm read, all set to the lab's.
_PROXY_VARIABLES = ("HTTP_PROXY", "HTTPS_PROXY", "http_proxy", "https_proxy")
_NPM_NOISE = ("code ", "errno ", "syscall ", "A complete log", "Log files were not written")
_QUERY_TIMEOUT = 60.0  # seconds to ask the runtime's pip or npm for its default registry


@dataclass(frozen=True)
class Step:
    """One build step: the installer's command line, and what it may reach."""

    tool: str  # "pip" or "npm"
    registry: str  # what it reaches, in a person's words
    argv: tuple[str, ...]  # the launcher's, relaying the proxy, then the installer's
    env: Mapping[str, str]
    mounts: tuple[Mount, ...]
    allowed: frozenset[Destination]

    def plan(self, proxy_socket: Path) -> Plan:
        """The step's plan, given the host socket its proxy serves on."""
        return Plan(
            argv=self.argv,
            env=self.env,
            mounts=self.mounts,
            bridge_socket=None,
            limits=INSTALL_LIMITS,
            proxy_socket=proxy_socket,
        )

    def failure(self, ended: Exit, refused: Sequence[str]) -> InstallError:
        """The InstallError of the step that ended so; ``refused``: what the proxy refused
        it, which is the reason when it did not run out of time or memory."""
        error = install_failure(ended, self.tool)
        if refused and not (ended.wall_exceeded or ended.out_of_memory):
            return InstallError(
                f"{self.tool} could not reach {refused[0]}: the build step reaches only the"
                f" configured {self.registry}",
                error.log,
            )
        return error


async def run_step(step: Step, run: Callable[[Plan], Awaitable[Exit]]) -> None:
    """Serve ``step``'s proxy, run its plan with ``run`` (a backend's start and wait), end
    the proxy, and raise the step's InstallError if the installer failed."""
    folder = Path(tempfile.mkdtemp(prefix="labd-proxy-", dir=_socket_parent()))
    try:
        folder.chmod(0o711)  # the sandbox's uid reaches the socket; nobody lists the folder
        upstream = urllib.request.getproxies_environment()
        proxy = RegistryProxy(folder / "proxy.sock", step.allowed, upstream)
        async with proxy:
            open_socket(proxy.path)
            ended = await run(step.plan(proxy.path))
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    if ended.code != 0:
        raise step.failure(ended, proxy.refused)


def _socket_parent() -> str:
    """Where the proxy's socket folder goes: the temporary folder, unless its path is too
    long for a unix socket's (107 bytes, the folder's name and the socket's included)."""
    parent = tempfile.gettempdir()
    return parent if len(parent.encode()) <= 64 else "/tmp"  # noqa: S108 - a private folder


def pip_step(runtime: rt.Runtime, staged_requirements: Path, target: Path) -> Step:
    """``pip install`` of a staged requirements file into ``target``, wheels only.

    Blocks a moment the first time (it asks the runtime's pip for its default index).
    """
    command = (
        "python",
        "-m",
        "pip",
        "install",
        "--no-input",
        "--disable-pip-version-check",
        "--no-cache-dir",
        "--progress-bar",
        "off",
        "--no-warn-script-location",
        "--only-binary=:all:",
        "--upgrade",
        "--target",
        rt.TARGET,
        "-r",
        f"{rt.REQUIREMENTS_DIR}/{staged_requirements.name}",
    )
    env = environment(runtime, bridge=False, python_paths=0, extra={})
    env["PYTHONPATH"] = rt.PIP_PATH  # pip, and nothing of the runtime's packages
    env["PIP_ONLY_BINARY"] = ":all:"
    env.update({k: v for k, v in os.environ.items() if k in _PIP_PASSTHROUGH})
    env["PIP_PROXY"] = PROXY_URL
    env.update(dict.fromkeys(_PROXY_VARIABLES, PROXY_URL))
    mounts = [
        Mount(staged_requirements.parent, rt.REQUIREMENTS_DIR),
        Mount(target, rt.TARGET, writable=True),
    ]
    default_index, files_host = pip_defaults(runtime.python, str(_host_path(runtime, rt.PIP_PATH)))
    indexes = [os.environ.get("PIP_INDEX_URL") or default_index]
    indexes += os.environ.get("PIP_EXTRA_INDEX_URL", "").split()
    allowed = {d for d in map(Destination.of_url, indexes) if d is not None}
    if Destination.of_url(default_index) in allowed:
        allowed.add(Destination(files_host, 443))
    argv = launcher_argv(runtime, command, rt.SCRATCH, (rt.PROXY_SOCKET, PROXY_PORT))
    return _step(
        tool="pip",
        registry="package index",
        argv=argv,
        env=env,
        mounts=mounts,
        allowed=allowed,
        certificates_variable="PIP_CERT",
    )


def npm_step(runtime: rt.Runtime, target: Path) -> Step:
    """``npm ci`` in ``target`` (package.json and its lock staged there).

    Install scripts are not run (``--ignore-scripts``): no code of the repository's
    packages runs at install time; dev dependencies are left out. Blocks a moment the
    first time (it asks the runtime's npm for its default registry).
    """
    if runtime.node is None:
        raise InstallError(
            f"this lab's sandbox has no Node.js (the lab's host needs node {rt.NODE_MAJOR}"
            " or later, with npm)"
        )
    command = (
        runtime.node,
        rt.NPM_CLI,
        "ci",
        "--ignore-scripts",
        "--omit=dev",
        "--no-audit",
        "--no-fund",
        "--no-update-notifier",
        "--loglevel=error",
    )
    registry = next((os.environ[k] for k in _NPM_REGISTRY if os.environ.get(k)), None)
    if registry is None:
        registry = npm_default_registry(runtime.node, str(_host_path(runtime, rt.NPM_CLI)))
    destination = Destination.of_url(registry)
    if destination is None:
        raise InstallError(f"npm's registry is not an http(s) URL: {registry}")
    env = environment(runtime, bridge=False, python_paths=0, extra={})
    env["npm_config_registry"] = registry
    env["npm_config_proxy"] = env["npm_config_https_proxy"] = PROXY_URL
    env.update(dict.fromkeys(_PROXY_VARIABLES, PROXY_URL))
    mounts = [Mount(target, rt.TARGET, writable=True)]
    argv = launcher_argv(runtime, command, rt.TARGET, (rt.PROXY_SOCKET, PROXY_PORT))
    return _step(
        tool="npm",
        registry="registry",
        argv=argv,
        env=env,
        mounts=mounts,
        allowed={destination},
        certificates_variable="NODE_EXTRA_CA_CERTS",
    )


def _step(
    *,
    tool: str,
    registry: str,
    argv: tuple[str, ...],
    env: dict[str, str],
    mounts: list[Mount],
    allowed: set[Destination],
    certificates_variable: str,
) -> Step:
    """A step with the host's trusted authorities (the registry's, or a TLS-inspecting
    proxy's) given to the installer through ``certificates_variable``."""
    authorities = host_certificates()
    if authorities is not None:
        mounts.append(Mount(authorities, CERTIFICATES))
        env[certificates_variable] = CERTIFICATES
    return Step(tool, registry, argv, env, tuple(mounts), frozenset(allowed))


def _host_path(runtime: rt.Runtime, inside: str) -> Path:
    return runtime.root / inside.lstrip("/")


@functools.lru_cache(maxsize=8)
def pip_defaults(python: str, pip_path: str) -> tuple[str, str]:
    """pip's default index URL and the host that index serves its files from, as the
    runtime's pip at ``pip_path`` knows them (run by the host's ``python``)."""
    code = (
        "import sys; sys.path.insert(0, sys.argv[1]);"
        " from pip._internal.models.index import PyPI;"
        " print(PyPI.simple_url); print(PyPI.file_storage_domain)"
    )
    lines = _ask([python, "-I", "-c", code, pip_path], {}, "pip's default index")
    if len(lines) != 2:
        raise InstallError(f"cannot tell pip's default index: it said {lines!r}")
    return lines[0], lines[1]


@functools.lru_cache(maxsize=8)
def npm_default_registry(node: str, npm_cli: str) -> str:
    """The registry the runtime's npm (``npm_cli``, run by ``node``) uses when none is
    configured: no user or global npmrc, no project folder."""
    with tempfile.TemporaryDirectory(prefix="labd-npm-") as empty:
        env = {
            "PATH": os.environ.get("PATH", "/usr/bin:/bin"),
            "HOME": empty,
            "npm_config_userconfig": f"{empty}/npmrc",
            "npm_config_globalconfig": f"{empty}/global-npmrc",
            "npm_config_update_notifier": "false",
        }
        lines = _ask([node, npm_cli, "config", "get", "registry"], env, "npm's registry", empty)
    if len(lines) != 1:
        raise InstallError(f"cannot tell npm's default registry: it said {lines!r}")
    return lines[0]


def _ask(argv: list[str], env: dict[str, str], what: str, cwd: str = "/") -> list[str]:
    try:
        done = subprocess.run(  # noqa: S603 - the runtime's own pip or npm
            argv,
            capture_output=True,
            text=True,
            env=env,
            cwd=cwd,
            timeout=_QUERY_TIMEOUT,
            check=True,
        )
    except (OSError, subprocess.SubprocessError) as err:
        raise InstallError(f"cannot tell {what}: {err}") from None
    return done.stdout.split()


def stage_node_package(package: Path, lock: Path, target: Path) -> None:
    """Copy a repository's package.json and package-lock.json into ``target`` for
    ``npm ci``: each read only if it is itself a regular file (never through a link)."""
    for source, name in ((package, "package.json"), (lock, "package-lock.json")):
        data = _read_regular(source, name)
        (target / name).write_bytes(data)
        (target / name).chmod(0o644)


def _read_regular(path: Path, what: str) -> bytes:
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError as err:
        reason = "it is a symbolic link" if err.errno == errno.ELOOP else err.strerror
        raise InstallError(f"{what} cannot be read: {reason}") from None
    with os.fdopen(fd, "rb") as f:
        if not stat.S_ISREG(os.fstat(f.fileno()).st_mode):
            raise InstallError(f"{what} is not a regular file")
        return f.read()


def host_certificates() -> Path | None:
    """The certificate authorities the host's pip trusts, if it names or has a bundle."""
    for name in ("PIP_CERT", "REQUESTS_CA_BUNDLE", "SSL_CERT_FILE"):
        if os.environ.get(name) and Path(os.environ[name]).is_file():
            return Path(os.environ[name]).resolve()
    bundle = Path("/etc/ssl/certs/ca-certificates.crt")
    return bundle.resolve() if bundle.is_file() else None


def check_requirements(text: str) -> None:
    """Refuse requirements that would build or run code at install time.

    ``--only-binary`` covers what pip finds in an index, not direct references (VCS
    URLs, archives, local paths), which pip would build: only wheels may be named so.
    """
    for raw in text.splitlines():
        line = raw.split(" #", 1)[0].strip()
        for option in _FORBIDDEN_OPTIONS:
            if line == option or line.startswith((option + " ", option + "=")):
                raise InstallError(f"{option} is not allowed in requirements: {raw.strip()}")
        if not line or line.startswith("-"):
            continue
        reference = line.split("@", 1)[1] if "@" in line else line
        reference = reference.split(";", 1)[0].split("#", 1)[0].strip()
        direct = "://" in reference or reference.startswith((".", "/", "~", "file:"))
        if direct and not reference.endswith(".whl"):
            raise InstallError(f"only wheels may be named by URL or path: {raw.strip()}")


def stage_requirements(requirements: Path, staging: Path) -> Path:
    """Check a requirements file and copy it into ``staging`` for the install step.

    ``requirements`` is read only if it is itself a regular file (``O_NOFOLLOW``: a
    symbolic link is refused, never read through), as UTF-8 text; the copy is what the
    sandbox sees, so it is the file that was checked.
    """
    data = _read_regular(requirements, "the requirements file")
    try:
        check_requirements(data.decode("utf-8"))
    except UnicodeDecodeError:
        raise InstallError("the requirements file is not UTF-8 text") from None
    staged = staging / "requirements.txt"
    staged.write_bytes(data)
    staging.chmod(0o755)
    staged.chmod(0o644)
    return staged


def install_failure(ended: Exit, tool: str = "pip") -> InstallError:
    """The InstallError of a failed pip (or npm) run, with the end of its output."""
    log = (ended.stdout + b"\n" + ended.stderr).decode("utf-8", "replace").strip()
    tail = "\n".join(log.splitlines()[-40:])
    if ended.wall_exceeded:
        reason = f"{tool} ran out of time"
    elif ended.out_of_memory:
        reason = f"{tool} ran out of memory"
    elif tool == "npm":
        reason = _npm_reason(log) or f"npm exited with {ended.code}"
    else:
        errors = [line for line in log.splitlines() if line.startswith("ERROR:")]
        reason = errors[-1].removeprefix("ERROR: ") if errors else f"pip exited with {ended.code}"
    return InstallError(reason, tail)


def _npm_reason(log: str) -> str:
    """npm's own reason in one line: its first ``npm error`` line but the codes."""
    for line in log.splitlines():
        for prefix in ("npm error", "npm ERR!"):
            if line.startswith(prefix):
                text = line.removeprefix(prefix).strip().removeprefix("notarget ")
                if text and not text.startswith(_NPM_NOISE):
                    return text[:300]
    return ""
