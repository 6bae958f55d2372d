"""A checkout's files: read and written by the lab without following a link on the host."""

from __future__ import annotations

import io
import os
from pathlib import Path

import pytest

from scheduler.controller import load
from scheduler.errors import (
    ControllerConfigError,
    FileNotInRepository,
    RepositoryError,
    RepositoryFileError,
    TrialError,
)
from scheduler.files import RepositoryFiles, TreeWriter, parts_of

HOST_FILE_LINES = ["first line of the host's file", "root:x:0:0:root:/root:/bin/bash"]


@pytest.fixture
def host_file(tmp_path: Path) -> Path:
    """A file of the host's, outside any repository, that no message may show."""
    path = tmp_path / "host" / "secret"
    path.parent.mkdir()
    path.write_text("\n".join(HOST_FILE_LINES) + "\n")
    return path


@pytest.fixture
def checkout(tmp_path: Path) -> Path:
    folder = tmp_path / "checkout"
    (folder / "msg").mkdir(parents=True)
    (folder / "lab.toml").write_text('[controller]\ncommand = ["python", "c.py"]\n')
    (folder / "msg" / "Goal.msg").write_text("float64 x\n")
    (folder / "msg" / "Alarm.msg").write_text("bool on\n")
    (folder / "msg" / "notes.txt").write_text("not a definition\n")
    (folder / "msg" / "old").mkdir()
    return folder


def assert_shows_nothing_of(error: BaseException, host_file: Path) -> None:
    text = str(error)
    assert str(host_file) not in text
    for line in HOST_FILE_LINES:
        assert line not in text


def test_regular_files_are_read(checkout: Path) -> None:
    """A regular file, at the root or in a folder, reads as its bytes and text."""
    files = RepositoryFiles(checkout)
    assert files.read_text("lab.toml").startswith("[controller]")
    assert files.read_bytes("msg/Goal.msg") == b"float64 x\n"
    assert files.read_text("./msg//Goal.msg") == "float64 x\n"
    assert files.is_file("lab.toml") and not files.is_file("nothing.toml")


@pytest.mark.parametrize("target", ["absolute", "../../host/secret", "../../../../../../etc"])
def test_a_link_that_leaves_the_repository_is_refused(
    checkout: Path, host_file: Path, target: str
) -> None:
    """A link out of the repository is refused by name, with nothing of what it points at."""
    (checkout / "lab.toml").unlink()
    (checkout / "lab.toml").symlink_to(host_file if target == "absolute" else target)
    files = RepositoryFiles(checkout)
    for read in (files.is_file, files.read_bytes, files.read_text):
        with pytest.raises(RepositoryFileError) as raised:
            read("lab.toml")
        assert str(raised.value) == (
            "lab.toml: it is a symbolic link (to somewhere outside the repository); the lab"
            " reads lab.toml only as a regular file of the repository, never through a link"
        )
        assert_shows_nothing_of(raised.value, host_file)


def test_a_link_within_the_repository_is_refused_and_named(checkout: Path) -> None:
    """Even a link to another file of the repository is not followed; the error says where."""
    (checkout / "conf.toml").symlink_to("msg/../lab.toml")
    with pytest.raises(RepositoryFileError, match=r"to 'lab\.toml' in the repository"):
        RepositoryFiles(checkout).read_text("conf.toml")


def test_a_folder_link_on_the_way_is_refused(checkout: Path, host_file: Path) -> None:
    """A path through a linked folder is refused, naming the link, whatever lies beyond."""
    (checkout / "etc").symlink_to(host_file.parent)
    files = RepositoryFiles(checkout)
    with pytest.raises(RepositoryFileError) as raised:
        files.read_text("etc/secret")
    assert raised.value.name == "etc/secret"
    assert str(raised.value).startswith("etc/secret: etc is a symbolic link (to somewhere outside")
    assert_shows_nothing_of(raised.value, host_file)
    with pytest.raises(RepositoryFileError, match="etc is a symbolic link"):
        files.is_file("etc/nothing-there")  # not even whether something exists beyond


def test_what_is_not_a_regular_file_is_refused(checkout: Path) -> None:
    """A folder, a FIFO (read without blocking) and a name through a file each say what."""
    os.mkfifo(checkout / "pipe")
    files = RepositoryFiles(checkout)
    with pytest.raises(RepositoryFileError, match="it is a folder, not a file"):
        files.read_bytes("msg")
    with pytest.raises(RepositoryFileError, match="it is not a regular file"):
        files.read_bytes("pipe")
    with pytest.raises(FileNotInRepository, match=r"lab.toml is not a folder"):
        files.read_bytes("lab.toml/x")
    with pytest.raises(FileNotInRepository, match="it is not in the repository"):
        files.read_bytes("msg/Nothing.msg")


@pytest.mark.parametrize("name", ["/etc/passwd", "../x", "msg/../../x", ""])
def test_names_outside_the_repository_are_refused(checkout: Path, name: str) -> None:
    """Absolute paths and paths with .. are no names of a repository's files."""
    assert parts_of(name) is None
    with pytest.raises(RepositoryFileError, match="not the path of a file inside the repository"):
        RepositoryFiles(checkout).read_bytes(name)


