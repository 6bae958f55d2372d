#!/usr/bin/env python3
"""Build the lab's container images from this repository and this machine; nothing pulled.

    .venv/bin/python deploy/build_image.py [--only lab|postgres] [--work DIR] [--keep]

Two images, each a root filesystem made of what this host has and imported with no base
(``docker import`` of a tar), the way the controller sandbox's runtime is made
(``sandbox/runtime.py``):

``labd:VERSION`` (also tagged ``labd:latest``): the lab, a remote worker and, for a
trial deployment, the S3-compatible store, one image for all three:

- the host's Python at its own absolute path (so its RUNPATH still holds), without its
  site-packages, and ``/opt/labd/venv``: a virtual environment of labd and its
  dependencies (``.[postgres,s3,cluster]``), held to the versions of the development venv
  (``pip freeze`` of ``.venv`` as constraints), without the packages' own test suites;
- ``/opt/labd/s3``: a second venv with moto's S3 service (``moto_server``), a stand-in
  store for the smoke test and trials of the compose file, never for production;
- ``deploy/labd_setup.py`` (as ``labd-setup``) and ``deploy/labd-worker-entrypoint`` in
  ``/usr/local/bin``;
- git with its helpers (``git http-backend`` for the playground's repositories,
  ``git-remote-https``, ``git daemon``), ssh, bubblewrap and the util-linux tools the
  bubblewrap sandbox uses (``prlimit``, ``unshare``, ``mount``, ``setpriv``), Node.js
  and npm, a shell and a few coreutils, PostgreSQL's client tools (``pg_dump``,
  ``pg_restore``, ``psql``);
- Mesa's EGL, which MuJoCo's cameras open at run time (``libEGL``, ``libEGL_mesa``,
  ``libOpenGL``, the ``swrast`` DRI driver and ``/usr/share/glvnd/egl_vendor.d``);
- the CA certificates;
- the controller runtime prebuilt in ``/opt/labd/cache`` (``labd worker --cache
  /opt/labd/cache``), so a worker needs neither PyPI nor npm: the image is checked to
  compute the same runtime key as the folder's;
- the shared libraries all of those load (the closure of ``ldd``), deduplicated: files
  of equal bytes, mode and owner become hard links, which ``docker import`` keeps.

``labd-postgres:VERSION``: PostgreSQL from Debian's ``postgresql`` package (installed on
the host with apt-get if missing) and ``deploy/postgres-entrypoint``.

Prints the tags it made, one a line. Needs root (files owned by the images' users) and a
Docker engine.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import shutil
import stat
import subprocess
import sys
import sysconfig
import tempfile
import time
from collections.abc import Iterable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
DEPLOY = REPO / "deploy"
sys.path.insert(0, str(REPO))

from sandbox import RuntimeBuildError  # noqa: E402 - after the repository is on the path
from sandbox import runtime as rt  # noqa: E402

LABD_UID = 10001  # the lab's user in the image; workers run as root (bubblewrap's uids)
POSTGRES_UID = 10002
VENV = "/opt/labd/venv"
S3_VENV = "/opt/labd/s3"
RUNTIME_CACHE = "/opt/labd/cache"
# moto's S3 service alone: moto[server] would add cfn-lint, sympy and networkx (120 MiB).
MOTO = ("moto[s3]==5.2.5", "flask", "flask-cors")
PATH = f"{VENV}/bin:/usr/local/bin:/usr/bin:/bin"

# Programs taken from the host, by name on its PATH (then their links and libraries).
LAB_PROGRAMS = (
    "sh",
    "bash",
    "env",
    "cat",
    "ls",
    "cp",
    "mv",
    "rm",
    "ln",
    "mkdir",
    "chmod",
    "chown",
    "id",
    "sleep",
    "git",
    "ssh",
    "bwrap",
    "prlimit",
    "unshare",
    "mount",
    "umount",
    "setpriv",
    "node",
    "npm",
)
LAB_TREES = (
    "/usr/lib/git-core",
    "/usr/share/git-core/templates",
    "/usr/lib/node_modules/npm",
    "/usr/share/glvnd/egl_vendor.d",
    "/usr/share/drirc.d",
    "/etc/ssl/certs/ca-certificates.crt",
    "/usr/lib/ssl/cert.pem",
    "/usr/lib/ssl/certs",
)
# What MuJoCo's EGL rendering dlopens (PyOpenGL asks for libEGL and libOpenGL by name;
# glvnd finds Mesa through egl_vendor.d; Mesa loads the DRI driver): seen in
# /proc/self/maps of a process that rendered a frame on this host.
MESA = (
    "libEGL.so",
    "libEGL.so.1",
    "libEGL_mesa.so.0",
    "libGLdispatch.so.0",
    "libOpenGL.so",
    "libOpenGL.so.0",
    "libgbm.so.1",
    "dri/swrast_dri.so",
)
POSTGRES_CLIENTS = ("pg_dump", "pg_restore", "psql", "pg_isready")
POSTGRES_PROGRAMS = ("sh", "cat", "rm", "mkdir", "chmod", "ls", "locale")


class BuildError(Exception):
    """A step of the build failed; the message says which and why."""


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--only", choices=("lab", "postgres"), help="build one image only")
    parser.add_argument(
        "--work",
        type=Path,
        default=REPO / "build" / "images",
        help="where the root filesystems are made (default: build/images)",
    )
    parser.add_argument(
        "--keep", action="store_true", help="keep the root filesystems (default: removed)"
    )
    args = parser.parse_args()
    if os.geteuid() != 0:
        print("build-image: run it as root (the images' files have their own owners)")
        return 2
    version = _version()
    args.work.mkdir(parents=True, exist_ok=True)
    try:
        if args.only in (None, "lab"):
            _image(args, "labd", version, build_lab, extra_tags=("latest",))
        if args.only in (None, "postgres"):
            _image(args, "labd-postgres", version, build_postgres, extra_tags=("latest",))
    except (BuildError, RuntimeBuildError) as err:
        print(f"build-image: {err}", file=sys.stderr)
        return 1
    return 0


def _image(
    args: argparse.Namespace,
    name: str,
    version: str,
    build: object,
    extra_tags: Iterable[str] = (),
) -> None:
    started = time.monotonic()
    work = Path(tempfile.mkdtemp(prefix=f"{name}-", dir=args.work))
    rootfs = work / "rootfs"
    rootfs.mkdir()
    try:
        changes = build(rootfs, version)  # type: ignore[operator]
        _dedupe(rootfs)
        tag = f"{name}:{version}"
        before = _image_id(tag)
        size = _import(rootfs, tag, changes)
        for extra in extra_tags:
            _run(["docker", "tag", tag, f"{name}:{extra}"])
        if before and before != _image_id(tag):  # the build it replaces: its GB go (unless
            _remove_image(before)  # a container still uses it)
        if name == "labd":
            _check_runtime(rootfs, tag)
        _log(f"{tag}: {size / 2**20:.0f} MiB, built in {time.monotonic() - started:.0f} s")
        print(tag)
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)


# -- the lab's image -----------------------------------------------------------------------


def build_lab(rootfs: Path, version: str) -> list[str]:
    """The lab's root filesystem; answers ``docker import``'s ``--change`` lines."""
    vendor = REPO / "labd" / "web" / "static" / "vendor" / ".built"
    if not vendor.exists():
        raise BuildError("the pages' scripts are not built (labd/web/static/vendor): make setup")
    _log("the host's Python")
    _add_python(rootfs)
    _log("the lab's virtual environment (pip)")
    constraints = rootfs.parent / "constraints.txt"
    constraints.write_text(_freeze())
    _venv(rootfs, VENV, [f"{REPO}[postgres,s3,cluster]"], constraints)
    _venv(rootfs, S3_VENV, list(MOTO), constraints)
    (rootfs / "usr/local/bin").mkdir(parents=True, exist_ok=True)
    (rootfs / "usr/local/bin/moto_server").symlink_to(f"{S3_VENV}/bin/moto_server")
    _log("programs: git, bubblewrap, Node.js, Mesa's EGL, certificates")
    for program in LAB_PROGRAMS:
        _add(rootfs, _which(program))
    for tree in LAB_TREES:
        _add(rootfs, Path(tree))
    multiarch = _multiarch()
    for name in MESA:
        _add(rootfs, multiarch / name)
    pg_bin = _postgres_bin()
    for program in POSTGRES_CLIENTS:
        _add(rootfs, pg_bin / program)
        (rootfs / "usr/local/bin" / program).symlink_to(pg_bin / program)
    for script, command in (
        ("labd_setup.py", "labd-setup"),
        ("labd-worker-entrypoint", "labd-worker-entrypoint"),
    ):
        shutil.copyfile(DEPLOY / script, rootfs / "usr/local/bin" / command)
        (rootfs / "usr/local/bin" / command).chmod(0o755)
    _log("shared libraries (ldd)")
    _libraries(rootfs)
    _etc(rootfs, [("labd", LABD_UID, "/var/lib/labd")])
    for folder, owner, mode in (
        ("var/lib/labd", LABD_UID, 0o700),  # the lab's data: its index, keys (docs/operate.md)
        ("etc/labd", 0, 0o755),
        ("run/labd", 0, 0o755),
        ("run/labd-tokens", LABD_UID, 0o700),  # the compose file's workers' tokens
        ("tmp", 0, 0o1777),
        ("root", 0, 0o711),  # the host's Python lives under /root/.pyenv here
    ):
        path = rootfs / folder
        path.mkdir(parents=True, exist_ok=True)
        os.chown(path, owner, owner)
        path.chmod(mode)
    _log("byte-compiling")
    rt._compile(rootfs, [rootfs / VENV.lstrip("/"), rootfs / S3_VENV.lstrip("/"), _stdlib(rootfs)])
    _log("the controller runtime (sandbox/runtime.py)")
    _prebuild_runtime(rootfs)
    return [
        f"ENV PATH={PATH}",
        "ENV LANG=C.UTF-8",
        "ENV PYTHONDONTWRITEBYTECODE=1",
        "ENV MUJOCO_GL=egl",
        "WORKDIR /var/lib/labd",
        "USER labd",
        "EXPOSE 8080 9090",
        f"LABEL org.labd.version={version}",
        'CMD ["labd", "--help"]',
    ]


def _add_python(rootfs: Path) -> None:
    exe = rt.python_executable()
    prefix = Path(sys.base_prefix)
    version = f"python{sys.version_info.major}.{sys.version_info.minor}"
    _add(rootfs, exe)
    stdlib = prefix / "lib" / version
    dest = rootfs / str(stdlib).lstrip("/")
    shutil.copytree(stdlib, dest, ignore=_stdlib_ignore, symlinks=True)
    for alias in ("python3", "python"):
        link = rootfs / str(prefix / "bin" / alias).lstrip("/")
        if not link.exists():
            link.symlink_to(exe.name)


def _stdlib_ignore(folder: str, names: list[str]) -> set[str]:
    # As the runtime's, but venv and ensurepip stay: an operator may make venvs inside.
    return {n for n in rt._stdlib_ignore(folder, names) if n != "ensurepip"}


def _stdlib(rootfs: Path) -> Path:
    version = f"python{sys.version_info.major}.{sys.version_info.minor}"
    return rootfs / str(Path(sys.base_prefix) / "lib" / version).lstrip("/")


def _freeze() -> str:
    """The development venv's versions, as constraints (labd itself left out)."""
    done = _run(
        [sys.executable, "-m", "pip", "freeze", "--exclude-editable", "--disable-pip-version-check"]
    )
    return "".join(f"{line}\n" for line in done.splitlines() if "==" in line)


