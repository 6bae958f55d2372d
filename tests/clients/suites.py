"""Run roslibpy's and roslibjs' own ROS 2 test suites against a real ``labd serve``.

Their suites expect a rosbridge server at ``ws://127.0.0.1:9090`` (written into their
tests) with the tutorials' nodes beside it. So this runs, in a network namespace of its
own (``unshare --net``: port 9090 there is nobody else's, and nothing leaves it):

1. ``labd serve --no-robots --no-service --bridge-port 9090``, the lab's playground
   graph at the root path;
2. ``tests/clients/fixtures.py``, an ordinary bridge client playing the tutorials'
   Fibonacci action server, ``/add_two_ints``, ``/listener`` and a static transform;
3. the suite, unmodified, and prints one JSON object: each test's outcome.

roslibpy's tests ship in its source distribution on PyPI: ``roslibpy`` downloads the
sdist of the installed version (``pip download --no-binary``) into ``--cache`` and runs
its ``tests/ros2`` with pytest, once per transport (``twisted``, ``asyncio``).
roslibjs' tests are not in its npm package; ``roslibjs --tests DIR`` runs the vitest
files a person put in DIR (from the roslibjs repository, imports pointed at ``roslib``)
with the installed ``roslib`` and vitest. docs/protocol.md says which pass.

    python -m tests.clients.suites roslibpy --cache DIR     # then in a namespace of its own
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import shutil
import socket
import subprocess
import sys
import tarfile
import tempfile
import time
import xml.etree.ElementTree as ET
from collections.abc import Iterator
from importlib import metadata
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[2]
PORT = 9090  # written into both suites
STARTUP = 60.0  # seconds for labd serve and the fixtures to come up
SUITE_TIMEOUT = 600.0
LABD_SERVE = [sys.executable, "-m", "labd", "serve", "--no-robots", "--no-service"]
FIXTURES = [sys.executable, "-m", "tests.clients.fixtures"]
PIP_DOWNLOAD = [sys.executable, "-m", "pip", "download", "--quiet", "--no-deps"]
VITEST = ["npx", "vitest", "run", "--reporter=default", "--reporter=junit"]
PYTEST = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider"]


def _wait_for_port(deadline: float) -> None:
    while time.monotonic() < deadline:
        with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", PORT), 1):
            return
        time.sleep(0.1)
    raise SystemExit(f"labd serve did not listen on 127.0.0.1:{PORT} within {STARTUP:g} s")


@contextlib.contextmanager
def served_with_fixtures(fibonacci_type: str, data: Path) -> Iterator[None]:
    """labd serve and the fixtures, in this network namespace, for the ``with`` block."""
    subprocess.run(["ip", "link", "set", "lo", "up"], check=True)
    with socket.socket() as probe:
        try:
            probe.bind(("127.0.0.1", PORT))
        except OSError:
            raise SystemExit(
                f"127.0.0.1:{PORT} is taken: run this in a network namespace of its own"
                " (unshare --net --fork)"
            ) from None
    serve = subprocess.Popen(
        [*LABD_SERVE, "--bridge-port", str(PORT), "--data", str(data)],
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    fixtures: subprocess.Popen[str] | None = None
    try:
        deadline = time.monotonic() + STARTUP
        _wait_for_port(deadline)
        fixtures = subprocess.Popen(
            [*FIXTURES, f"ws://127.0.0.1:{PORT}", "--fibonacci-type", fibonacci_type],
            cwd=ROOT,
            stdout=subprocess.PIPE,
            text=True,
        )
        assert fixtures.stdout is not None
        if fixtures.stdout.readline().strip() != "ready":
            raise SystemExit("the fixtures did not come up")
        yield
    finally:
        for process in (fixtures, serve):
            if process is not None:
                process.terminate()
                try:
                    process.wait(10)
                except subprocess.TimeoutExpired:
                    process.kill()
                    process.wait()


def roslibpy_tests(cache: Path) -> Path:
    """The ``tests`` folder of the installed roslibpy's sdist, downloaded once into ``cache``."""
    version = metadata.version("roslibpy")
    folder = cache / f"roslibpy-{version}"
    if not (folder / "tests" / "ros2").is_dir():
        with tempfile.TemporaryDirectory() as download:
            subprocess.run(
                [*PIP_DOWNLOAD, "--no-binary", ":all:", f"roslibpy=={version}", "-d", download],
                check=True,
            )
            (archive,) = Path(download).glob("roslibpy-*.tar.gz")
            with tarfile.open(archive) as sdist:
                members = [m for m in sdist.getmembers() if m.isfile()]
                sdist.extractall(cache / "partial", members=members, filter="data")
        shutil.rmtree(folder, ignore_errors=True)
        (cache / "partial" / f"roslibpy-{version}").rename(folder)
        shutil.rmtree(cache / "partial", ignore_errors=True)
    return folder