def test_files_are_read_up_to_a_limit(checkout: Path) -> None:
    """A file larger than the limit is refused rather than read whole."""
    (checkout / "big").write_bytes(b"x" * 5000)
    assert len(RepositoryFiles(checkout, limit=5000).read_bytes("big")) == 5000
    with pytest.raises(RepositoryFileError, match="larger than"):
        RepositoryFiles(checkout, limit=4999).read_bytes("big")


def test_a_folder_of_definitions_is_listed(checkout: Path) -> None:
    """listdir gives the folder's regular files with the suffix, sorted, ready to read."""
    files = RepositoryFiles(checkout)
    names = files.listdir("msg", ".msg")
    assert names == ["msg/Alarm.msg", "msg/Goal.msg"]
    assert [files.read_text(n) for n in names] == ["bool on\n", "float64 x\n"]
    assert "lab.toml" in files.listdir("")


def test_links_in_or_to_a_listed_folder_are_refused(checkout: Path, host_file: Path) -> None:
    """A linked definition, or a linked folder of them, is refused by name."""
    files = RepositoryFiles(checkout)
    (checkout / "msg" / "Secret.msg").symlink_to(host_file)
    with pytest.raises(RepositoryFileError, match=r"^msg/Secret.msg: it is a symbolic link"):
        files.listdir("msg", ".msg")
    assert files.listdir("msg", ".txt") == ["msg/notes.txt"]  # links of no interest are let be
    (checkout / "defs").symlink_to(host_file.parent)
    with pytest.raises(RepositoryFileError, match=r"^defs: it is a symbolic link") as raised:
        files.listdir("defs", ".msg")
    assert_shows_nothing_of(raised.value, host_file)
    with pytest.raises(RepositoryFileError, match="it is a file, not a folder"):
        files.listdir("lab.toml")


def test_lab_toml_as_a_link_is_a_trial_error(checkout: Path, host_file: Path) -> None:
    """load() refuses a linked lab.toml with an error the runner reports as the reason."""
    (checkout / "lab.toml").unlink()
    (checkout / "lab.toml").symlink_to(host_file)
    with pytest.raises(TrialError) as raised:
        load(checkout)
    assert isinstance(raised.value, RepositoryFileError)
    assert str(raised.value).startswith("lab.toml: it is a symbolic link")
    assert_shows_nothing_of(raised.value, host_file)


@pytest.mark.parametrize(
    ("layout", "expected"),
    [
        ("absolute", "requirements.txt: it is a symbolic link (to somewhere outside"),
        ("folder", "deps/requirements.txt: deps is a symbolic link (to somewhere outside"),
        ("binary", "requirements.txt: it is not UTF-8 text"),
    ],
)
def test_the_requirements_file_is_read_as_the_repositorys_own(
    checkout: Path, host_file: Path, layout: str, expected: str
) -> None:
    """A linked requirements file (or folder) or a binary one is refused before installing."""
    name = "deps/requirements.txt" if layout == "folder" else "requirements.txt"
    if layout == "absolute":
        (checkout / name).symlink_to(host_file)
    elif layout == "folder":
        (checkout / "deps").symlink_to(host_file.parent)
        host_file.with_name("requirements.txt").write_text("six\n")
    else:
        (checkout / name).write_bytes(b"\xff\xfe six\n")
    (checkout / "lab.toml").write_text(f'[controller]\ncommand = ["x"]\nrequirements = "{name}"\n')
    with pytest.raises(RepositoryFileError) as raised:
        load(checkout)
    assert str(raised.value).startswith(expected)
    assert_shows_nothing_of(raised.value, host_file)


def test_lab_toml_that_is_not_text_is_a_config_error(checkout: Path) -> None:
    """Read through the same reader, a binary lab.toml says so as before."""
    (checkout / "lab.toml").write_bytes(b"\xff\xfe")
    with pytest.raises(ControllerConfigError, match=r"lab\.toml: it is not UTF-8 text"):
        load(checkout)


def test_the_writer_never_writes_through_a_link(tmp_path: Path) -> None:
    """Links are made as they are, and a file behind one is refused, not written outside."""
    outside = tmp_path / "outside"
    outside.mkdir()
    dest = tmp_path / "dest"
    dest.mkdir()
    with TreeWriter(dest, "repo") as writer:
        writer.symlink("data", str(outside))
        writer.symlink("lib", "../outside")
        writer.file("src/c.py", io.BytesIO(b"print(1)\n"), executable=True)
        for name in ("data/x", "lib/x", "data/deeper/x"):
            with pytest.raises(RepositoryError, match=f"{name} lies behind the symbolic link"):
                writer.file(name, io.BytesIO(b"pwned"), executable=False)
        with pytest.raises(RepositoryError, match="data is both a symbolic link and a folder"):
            writer.directory("data")
        with pytest.raises(RepositoryError, match=r"src/c\.py appears twice"):
            writer.file("src/c.py", io.BytesIO(b"again"), executable=False)
        with pytest.raises(RepositoryError, match="not a path inside the repository"):
            writer.file("../escape", io.BytesIO(b"pwned"), executable=False)
    assert list(outside.iterdir()) == []
    assert not (tmp_path / "escape").exists()
    assert os.readlink(dest / "data") == str(outside) and os.readlink(dest / "lib") == "../outside"
    assert (dest / "src" / "c.py").stat().st_mode & 0o777 == 0o755