def _venv(rootfs: Path, where: str, requirements: list[str], constraints: Path) -> None:
    """A venv at ``where`` inside ``rootfs``, made and filled by the host's Python and
    pip, then its scripts and pyvenv.cfg pointed at ``where`` itself."""
    target = rootfs / where.lstrip("/")
    _run([str(rt.python_executable()), "-m", "venv", str(target)])
    _run(
        [
            str(target / "bin" / "python"),
            "-m",
            "pip",
            "install",
            "--quiet",
            "--no-compile",
            "--no-input",
            "--disable-pip-version-check",
            "--no-warn-script-location",
            "--progress-bar",
            "off",
            "--constraint",
            str(constraints),
            *requirements,
        ]
    )
    built = str(target).encode()
    for path in [*(target / "bin").iterdir(), target / "pyvenv.cfg"]:
        if path.is_symlink() or not path.is_file():
            continue
        data = path.read_bytes()
        if built in data:
            path.write_bytes(data.replace(built, where.encode()))
    for cache in target.rglob("__pycache__"):
        shutil.rmtree(cache)
    for tests in target.glob("lib/python*/site-packages/*/**/tests"):
        shutil.rmtree(tests)  # the packages' own test suites (numpy's, scipy's): 100 MiB


def _prebuild_runtime(rootfs: Path) -> None:
    """Build the controller runtime with the image's own labd, into the image.

    The image's venv runs on the host (its interpreter is the host's, at the same path),
    from ``/`` so that this checkout's packages are not the ones imported, with the
    host's pip settings and npm: the key it computes (Python, pins, the client library's
    files, Node.js) is the one the image computes, which ``_check_runtime`` confirms.
    """
    script = (
        "import sys; from pathlib import Path; import sandbox.runtime as rt;"
        " from labd.trial import client_library;"
        " print(rt.build_runtime(Path(sys.argv[1]), [client_library()]).root.parent.name)"
    )
    cache = rootfs / RUNTIME_CACHE.lstrip("/")
    python = rootfs / VENV.lstrip("/") / "bin" / "python"
    env = {**os.environ, "PYTHONDONTWRITEBYTECODE": "1"}
    env.pop("PYTHONPATH", None)
    name = _run([str(python), "-P", "-c", script, str(cache)], cwd="/", env=env).strip()
    for leftover in cache.glob(".runtime-*.lock"):
        leftover.unlink()
    _log(f"  {name}")


