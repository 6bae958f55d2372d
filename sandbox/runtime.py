"""The controller runtime: one root filesystem that every backend runs jobs in.

A controller must behave the same under Docker and under bubblewrap, so both start it in
the same tree, built once on the host from what the host has:

- the host's Python (interpreter, ``libpython`` and standard library) at the same absolute
  path, so the interpreter's absolute RUNPATH keeps working, without the host's
  site-packages;
- ``/opt/labd/site-packages``: pinned numpy, websockets, roslibpy and their dependencies,
  plus the extra package folders the lab passes in (its controller client library);
- ``/opt/labd/pip``: pip itself, put on ``PYTHONPATH`` only by ``install()``;
- ``/opt/labd/launcher.py``: the first process of every job (see ``launcher.py``);
- when the host has Node.js 20 or later with npm: its ``node`` at the same absolute path
  (and on ``PATH``), and ``/opt/labd/node_modules``, installed from ``sandbox/node``'s
  lock file: ``roslib`` (roslibjs 2.x) for every controller, found from ``/code``
  through ``/node_modules/roslib``, and npm for the build step of a repository's own
  packages (``install_node``);
- the shared libraries all of those load (the closure of ``ldd`` over every ELF file),
  the dynamic loader, ``/bin/sh`` (dash) and ``/usr/bin/env``;
- a minimal ``/etc`` (passwd and group with the sandbox user, hosts, nsswitch.conf; no
  resolv.conf) and the mount points the backends use.

Every ``.py`` file is byte-compiled into ``unchecked-hash`` pycs (valid whatever the file
times), so imports are fast from a read-only tree and the bytes do not depend on when it
was built. The tree lives in ``CACHE/runtime-KEY/rootfs`` where KEY digests the inputs
(Python version, pins, extra folders' content, the launcher and this recipe); it is
built in a temporary folder and renamed into place, so no one sees half a runtime.
``Runtime.digest`` is the sha256 of the built tree's content (paths, modes, bytes, link
targets): the same inputs on the same host give the same digest.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import json
import logging
import os
import shutil
import stat
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

from .api import MiB, RuntimeBuildError

log = logging.getLogger(__name__)

# The runtime's packages: the top-level pins of the brief and the whole closure they
# resolve to, pinned so that the same inputs give the same tree.
PACKAGES = (
    "numpy==2.4.6",
    "websockets==17.4",
    "roslibpy==2.1.0",
    "attrs==26.1.0",
    "autobahn==26.10.2",
    "automat==25.4.16",
    "cbor2==6.2.1",
    "cffi==2.1.1",
    "constantly==23.10.4",
    "cryptography==50.0.2",
    "hyperlink==21.0.0",
    "idna==3.20",
    "incremental==24.11.0",
    "msgpack==1.2.4",
    "packaging==26.3",
    "pycparser==3.12",
    "pyopenssl==26.4.0",
    "service-identity==26.1.0",
    "twisted==26.10.0",
    "txaio==26.6.1",
    "typing-extensions==4.16.0",
    "ujson==6.1.0",
    "zope-interface==8.7",
)
PIP = "pip==26.3"

# Paths inside the sandbox (the same in every backend).
LABD_DIR = "/opt/labd"
SITE_PACKAGES = f"{LABD_DIR}/site-packages"
PIP_PATH = f"{LABD_DIR}/pip"
LAUNCHER = f"{LABD_DIR}/launcher.py"
CODE = "/code"
SCRATCH = "/scratch"
HOME = f"{SCRATCH}/home"
TMPDIR = f"{SCRATCH}/tmp"  # noqa: S108 - inside the sandbox: its own scratch tmpfs
RUN_DIR = "/run/labd"
BRIDGE_SOCKET = f"{RUN_DIR}/bridge.sock"
PROXY_SOCKET = f"{RUN_DIR}/proxy.sock"  # a build step's way to the registry (proxy.py)
MNT = "/mnt"
PYTHON_PATHS = f"{MNT}/python"  # the job's python_paths: /mnt/python/0, /mnt/python/1, ...
REQUIREMENTS_DIR = f"{MNT}/requirements"  # install(): the requirements file, read-only
TARGET = f"{MNT}/target"  # install(): where pip puts the packages
DATA = f"{MNT}/data"  # the job's data folder, read-only: LAB_DATA_DIR
SANDBOX_UID = 64000  # the uid (and gid) a job sees itself as
MOUNT_POINTS = ("code", "scratch", "proc", "dev", "run", "mnt", "sys")
# Node.js: the runtime's own packages, and where a controller's imports look after
# /code/node_modules (Node searches each parent folder's node_modules): roslib there by
# default, a repository's installed packages mounted over it (with roslib added).
NODE_SOURCE = Path(__file__).with_name("node")  # package.json and package-lock.json
NODE_MODULES = f"{LABD_DIR}/node_modules"
NPM_CLI = f"{NODE_MODULES}/npm/bin/npm-cli.js"
SHARED_NODE_MODULES = "/node_modules"
PROVIDED_NODE_PACKAGES = ("roslib",)  # what every controller may import without installing
NODE_MAJOR = 20  # the oldest Node.js the runtime takes from the host

# What of the host's standard library a controller does not need.
_STDLIB_SKIP_DIRS = {
    "site-packages",
    "test",
    "tests",
    "idle_test",
    "idlelib",
    "tkinter",
    "turtledemo",
    "ensurepip",
    "__pycache__",
}
_DYNLOAD_SKIP = ("_test", "_ctypes_test", "_xxtestfuzz", "xxlimited", "_tkinter", "xxsubtype")

_PASSWD = (
    "root:x:0:0:root:/root:/usr/sbin/nologin\n"
    f"sandbox:x:{SANDBOX_UID}:{SANDBOX_UID}:labd sandbox:{HOME}:/bin/sh\n"
    "nobody:x:65534:65534:nobody:/nonexistent:/usr/sbin/nologin\n"
)
_GROUP = f"root:x:0:\nsandbox:x:{SANDBOX_UID}:\nnogroup:x:65534:\n"
_HOSTS = "127.0.0.1\tlocalhost\n::1\tlocalhost ip6-localhost ip6-loopback\n"
_NSSWITCH = "passwd: files\ngroup: files\nshadow: files\nhosts: files dns\n"


@dataclass(frozen=True)
class Runtime:
    """A built controller runtime on the host."""

    root: Path  # the root filesystem
    digest: str  # sha256 of the tree's content
    python: str  # the interpreter's absolute path, inside and on the host
    size: int  # bytes of its files
    build_seconds: float  # time it took to build; 0.0 when an existing one was reused
    node: str | None = None  # Node.js's absolute path inside, None when the host had none
    node_version: str | None = None  # e.g. "v20.20.2"


def python_executable() -> Path:
    """The host interpreter the runtime is made of (the base of a virtualenv, if any)."""
    version = f"{sys.version_info.major}.{sys.version_info.minor}"
    exe = Path(sys.base_prefix) / "bin" / f"python{version}"
    if not exe.is_file():
        raise RuntimeBuildError(f"no interpreter at {exe}")
    return exe


@dataclass(frozen=True)
class HostNode:
    """The host's Node.js and npm, which the runtime is given."""

    node: Path  # the binary itself (links resolved)
    npm: Path  # the host's npm command, which installs the runtime's packages
    version: str  # e.g. "v20.20.2"


