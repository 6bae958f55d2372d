"""A controller's life in each backend: its output, its exit, what it can import, who it is."""

from __future__ import annotations

import json
import signal

import pytest

from sandbox.api import Limits
from sandbox.runtime import SANDBOX_UID
from tests.sandbox.conftest import Controllers, lines

pytestmark = [pytest.mark.integration, pytest.mark.timeout(300)]


async def test_output_and_exit_zero_are_captured(controllers: Controllers) -> None:
    """A controller that prints and exits 0 ends with code 0 and its stdout and stderr."""
    ended = await controllers.run(
        """
        import sys
        print("hello from the sandbox")
        print("and from stderr", file=sys.stderr)
        """
    )
    assert (ended.code, ended.signal) == (0, None)
    assert ended.stdout == b"hello from the sandbox\n"
    assert ended.stderr == b"and from stderr\n"
    assert not (ended.out_of_memory or ended.output_exceeded or ended.wall_exceeded)
    assert 0 < ended.seconds < 30


async def test_exit_code_is_the_controllers(controllers: Controllers) -> None:
    """A controller's exit status 3 is the job's exit code."""
    ended = await controllers.run("raise SystemExit(3)")
    assert (ended.code, ended.signal) == (3, None)


async def test_an_exception_gives_code_1_and_a_traceback(controllers: Controllers) -> None:
    """An uncaught exception ends the job with code 1 and its traceback on stderr."""
    ended = await controllers.run(
        """
        def act():
            raise ValueError("the robot is upside down")
        act()
        """
    )
    assert ended.code == 1
    assert b"Traceback (most recent call last):" in ended.stderr
    assert b'File "/code/controller.py", line 3, in act' in ended.stderr
    assert lines(ended.stderr)[-1] == "ValueError: the robot is upside down"


async def test_a_missing_command_says_so(controllers: Controllers) -> None:
    """A command that does not exist ends with 127 and a message naming it."""
    ended = await controllers.run("", command=["no-such-program"])
    assert ended.code == 127
    assert b"no-such-program" in ended.stderr


async def test_runtime_packages_import(controllers: Controllers) -> None:
    """numpy, websockets, roslibpy and the lab's controllers library import, pinned."""
    ended = await controllers.run(
        """
        import json
        import numpy, websockets, roslibpy, controllers.client
        print(json.dumps({
            "numpy": numpy.__version__,
            "websockets": websockets.__version__,
            "roslibpy": roslibpy.__version__,
            "controllers": controllers.client.Lab.__name__,
            "sum": float(numpy.linalg.solve([[2.0, 0.0], [0.0, 4.0]], [2.0, 8.0]).sum()),
        }))
        """
    )
    assert ended.code == 0, ended.stderr
    assert json.loads(ended.stdout) == {
        "numpy": "2.4.6",
        "websockets": "17.4",
        "roslibpy": "2.1.0",
        "controllers": "Lab",
        "sum": 3.0,
    }


async def test_host_only_packages_do_not_import(controllers: Controllers) -> None:
    """Packages of the lab's host Python (mujoco, dm_control, pytest, docker) are not there."""
    ended = await controllers.run(
        """
        import importlib, sys
        for name in ["mujoco", "dm_control", "pytest", "docker", "labd", "sandbox"]:
            try:
                importlib.import_module(name)
                print(name, "imported")
            except ModuleNotFoundError:
                print(name, "missing")
        print("site", [p for p in sys.path if "site-packages" in p])
        """
    )
    assert ended.code == 0, ended.stderr
    assert lines(ended.stdout) == [
        "mujoco missing",
        "dm_control missing",
        "pytest missing",
        "docker missing",
        "labd missing",
        "sandbox missing",
        "site ['/opt/labd/site-packages']",
    ]


async def test_environment_is_the_runtimes(controllers: Controllers) -> None:
    """The controller runs in /code with the runtime's environment, plus the job's."""
    ended = await controllers.run(
        """
        import json, os, shutil, sys, tempfile
        print(json.dumps({
            "cwd": os.getcwd(),
            "home": os.path.expanduser("~"),
            "tmp": tempfile.gettempdir(),
            "python": shutil.which("python"),
            "python3": shutil.which("python3"),
            "executable": sys.executable,
            "bridge": os.environ.get("LAB_BRIDGE_URL"),
            "extra": os.environ.get("TRIAL_SEED"),
            "bytecode": sys.dont_write_bytecode,
            "user_site": os.environ.get("PYTHONNOUSERSITE"),
        }))
        """,
        env={"TRIAL_SEED": "7"},
    )
    assert ended.code == 0, ended.stderr
    seen = json.loads(ended.stdout)
    assert seen["cwd"] == "/code"
    assert seen["home"] == "/scratch/home"
    assert seen["tmp"] == "/scratch/tmp"
    assert seen["python"] and seen["python"].endswith("/bin/python")
    assert seen["python3"] and seen["python3"].endswith("/bin/python3")
    assert seen["bridge"] is None  # no bridge for this job
    assert seen["extra"] == "7"
    assert seen["bytecode"] is True
    assert seen["user_site"] == "1"


async def test_runs_as_an_unprivileged_user(controllers: Controllers) -> None:
    """The controller is uid and gid 64000, in no other group, with no capabilities."""
    ended = await controllers.run(
        """
        import os, pwd
        status = dict(line.split(":", 1) for line in open("/proc/self/status"))
        print(os.getuid(), os.geteuid(), os.getgid(), os.getgroups())
        print(pwd.getpwuid(os.getuid()).pw_name)
        print(int(status["CapEff"], 16), int(status["CapPrm"], 16), status["NoNewPrivs"].strip())
        """
    )
    assert ended.code == 0, ended.stderr
    uid, euid, gid, groups = lines(ended.stdout)[0].split(" ", 3)
    assert int(uid) == int(euid) == int(gid) == SANDBOX_UID
    assert groups in ("[]", f"[{SANDBOX_UID}]")
    assert lines(ended.stdout)[1] == "sandbox"
    cap_eff, cap_prm, _ = lines(ended.stdout)[2].split()
    assert (cap_eff, cap_prm) == ("0", "0")


async def test_the_launcher_is_pid_1_and_the_controller_its_child(
    controllers: Controllers,
) -> None:
    """The controller's parent is pid 1 (the launcher); it sees no process of the host."""
    ended = await controllers.run(
        """
        import os
        pids = sorted(int(p) for p in os.listdir("/proc") if p.isdigit())
        print(os.getppid(), pids == [1, os.getpid()])
        """
    )
    assert ended.code == 0, ended.stderr
    assert ended.stdout == b"1 True\n"


async def test_a_signal_death_is_reported_as_the_signal(controllers: Controllers) -> None:
    """A controller killed by a signal (here its own SIGABRT) ends with that signal, no code."""
    ended = await controllers.run("import os; os.abort()", limits=Limits(wall=30))
    assert (ended.code, ended.signal) == (None, signal.SIGABRT)