def _check_runtime(rootfs: Path, tag: str) -> None:
    """The image computes the prebuilt runtime's key: a worker will not try to build one."""
    script = (
        "from sandbox.runtime import runtime_key, host_node;"
        " from labd.trial import client_library;"
        " print('runtime-' + runtime_key([client_library()], host_node())[:32])"
    )
    inside = _run(["docker", "run", "--rm", "--user", "root", tag, "python", "-c", script])
    built = sorted(p.name for p in (rootfs / RUNTIME_CACHE.lstrip("/")).glob("runtime-*"))
    if [inside.strip()] != built:
        raise BuildError(f"the image computes {inside.strip()}, but it holds {built}")


# -- PostgreSQL's image ---------------------------------------------------------------------


def build_postgres(rootfs: Path, version: str) -> list[str]:
    """PostgreSQL's root filesystem, from Debian's package on this host."""
    pg_bin = _postgres_bin()
    major = pg_bin.parent.name
    _log(f"PostgreSQL {major}")
    for program in ("postgres", "initdb", "pg_ctl", "pg_isready", "psql", "pg_dump"):
        _add(rootfs, pg_bin / program)
    lib = pg_bin.parent / "lib"
    for path in sorted(lib.iterdir()):
        if path.name == "bitcode" or path.name.startswith("llvmjit"):
            continue  # the JIT: LLVM's 100 MiB for what the lab's queries never need
        _add(rootfs, path)
    _add(rootfs, Path("/usr/share/postgresql") / major)
    _add(rootfs, Path("/usr/share/zoneinfo"))
    for program in POSTGRES_PROGRAMS:
        _add(rootfs, _which(program))
    entry = rootfs / "usr/local/bin/postgres-entrypoint"
    entry.parent.mkdir(parents=True)
    shutil.copyfile(DEPLOY / "postgres-entrypoint", entry)
    entry.chmod(0o755)
    _libraries(rootfs)
    shutil.rmtree(rootfs / "usr/share/postgresql" / major / "man", ignore_errors=True)
    _etc(rootfs, [("postgres", POSTGRES_UID, "/var/lib/postgresql")])
    for folder, owner, mode in (
        ("var/lib/postgresql", POSTGRES_UID, 0o755),
        ("var/lib/postgresql/data", POSTGRES_UID, 0o700),
        ("var/run/postgresql", POSTGRES_UID, 0o2775),
        ("tmp", 0, 0o1777),
    ):
        path = rootfs / folder
        path.mkdir(parents=True, exist_ok=True)
        os.chown(path, owner, owner)
        path.chmod(mode)
    return [
        f"ENV PATH={pg_bin}:/usr/local/bin:/usr/bin:/bin",
        "ENV LANG=C.UTF-8",
        "ENV PGDATA=/var/lib/postgresql/data",
        "USER postgres",
        "EXPOSE 5432",
        f"LABEL org.labd.version={version}",
        'CMD ["postgres-entrypoint"]',
    ]