def host_node() -> HostNode | None:
    """The host's ``node`` (20 or later) and ``npm``, or None: the runtime then has no
    Node.js, and a controller run with ``node`` is told so."""
    node, npm = shutil.which("node"), shutil.which("npm")
    if node is None or npm is None:
        return None
    try:
        done = subprocess.run(  # noqa: S603 - the host's own node
            [node, "--version"], capture_output=True, text=True, timeout=30, check=True
        )
    except (OSError, subprocess.SubprocessError):
        return None
    version = done.stdout.strip()
    try:
        major = int(version.lstrip("v").split(".")[0])
    except ValueError:
        return None
    if major < NODE_MAJOR:
        log.warning(
            "the host's node is %s; controllers in JavaScript need %d+", version, NODE_MAJOR
        )
        return None
    return HostNode(Path(os.path.realpath(node)), Path(npm), version)


def runtime_key(extra_packages: Sequence[Path] = (), node: HostNode | None = None) -> str:
    """Digest of everything the runtime is built from (``node``: the host's, if any)."""
    h = hashlib.sha256()
    inputs = {
        "python": sys.version,
        "prefix": sys.base_prefix,
        "platform": sys.platform,
        "packages": PACKAGES,
        "pip": PIP,
        "launcher": _file_digest(Path(__file__).with_name("launcher.py")),
        "recipe": _file_digest(Path(__file__)),
        "extra": [[p.name, tree_digest(p, skip=_is_cache)] for p in extra_packages],
        "node": _node_inputs(node),
    }
    h.update(json.dumps(inputs, sort_keys=True).encode())
    return h.hexdigest()