def _junit(path: Path) -> dict[str, str]:
    """test id -> passed, failed or skipped (with the reason), from a JUnit XML report."""
    outcomes: dict[str, str] = {}
    for case in ET.parse(path).getroot().iter("testcase"):
        name = f"{case.get('classname')}::{case.get('name')}"
        failed = case.find("failure") if case.find("failure") is not None else case.find("error")
        skipped = case.find("skipped")
        if failed is not None:
            outcomes[name] = f"failed: {(failed.get('message') or '')[:300]}"
        elif skipped is not None:
            outcomes[name] = f"skipped: {skipped.get('message') or ''}"
        else:
            outcomes[name] = "passed"
    return outcomes


def in_namespace(*args: str) -> dict[str, Any]:
    """Run this module with ``--inside ARGS`` in a network namespace of its own; its results."""
    unshare = shutil.which("unshare")
    if unshare is None:
        raise SystemExit("unshare (util-linux) is needed for a network namespace")
    as_user = [] if os.geteuid() == 0 else ["--map-root-user"]
    proc = subprocess.run(
        [
            unshare,
            "--net",
            "--fork",
            *as_user,
            sys.executable,
            "-m",
            __spec__.name,
            "--inside",
            *args,
        ],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        text=True,
        timeout=3 * SUITE_TIMEOUT,
        check=False,
    )
    if proc.returncode != 0:
        raise SystemExit(f"the suite's run in a network namespace exited with {proc.returncode}")
    result: dict[str, Any] = json.loads(proc.stdout)
    return result


def run_roslibpy(suite: Path, transports: list[str]) -> dict[str, Any]:
    results: dict[str, Any] = {}
    with (
        tempfile.TemporaryDirectory() as work,
        served_with_fixtures("example_interfaces/action/Fibonacci", Path(work) / "data"),
    ):
        for transport in transports:
            report = Path(work) / f"{transport}.xml"
            env = {**os.environ, "ROSLIBPY_TRANSPORT": transport}
            subprocess.run(
                [*PYTEST, f"--junitxml={report}", "tests/ros2"],
                cwd=suite,
                env=env,
                timeout=SUITE_TIMEOUT,
                check=False,
                stdout=sys.stderr,
            )
            results[transport] = _junit(report)
    return results


def run_roslibjs(tests: Path, distro: str) -> dict[str, Any]:
    results: dict[str, Any] = {}
    with (
        tempfile.TemporaryDirectory() as work,
        served_with_fixtures("action_tutorials_interfaces/action/Fibonacci", Path(work) / "data"),
    ):
        report = Path(work) / "vitest.xml"
        env = {**os.environ, "ROS_DISTRO": distro, "ROS_VERSION": "2"}
        subprocess.run(
            [*VITEST, f"--outputFile.junit={report}"],
            cwd=tests,
            env=env,
            timeout=SUITE_TIMEOUT,
            check=False,
            stdout=sys.stderr,
        )
        results["vitest"] = _junit(report)
    return results


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--inside", action="store_true", help=argparse.SUPPRESS)
    sub = parser.add_subparsers(dest="suite", required=True)
    py = sub.add_parser("roslibpy", help="roslibpy's tests/ros2, from its sdist")
    py.add_argument("--cache", type=Path, help="where the sdist is kept (downloaded once)")
    py.add_argument("--tests", type=Path, help=argparse.SUPPRESS)  # the sdist's folder
    py.add_argument(
        "--transport", action="append", choices=["twisted", "asyncio"], dest="transports"
    )
    js = sub.add_parser("roslibjs", help="roslibjs' vitest files in --tests")
    js.add_argument("--tests", type=Path, required=True)
    js.add_argument(
        "--ros-distro",
        default="humble",
        help="ROS_DISTRO for their skipIf (humble: their ROS 2 action tests run)",
    )
    args = parser.parse_args(argv)
    transports = args.transports or ["twisted", "asyncio"] if args.suite == "roslibpy" else []
    if args.inside and args.suite == "roslibpy":
        results = run_roslibpy(args.tests, transports)
    elif args.inside:
        results = run_roslibjs(args.tests, args.ros_distro)
    elif args.suite == "roslibpy":
        if args.cache is None:
            parser.error("roslibpy needs --cache")
        tests = roslibpy_tests(args.cache.resolve())  # downloaded here: the namespace has no net
        flags = [f"--transport={t}" for t in transports]
        results = in_namespace("roslibpy", f"--tests={tests}", *flags)
    else:
        tests = args.tests.resolve()
        results = in_namespace("roslibjs", f"--tests={tests}", f"--ros-distro={args.ros_distro}")
    print(json.dumps(results, indent=2, sort_keys=True))
    return 0


if __name__ == "__main__":
    sys.exit(main())