def _postgres_bin() -> Path:
    """Debian's PostgreSQL (the newest installed), installed with apt-get if missing."""
    found = sorted(Path("/usr/lib/postgresql").glob("*/bin/postgres"), key=_major)
    if not found:
        _log("installing Debian's postgresql package")
        env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
        _run(["apt-get", "update", "-q"], env=env)
        _run(["apt-get", "install", "-y", "-q", "--no-install-recommends", "postgresql"], env=env)
        found = sorted(Path("/usr/lib/postgresql").glob("*/bin/postgres"), key=_major)
    if not found:
        raise BuildError("no PostgreSQL server under /usr/lib/postgresql after apt-get")
    return found[-1].parent


def _major(path: Path) -> int:
    name = path.parent.parent.name
    return int(name) if name.isdigit() else 0


# -- the tree --------------------------------------------------------------------------------


def _add(rootfs: Path, host: Path) -> None:
    """Copy ``host`` (a file, a link and what it leads to, or a folder) into ``rootfs`` at
    the same path, folders along the way at their real paths (``/lib`` is ``/usr/lib``)."""
    if not host.exists() and not host.is_symlink():
        raise BuildError(f"{host} is not on this host")
    parent = Path(os.path.realpath(host.parent))
    dest = rootfs / str(parent / host.name).lstrip("/")
    if dest.exists() or dest.is_symlink():
        return
    dest.parent.mkdir(parents=True, exist_ok=True)
    if host.is_symlink():
        target = os.readlink(host)
        dest.symlink_to(target)
        _add(rootfs, parent / target)
    elif host.is_dir():
        dest.mkdir()
        shutil.copystat(host, dest)
        for child in sorted(host.iterdir()):
            _add(rootfs, child)
    else:
        shutil.copy2(host, dest)