def _node_inputs(node: HostNode | None) -> list[str] | None:
    if node is None:
        return None
    lock = [_file_digest(NODE_SOURCE / name) for name in ("package.json", "package-lock.json")]
    return [str(node.node), node.version, _file_digest(node.node), *lock]


def build_runtime(cache: Path, extra_packages: Sequence[Path] = ()) -> Runtime:
    """Build the runtime into ``cache`` (or reuse the one built from the same inputs)."""
    cache = Path(cache).resolve()
    extra = [Path(p).resolve() for p in extra_packages]
    names = [p.name for p in extra]
    if len(set(names)) != len(names):
        raise RuntimeBuildError(f"extra package folders share a name: {names}")
    for p in extra:
        if not p.is_dir():
            raise RuntimeBuildError(f"extra package folder {p} does not exist")
    cache.mkdir(parents=True, exist_ok=True)
    node = host_node()
    key = runtime_key(extra, node)
    final = cache / f"runtime-{key[:32]}"
    with _locked(cache / f".runtime-{key[:32]}.lock"):
        if not (final / "runtime.json").is_file():
            started = time.monotonic()
            tmp = Path(tempfile.mkdtemp(prefix=".build-", dir=cache))
            try:
                _build(tmp, extra, node)
                seconds = time.monotonic() - started
                (tmp / "runtime.json").write_text(
                    json.dumps(_describe(tmp / "rootfs", seconds, node), indent=2)
                )
                tmp.chmod(0o755)  # the sandboxes' uids must reach the rootfs
                if final.exists():  # a half-removed leftover without runtime.json
                    shutil.rmtree(final)
                tmp.rename(final)
            except BaseException:
                shutil.rmtree(tmp, ignore_errors=True)
                raise
            info = json.loads((final / "runtime.json").read_text())
            log.info(
                "built the controller runtime %s (%d MiB) in %.1f s",
                info["digest"][:12],
                info["size"] >> 20,
                seconds,
            )
        else:
            seconds = 0.0
            info = json.loads((final / "runtime.json").read_text())
    return Runtime(
        root=final / "rootfs",
        digest=info["digest"],
        python=info["python"],
        size=info["size"],
        build_seconds=seconds,
        node=info.get("node"),
        node_version=info.get("node_version"),
    )


def tree_digest(root: Path, skip: Callable[[Path], bool] | None = None) -> str:
    """sha256 over a tree's relative paths, modes, file bytes and link targets."""
    h = hashlib.sha256()
    for path in walk(root, skip):
        rel = path.relative_to(root).as_posix()
        st = path.lstat()
        mode = stat.S_IMODE(st.st_mode)
        if stat.S_ISLNK(st.st_mode):
            entry = f"L {rel} {os.readlink(path)}"
        elif stat.S_ISDIR(st.st_mode):
            entry = f"D {rel} {mode:o}"
        else:
            entry = f"F {rel} {mode:o} {_file_digest(path)}"
        h.update(entry.encode("utf-8", "surrogateescape") + b"\0")
    return h.hexdigest()


