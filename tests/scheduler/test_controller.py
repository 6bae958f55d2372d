"""lab.toml: what a repository must say, and the errors when it does not."""

from __future__ import annotations

import re

import pytest

from scheduler.controller import load
from scheduler.errors import ControllerConfigError, NodePackagesError, RepositoryFileError


def write(tmp_path, text):
    (tmp_path / "lab.toml").write_text(text)
    return tmp_path


def test_a_complete_file(tmp_path):
    """Every key is read, and the text is kept for the record."""
    (tmp_path / "requirements.txt").write_text("six\n")
    text = (
        '[controller]\ncommand = ["python", "controller.py"]\ntask = "icreate-maze"\n'
        'requirements = "requirements.txt"\nrealtime = true\n'
    )
    config = load(write(tmp_path, text))
    assert config.command == ("python", "controller.py")
    assert config.task == "icreate-maze" and config.requirements == "requirements.txt"
    assert config.realtime is True and config.text == text


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        (None, "has no lab.toml"),
        ("[controller\ncommand = 1", "not valid TOML"),
        ("[robot]\n", "needs a [controller] table"),
        ("[controller]\ntask = 'icreate-maze'\n", "needs command"),
        ('[controller]\ncommand = "python controller.py"\n', "must be a list of strings"),
        ("[controller]\ncommand = []\n", "non-empty list"),
        ('[controller]\ncommand = ["python", 3]\n', "every item of command"),
        ('[controller]\ncommand = ["x"]\nrealtime = "yes"\n', "realtime must be true or false"),
        ('[controller]\ncommand = ["x"]\nspeed = 3\n', "has no key 'speed'"),
        (
            '[controller]\ncommand = ["x"]\nrequirements = "../etc/passwd"\n',
            "inside the repository",
        ),
        ('[controller]\ncommand = ["x"]\nrequirements = "missing.txt"\n', "not in the repository"),
        (
            '[controller]\ncommand = ["x"]\n[data]\ntrials = [9223372036854775808]\n',
            "[data] trials: 9223372036854775808 is no trial id (trial ids are 1 to 2147483647)",
        ),
    ],
)
def test_broken_files_say_what_is_wrong(tmp_path, text, expected):
    """Each way of getting lab.toml wrong gives an error a person can act on."""
    if text is not None:
        write(tmp_path, text)
    with pytest.raises(ControllerConfigError, match=re.escape(expected)):
        load(tmp_path)


def interfaces_repo(tmp_path):
    """A repository with two interface packages, one with a file the lab does not read."""
    (tmp_path / "msgs" / "planner_msgs" / "msg").mkdir(parents=True)
    (tmp_path / "msgs" / "planner_msgs" / "msg" / "Debug.msg").write_text("string phase\n")
    (tmp_path / "msgs" / "planner_msgs" / "msg" / "notes.txt").write_text("not a type\n")
    (tmp_path / "msgs" / "planner_msgs" / "srv").mkdir()
    (tmp_path / "msgs" / "planner_msgs" / "srv" / "Reset.srv").write_text("---\nbool ok\n")
    (tmp_path / "arm_msgs" / "action").mkdir(parents=True)
    (tmp_path / "arm_msgs" / "action" / "Reach.action").write_text("float64 x\n---\n---\n")
    return tmp_path


def test_interfaces_are_read_with_their_paths(tmp_path):
    """interfaces names package folders (one or a list); their msg/, srv/ and action/ files
    are read with their paths, and digested for the manifest."""
    root = interfaces_repo(tmp_path)
    text = '[controller]\ncommand = ["x"]\ninterfaces = ["msgs/planner_msgs", "arm_msgs/"]\n'
    config = load(write(root, text))
    assert config.interfaces == ("msgs/planner_msgs", "arm_msgs")
    assert config.interface_files == {
        "msgs/planner_msgs/msg/Debug.msg": "string phase\n",
        "msgs/planner_msgs/srv/Reset.srv": "---\nbool ok\n",
        "arm_msgs/action/Reach.action": "float64 x\n---\n---\n",
    }
    digest = config.interfaces_sha256
    assert digest is not None and len(digest) == 64
    (root / "arm_msgs" / "action" / "Reach.action").write_text("float64 y\n---\n---\n")
    assert load(root).interfaces_sha256 != digest
    single = load(write(root, '[controller]\ncommand = ["x"]\ninterfaces = "arm_msgs"\n'))
    assert list(single.interface_files) == ["arm_msgs/action/Reach.action"]
    assert load(write(root, '[controller]\ncommand = ["x"]\n')).interfaces_sha256 is None


@pytest.mark.parametrize(
    ("value", "expected"),
    [
        ("3", "interfaces must name a folder"),
        ('"../outside"', "folders inside the repository"),
        ('"missing_msgs"', "names 'missing_msgs', which is not a folder of the repository"),
        ('"empty_msgs"', "has no msg/*.msg, srv/*.srv or action/*.action file"),
    ],
)
def test_bad_interfaces_say_what_is_wrong(tmp_path, value, expected):
    """A folder outside, missing or holding no interface file is refused with a reason."""
    (tmp_path / "empty_msgs" / "msg").mkdir(parents=True)
    write(tmp_path, f'[controller]\ncommand = ["x"]\ninterfaces = {value}\n')
    with pytest.raises(ControllerConfigError, match=re.escape(expected)):
        load(tmp_path)