def _which(program: str) -> Path:
    found = shutil.which(program, path="/usr/local/bin:/usr/bin:/bin:/usr/sbin:/sbin")
    if found is None:
        raise BuildError(f"{program} is not installed on this host (apt-get install it)")
    return Path(found)


def _multiarch() -> Path:
    return Path("/usr/lib") / (sysconfig.get_config_var("MULTIARCH") or "x86_64-linux-gnu")


def _libraries(rootfs: Path) -> None:
    """Every shared library the tree's ELF files load, at its real path, and the top-level
    links of a merged /usr (``/lib`` to ``usr/lib``, ...).

    A library ldd cannot find is an error unless the tree ships a file of that name: a
    wheel's plugins (MuJoCo's) and vendored libraries (scipy.libs) are loaded after the
    library they need, which is then found by the process, not by ldd.
    """
    elves = [p for p in rt.walk(rootfs) if p.is_file() and not p.is_symlink() and rt._is_elf(p)]
    shipped = {p.name for p in rt.walk(rootfs)}
    missing: set[str] = set()
    with ThreadPoolExecutor(max_workers=os.cpu_count() or 2) as pool:
        for elf, needed in zip(elves, pool.map(rt._ldd, elves), strict=True):
            for name, resolved in needed:
                if resolved is None:
                    if name not in shipped:
                        missing.add(f"{name} (needed by {elf.relative_to(rootfs)})")
                elif not resolved.is_relative_to(rootfs):
                    _add(rootfs, resolved)
    if missing:
        raise BuildError("shared libraries not found: " + ", ".join(sorted(missing)))
    for top in ("bin", "sbin", "lib", "lib32", "lib64", "libx32"):
        host = Path("/") / top
        if host.is_symlink() and not (rootfs / top).exists():
            (rootfs / top).symlink_to(os.readlink(host))
    # glibc loads libgcc_s at run time (thread exit, unwinding); ldd cannot see that.
    _add(rootfs, _multiarch() / "libgcc_s.so.1")