def _is_cache(path: Path) -> bool:
    return path.name == "__pycache__" or path.suffix == ".pyc"


def walk(root: Path, skip: Callable[[Path], bool] | None = None) -> Iterator[Path]:
    """Every entry under ``root`` in a fixed order (symlinks are not followed)."""
    for dirpath, dirnames, filenames in os.walk(root):
        dirnames.sort()
        base = Path(dirpath)
        entries = sorted([*dirnames, *filenames])
        for name in entries:
            path = base / name
            if skip is not None and skip(path):
                if name in dirnames:
                    dirnames.remove(name)
                continue
            yield path
        # os.walk does not descend into symlinked folders; they are listed as entries.


def _file_digest(path: Path) -> str:
    h = hashlib.sha256()
    with path.open("rb") as f:
        for block in iter(lambda: f.read(MiB), b""):
            h.update(block)
    return h.hexdigest()


@contextlib.contextmanager
def _locked(path: Path) -> Iterator[None]:
    """Hold an exclusive lock on ``path`` (one builder per key, across processes)."""
    fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o600)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)


def _describe(rootfs: Path, seconds: float, node: HostNode | None) -> dict[str, object]:
    size = sum(p.lstat().st_size for p in walk(rootfs) if p.is_file() and not p.is_symlink())
    return {
        "node": None if node is None else str(node.node),
        "node_version": None if node is None else node.version,
        "digest": tree_digest(rootfs),
        "python": str(python_executable()),
        "size": size,
        "build_seconds": round(seconds, 3),
        "packages": PACKAGES,
        "pip": PIP,
    }


def _build(tmp: Path, extra: Sequence[Path], node: HostNode | None) -> None:
    rootfs = tmp / "rootfs"
    rootfs.mkdir()
    exe = python_executable()
    prefix = Path(sys.base_prefix)
    version = f"python{sys.version_info.major}.{sys.version_info.minor}"

    # The interpreter and its standard library, at the host's absolute path.
    bindir = _inside(rootfs, prefix / "bin")
    bindir.mkdir(parents=True)
    shutil.copy2(exe, bindir / exe.name)
    for alias in ("python3", "python"):
        (bindir / alias).symlink_to(exe.name)
    stdlib = prefix / "lib" / version
    shutil.copytree(stdlib, _inside(rootfs, stdlib), ignore=_stdlib_ignore, symlinks=True)

    # Packages, pip for install(), the extra folders, the launcher.
    labd = _inside(rootfs, Path(LABD_DIR))
    _pip_install(labd / "site-packages", PACKAGES)
    _pip_install(labd / "pip", (PIP,))
    for folder in extra:
        shutil.copytree(
            folder,
            labd / "site-packages" / folder.name,
            ignore=shutil.ignore_patterns("__pycache__", "*.pyc"),
        )
    shutil.copyfile(Path(__file__).with_name("launcher.py"), labd / "launcher.py")
    if node is not None:
        _add_node(rootfs, labd, node)

    # The shell, env, and every shared library all those ELF files load.
    usrbin = _inside(rootfs, Path(os.path.realpath("/bin")))
    usrbin.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(os.path.realpath("/bin/sh"), usrbin / "sh")
    envbin = _inside(rootfs, Path(os.path.realpath("/usr/bin")))
    envbin.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(os.path.realpath("/usr/bin/env"), envbin / "env")
    (usrbin / "sh").chmod(0o755)
    (envbin / "env").chmod(0o755)
    _copy_shared_libraries(rootfs)
    for top in ("bin", "sbin", "lib", "lib32", "lib64", "libx32"):
        host = Path("/") / top
        if host.is_symlink() and (rootfs / os.readlink(host).lstrip("/")).exists():
            (rootfs / top).symlink_to(os.readlink(host))

    # /etc, the mount points, /tmp in the scratch folder.
    etc = rootfs / "etc"
    etc.mkdir()
    for name, text in (
        ("passwd", _PASSWD),
        ("group", _GROUP),
        ("hosts", _HOSTS),
        ("nsswitch.conf", _NSSWITCH),
    ):
        (etc / name).write_text(text)
    for name in MOUNT_POINTS:
        (rootfs / name).mkdir(exist_ok=True)
    (rootfs / "tmp").symlink_to(os.path.relpath(TMPDIR, "/"))

    _compile(rootfs, [_inside(rootfs, stdlib), labd / "site-packages", labd / "pip"])
    _normalize_modes(rootfs)


