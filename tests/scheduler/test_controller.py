"""lab.toml: what a repository must say, and the errors when it does not."""

from __future__ import annotations

import re

import pytest

from scheduler.controller import load
from scheduler.errors import ControllerConfigError


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
    ],
)
def test_broken_files_say_what_is_wrong(tmp_path, text, expected):
    """Each way of getting lab.toml wrong gives an error a person can act on."""
    if text is not None:
        write(tmp_path, text)
    with pytest.raises(ControllerConfigError, match=re.escape(expected)):
        load(tmp_path)