def test_interfaces_are_never_read_through_a_link(tmp_path):
    """A linked msg/ folder or .msg file is refused, naming it (the lab would read it on its
    own host)."""
    root = interfaces_repo(tmp_path)
    outside = tmp_path.parent / f"{tmp_path.name}-outside"
    outside.mkdir()
    (outside / "Secret.msg").write_text("string password\n")
    (root / "msgs" / "planner_msgs" / "msg" / "Secret.msg").symlink_to(outside / "Secret.msg")
    write(root, '[controller]\ncommand = ["x"]\ninterfaces = "msgs/planner_msgs"\n')
    with pytest.raises(
        RepositoryFileError, match=r"msgs/planner_msgs/msg/Secret\.msg: it is a symbolic"
    ):
        load(root)
    (root / "msgs" / "planner_msgs" / "msg" / "Secret.msg").unlink()
    (root / "arm_msgs" / "msg").symlink_to(outside)
    write(root, '[controller]\ncommand = ["x"]\ninterfaces = "arm_msgs"\n')
    with pytest.raises(RepositoryFileError, match="arm_msgs/msg: it is a symbolic link"):
        load(root)


@pytest.mark.parametrize(
    ("package", "lock", "installs"),
    [
        (None, False, False),
        ('{"name": "x", "type": "module"}', False, False),
        ('{"devDependencies": {"eslint": "9.0.0"}}', False, False),
        ('{"dependencies": {}}', False, False),
        ('{"dependencies": {"three": "0.170.0"}}', True, True),
    ],
    ids=["none", "no-dependencies", "dev-only", "empty", "dependencies-and-lock"],
)
def test_npm_packages_are_installed_when_package_json_names_dependencies(
    tmp_path, package, lock, installs
):
    """Only dependencies (not devDependencies) call for the build step's npm ci."""
    write(tmp_path, '[controller]\ncommand = ["node", "controller.mjs"]\n')
    if package is not None:
        (tmp_path / "package.json").write_text(package)
    if lock:
        (tmp_path / "package-lock.json").write_text("{}")
    assert load(tmp_path).node_packages is installs


@pytest.mark.parametrize(
    ("package", "expected"),
    [
        ('{"dependencies": {"three": "0.170.0", "ms": "2.1.3"}}', "names dependencies (ms, three)"),
        ("{not json", "package.json is not valid JSON"),
        ('{"dependencies": ["three"]}', "package.json: dependencies must be an object"),
    ],
    ids=["no-lock", "not-json", "not-an-object"],
)
def test_bad_npm_packages_say_what_is_wrong(tmp_path, package, expected):
    """A package.json with dependencies but no lock file, or that is not what npm reads, is
    refused with what to do."""
    write(tmp_path, '[controller]\ncommand = ["node", "controller.mjs"]\n')
    (tmp_path / "package.json").write_text(package)
    with pytest.raises(NodePackagesError, match=re.escape(expected)):
        load(tmp_path)


def test_a_linked_lock_file_is_refused(tmp_path):
    """package-lock.json as a symbolic link is refused, never read on the lab's host."""
    write(tmp_path, '[controller]\ncommand = ["node", "controller.mjs"]\n')
    (tmp_path / "package.json").write_text('{"dependencies": {"ms": "2.1.3"}}')
    (tmp_path / "package-lock.json").symlink_to("/etc/passwd")
    with pytest.raises(RepositoryFileError, match=r"package-lock\.json: it is a symbolic link"):
        load(tmp_path)


def test_tasks_lists_the_tasks_a_controller_supports(tmp_path):
    """``tasks`` is read as the tuple of names it lists, in its order; without it, empty."""
    listed = load(
        write(
            tmp_path,
            '[controller]\ncommand = ["x"]\ntasks = ["dmc-cartpole-balance", "dmc-reacher-easy"]\n',
        )
    )
    assert listed.tasks == ("dmc-cartpole-balance", "dmc-reacher-easy")
    assert load(write(tmp_path, '[controller]\ncommand = ["x"]\n')).tasks == ()


@pytest.mark.parametrize(
    ("value", "expected"),
    [
        ('"dmc-cartpole-balance"', "tasks must be a non-empty list of task names"),
        ("[]", "tasks must be a non-empty list of task names"),
        ('["dmc-cartpole-balance", 3]', "every item of tasks must be a task's name, not 3"),
        ('["dmc-cartpole-balance", ""]', "every item of tasks must be a task's name, not ''"),
        ('["a", "b", "a"]', "tasks names 'a' more than once"),
    ],
)
def test_bad_tasks_say_what_is_wrong(tmp_path, value, expected):
    """A ``tasks`` that is not a list of distinct task names is refused, saying why."""
    write(tmp_path, f'[controller]\ncommand = ["x"]\ntasks = {value}\n')
    with pytest.raises(ControllerConfigError, match=re.escape(expected)):
        load(tmp_path)