def _add_node(rootfs: Path, labd: Path, node: HostNode) -> None:
    """Node.js at its host path (and ``/usr/local/bin/node``), the runtime's packages
    from ``sandbox/node``'s lock file, and ``/node_modules`` linking what is provided."""
    binary = _inside(rootfs, node.node)
    binary.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(node.node, binary)
    binary.chmod(0o755)
    local = rootfs / "usr" / "local" / "bin"
    local.mkdir(parents=True, exist_ok=True)
    if not (local / "node").exists():
        (local / "node").symlink_to(node.node)
    for name in ("package.json", "package-lock.json"):
        shutil.copyfile(NODE_SOURCE / name, labd / name)
    command = [
        str(node.npm),
        "ci",
        "--ignore-scripts",
        "--no-audit",
        "--no-fund",
        "--no-update-notifier",
        "--loglevel=error",
    ]
    done = subprocess.run(  # noqa: S603 - the host's npm, on the runtime's own lock file
        command, cwd=labd, capture_output=True, text=True, check=False
    )
    if done.returncode != 0:
        raise RuntimeBuildError(f"npm ci failed ({done.returncode}): {_tail(done.stderr)}")
    shared = _inside(rootfs, Path(SHARED_NODE_MODULES))
    shared.mkdir()
    for name in PROVIDED_NODE_PACKAGES:
        (shared / name).symlink_to(f"{NODE_MODULES}/{name}")


def _inside(rootfs: Path, host_path: Path) -> Path:
    return rootfs / str(host_path).lstrip("/")


def _stdlib_ignore(folder: str, names: list[str]) -> set[str]:
    skipped = {n for n in names if n in _STDLIB_SKIP_DIRS or n.endswith(".pyc")}
    skipped |= {n for n in names if n.startswith("config-")}
    if Path(folder).name == "lib-dynload":
        skipped |= {n for n in names if n.startswith(_DYNLOAD_SKIP)}
    return skipped


def _pip_install(target: Path, requirements: Iterable[str]) -> None:
    """Install wheels into ``target`` with the host's pip (and its index settings)."""
    command = [
        sys.executable,
        "-m",
        "pip",
        "install",
        "--target",
        str(target),
        "--only-binary=:all:",
        "--no-compile",
        "--no-input",
        "--disable-pip-version-check",
        "--no-warn-script-location",
        "--progress-bar",
        "off",
        *requirements,
    ]
    done = subprocess.run(command, capture_output=True, text=True, check=False)  # noqa: S603
    if done.returncode != 0:
        raise RuntimeBuildError(f"pip failed ({done.returncode}): {_tail(done.stderr)}")
    # Console scripts name the interpreter that ran pip, which does not exist inside;
    # their lines in RECORD go too, so the runtime does not depend on where pip ran.
    shutil.rmtree(target / "bin", ignore_errors=True)
    for record in target.glob("*.dist-info/RECORD"):
        lines = record.read_text().splitlines(keepends=True)
        record.write_text("".join(x for x in lines if not x.startswith("../../bin/")))
    for cache in target.rglob("__pycache__"):
        shutil.rmtree(cache)


