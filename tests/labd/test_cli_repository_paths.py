"""A repository named on the command line: a path is the caller's, made absolute before
it is sent (the lab would read it in its own folder); a URL goes as it is, by the same
rule as the lab's (``scheduler.fetch``), which is git's."""

from __future__ import annotations

from pathlib import Path

import pytest

from labd.commands.common import is_url, repository_arg
from scheduler.fetch import SCHEME, SCP, TRANSPORT

URLS = [
    "https://example.org/alice/robot.git",
    "http://localhost:8080/git/ann/pg1.git",
    "ssh://git@example.org/alice/robot.git",
    "git+ssh://example.org/robot",
    "file:///srv/controllers/maze",
    "git@example.org:alice/robot.git",
    "example.org:robot",
    "[::1]:robot",
    "ext::ssh -i key example.org robot",
]
PATHS = ["maze", "./maze/", "../elsewhere/maze", "sub/dir:with-colon", "~/maze", "/srv/maze"]


@pytest.mark.parametrize("given", URLS)
def test_a_url_goes_as_it_is(given):
    assert repository_arg(given) == given


@pytest.mark.parametrize("given", PATHS)
def test_a_path_is_made_absolute_in_the_caller_s_folder(given, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    expected = Path(given).expanduser()
    assert repository_arg(given) == str((tmp_path / expected).resolve())


def test_a_path_through_a_link_is_the_folder_it_names(tmp_path, monkeypatch):
    """The lab records a local repository under its real path: so does the command, so
    ``--repo LINK`` finds what ``submit LINK`` queued."""
    (tmp_path / "real").mkdir()
    (tmp_path / "link").symlink_to(tmp_path / "real")
    monkeypatch.chdir(tmp_path)
    assert repository_arg("link") == str((tmp_path / "real").resolve())


@pytest.mark.parametrize("given", URLS + PATHS)
def test_what_is_a_url_is_what_the_lab_takes_for_one(given):
    """The command and the lab agree on every example (so a path is never sent as one
    the lab would take for a URL, nor a URL rewritten as a path)."""
    lab_says_url = bool(SCHEME.match(given) or TRANSPORT.match(given) or SCP.match(given))
    assert is_url(given) == lab_says_url == (given in URLS)