def _etc(rootfs: Path, users: list[tuple[str, int, str]]) -> None:
    etc = rootfs / "etc"
    etc.mkdir(exist_ok=True)
    passwd = ["root:x:0:0:root:/root:/bin/sh"]
    group = ["root:x:0:"]
    for name, uid, home in users:
        passwd.append(f"{name}:x:{uid}:{uid}:{name}:{home}:/bin/sh")
        group.append(f"{name}:x:{uid}:")
    passwd.append("nobody:x:65534:65534:nobody:/nonexistent:/usr/sbin/nologin")
    group.append("nogroup:x:65534:")
    (etc / "passwd").write_text("\n".join(passwd) + "\n")
    (etc / "group").write_text("\n".join(group) + "\n")
    (etc / "nsswitch.conf").write_text(rt._NSSWITCH)
    (etc / "os-release").write_text('NAME="labd"\nID=labd\n')


def _dedupe(rootfs: Path) -> None:
    """Files of the same bytes, mode and owner become one file with several names."""
    first: dict[tuple[str, int, int, int], Path] = {}
    saved = 0
    for path in rt.walk(rootfs):
        st = path.lstat()
        if not stat.S_ISREG(st.st_mode) or st.st_size == 0:
            continue
        key = (_digest(path), st.st_mode, st.st_uid, st.st_gid)
        kept = first.setdefault(key, path)
        if kept is path or kept.stat().st_ino == st.st_ino:
            continue
        path.unlink()
        os.link(kept, path)
        saved += st.st_size
    _log(f"  {saved / 2**20:.0f} MiB of duplicates linked")


def _digest(path: Path) -> str:
    h = hashlib.sha256()
    with path.open("rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _image_id(tag: str) -> str:
    """The id of the image ``tag`` names ('' when there is none)."""
    done = subprocess.run(  # noqa: S603 - docker inspecting our own tag
        ["docker", "image", "inspect", "--format", "{{.Id}}", tag],  # noqa: S607
        capture_output=True,
        text=True,
        check=False,
    )
    return done.stdout.strip() if done.returncode == 0 else ""


def _remove_image(image: str) -> None:
    done = subprocess.run(  # noqa: S603 - removing our own previous build
        ["docker", "image", "rm", image],  # noqa: S607
        capture_output=True,
        text=True,
        check=False,
    )
    if done.returncode != 0:
        _log(f"the previous build {image[:19]} stays: {done.stderr.strip()}")


def _import(rootfs: Path, tag: str, changes: list[str]) -> int:
    """``docker import`` the tree as ``tag``; answers the image's size in bytes."""
    command = ["docker", "import"]
    for change in changes:
        command += ["--change", change]
    command += ["-", tag]
    tar = subprocess.Popen(  # noqa: S603 - tar of our own tree
        ["tar", "--numeric-owner", "--sort=name", "-C", str(rootfs), "-cf", "-", "."],  # noqa: S607
        stdout=subprocess.PIPE,
    )
    assert tar.stdout is not None
    done = subprocess.run(  # noqa: S603 - docker import of our own tree
        command, stdin=tar.stdout, capture_output=True, text=True, check=False
    )
    tar.stdout.close()
    if tar.wait() != 0 or done.returncode != 0:
        raise BuildError(f"docker import {tag} failed: {done.stderr.strip()}")
    return int(_run(["docker", "image", "inspect", "--format", "{{.Size}}", tag]).strip())


def _version() -> str:
    import labd  # noqa: PLC0415 - this checkout's, once it is on the path

    return labd.__version__


def _run(command: list[str], cwd: str | None = None, env: dict[str, str] | None = None) -> str:
    done = subprocess.run(  # noqa: S603 - the build's own commands
        command, capture_output=True, text=True, check=False, cwd=cwd, env=env
    )
    if done.returncode != 0:
        raise BuildError(
            f"{' '.join(command[:4])} ... failed ({done.returncode}):"
            f" {rt._tail(done.stderr or done.stdout)}"
        )
    return done.stdout


def _log(message: str) -> None:
    print(f"build-image: {message}", file=sys.stderr, flush=True)


if __name__ == "__main__":
    sys.exit(main())