def _copy_shared_libraries(rootfs: Path) -> None:
    """Copy into ``rootfs`` every host library that its ELF files need, at the same path."""
    elves = [p for p in walk(rootfs) if p.is_file() and not p.is_symlink() and _is_elf(p)]
    missing: set[str] = set()
    copied: set[Path] = set()
    for elf in elves:
        for name, resolved in _ldd(elf):
            if resolved is None:
                missing.add(f"{name} (needed by {elf.relative_to(rootfs)})")
                continue
            if resolved.is_relative_to(rootfs):
                continue
            dest = _inside(rootfs, Path(os.path.realpath(resolved.parent)) / resolved.name)
            if dest in copied or dest.exists():
                continue
            dest.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(os.path.realpath(resolved), dest)
            dest.chmod(0o755)
            copied.add(dest)
    if missing:
        raise RuntimeBuildError("shared libraries not found: " + ", ".join(sorted(missing)))
    # glibc loads libgcc_s at run time (thread exit, unwinding); ldd cannot see that.
    for directory in ("/lib/x86_64-linux-gnu", "/usr/lib/x86_64-linux-gnu", "/lib64"):
        libgcc = Path(directory) / "libgcc_s.so.1"
        dest = _inside(rootfs, Path(os.path.realpath(directory)) / libgcc.name)
        if libgcc.exists() and not dest.exists():
            dest.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(os.path.realpath(libgcc), dest)
            dest.chmod(0o755)
            break


def _is_elf(path: Path) -> bool:
    with path.open("rb") as f:
        return f.read(4) == b"\x7fELF"


def _ldd(elf: Path) -> list[tuple[str, Path | None]]:
    """The libraries ``elf`` loads, as ldd resolves them on the host (None: not found)."""
    done = subprocess.run(  # noqa: S603 - the host's ldd on the runtime's own files
        ["ldd", str(elf)],  # noqa: S607
        capture_output=True,
        text=True,
        check=False,
    )
    if done.returncode != 0:
        if "not a dynamic executable" in done.stdout + done.stderr:
            return []
        raise RuntimeBuildError(f"ldd {elf} failed: {_tail(done.stderr)}")
    found: list[tuple[str, Path | None]] = []
    for raw in done.stdout.splitlines():
        line = raw.strip()
        if "=>" in line:
            name, _, rest = line.partition("=>")
            rest = rest.strip()
            if rest.startswith("not found"):
                found.append((name.strip(), None))
            elif rest.startswith("/"):
                found.append((name.strip(), Path(rest.split(" (")[0])))
        elif line.startswith("/"):  # the dynamic loader
            path = Path(line.split(" (")[0])
            found.append((path.name, path))
    return found


def _compile(rootfs: Path, folders: Sequence[Path]) -> None:
    """Byte-compile ``folders`` with pycs that name the paths seen inside."""
    command = [
        str(python_executable()),
        "-I",
        "-m",
        "compileall",
        "-q",
        "-j",
        "0",
        "--invalidation-mode",
        "unchecked-hash",
        "-s",
        str(rootfs),
        "-p",
        "/",
        *map(str, folders),
    ]
    done = subprocess.run(command, capture_output=True, text=True, check=False)  # noqa: S603
    if done.returncode != 0:
        # A few packages ship files that are not Python 3 on purpose; they stay uncompiled.
        log.debug("compileall left some files uncompiled: %s", _tail(done.stdout))


def _normalize_modes(rootfs: Path) -> None:
    """Modes that do not depend on the umask: 0755 for folders and programs, else 0644."""
    for path in walk(rootfs):
        st = path.lstat()
        if stat.S_ISLNK(st.st_mode):
            continue
        executable = stat.S_ISDIR(st.st_mode) or st.st_mode & 0o111
        path.chmod(0o755 if executable else 0o644)
    rootfs.chmod(0o755)


def _tail(text: str, lines: int = 30) -> str:
    return "\n".join(text.strip().splitlines()[-lines:])
