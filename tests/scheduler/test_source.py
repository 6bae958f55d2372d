"""Where code comes from: folders, git work trees, and repositories by URL."""

from __future__ import annotations

import subprocess

import pytest

from scheduler.errors import RepositoryError
from scheduler.source import checkout, tree_digest


def git(cwd, *args):
    return subprocess.run(
        ["git", *args], cwd=cwd, check=True, capture_output=True, text=True
    ).stdout.strip()


@pytest.fixture
def repo(tmp_path):
    """A real git repository with two commits and a tag."""
    path = tmp_path / "repo"
    path.mkdir()
    git(path, "init", "-q", "-b", "main")
    git(path, "config", "user.email", "t@example.org")
    git(path, "config", "user.name", "Test")
    (path / "lab.toml").write_text('[controller]\ncommand = ["python", "c.py"]\n')
    (path / "c.py").write_text("print(1)\n")
    (path / "sub").mkdir()
    (path / "sub" / "x.txt").write_text("x\n")
    git(path, "add", "-A")
    git(path, "commit", "-q", "-m", "one")
    git(path, "tag", "v1")
    (path / "c.py").write_text("print(2)\n")
    git(path, "commit", "-q", "-am", "two")
    return path


def test_clean_work_tree_runs_head(repo, tmp_path):
    """A clean folder runs as it is, named by HEAD's commit and tree."""
    source = checkout(str(repo), None, tmp_path / "out", tmp_path / "cache")
    assert source.commit == git(repo, "rev-parse", "HEAD")
    assert source.git_tree == git(repo, "rev-parse", "HEAD^{tree}")
    assert not source.dirty and (tmp_path / "out" / "c.py").read_text() == "print(2)\n"
    assert not (tmp_path / "out" / ".git").exists()


def test_dirty_work_tree_runs_the_edit_without_a_commit(repo, tmp_path):
    """Uncommitted changes are run, and then the code has no commit to name it."""
    (repo / "c.py").write_text("print(3)\n")
    (repo / "new.py").write_text("print('new')\n")
    source = checkout(str(repo), None, tmp_path / "out", tmp_path / "cache")
    assert source.dirty and source.commit is None
    assert (tmp_path / "out" / "new.py").exists()
    assert (tmp_path / "out" / "c.py").read_text() == "print(3)\n"


def test_ref_exports_that_commit(repo, tmp_path):
    """With --ref, the files of that commit run, whatever the work tree holds."""
    (repo / "c.py").write_text("print(3)\n")
    source = checkout(str(repo), "v1", tmp_path / "out", tmp_path / "cache")
    assert source.commit == git(repo, "rev-parse", "v1^{commit}")
    assert (tmp_path / "out" / "c.py").read_text() == "print(1)\n"


def test_subfolder_of_a_repository(repo, tmp_path):
    """A folder inside a repository is the code; the record says which subfolder."""
    source = checkout(str(repo / "sub"), None, tmp_path / "out", tmp_path / "cache")
    assert source.subdir == "sub" and source.commit == git(repo, "rev-parse", "HEAD")
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["x.txt"]


def test_url_resolves_refs_to_commits(repo, tmp_path):
    """A URL is fetched into a mirror and the ref's commit is exported; a bad ref says so."""
    url = f"file://{repo}"
    cache = tmp_path / "cache"
    head = checkout(url, None, tmp_path / "a", cache)
    tagged = checkout(url, "v1", tmp_path / "b", cache)
    assert head.commit == git(repo, "rev-parse", "HEAD")
    assert tagged.commit == git(repo, "rev-parse", "v1^{commit}")
    assert (tmp_path / "b" / "c.py").read_text() == "print(1)\n"
    short = checkout(url, head.commit[:8], tmp_path / "c", cache)
    assert short.commit == head.commit and short.tree == head.tree
    with pytest.raises(RepositoryError, match="'nope' is not a branch, tag or commit of"):
        checkout(url, "nope", tmp_path / "d", cache)


def test_unreachable_url_and_missing_folder(tmp_path):
    """A URL that cannot be fetched, and a folder that does not exist, are clear errors."""
    with pytest.raises(RepositoryError, match="could not be fetched"):
        checkout(f"file://{tmp_path}/nothing-here", None, tmp_path / "a", tmp_path / "cache")
    with pytest.raises(RepositoryError, match="no such folder"):
        checkout(str(tmp_path / "nothing"), None, tmp_path / "b", tmp_path / "cache")


def test_tree_digest_names_content(tmp_path):
    """The tree digest changes with any content or executable bit, not with the location."""
    a, b = tmp_path / "a", tmp_path / "b"
    for folder in (a, b):
        folder.mkdir()
        (folder / "f.py").write_text("x = 1\n")
    assert tree_digest(a) == tree_digest(b)
    (b / "f.py").chmod(0o755)
    assert tree_digest(a) != tree_digest(b)
