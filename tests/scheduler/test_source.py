"""Where code comes from: folders, git work trees, and repositories by URL."""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import tracemalloc

import pytest

from scheduler.errors import CheckoutTooLarge, RepositoryError
from scheduler.fetch import FetchPolicy
from scheduler.source import Expanded, checkout, expanded_size, tree_digest
from tests.helpers.githttp import GitRepo, Link


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


LINKS = {
    "lab.toml": Link("/etc/passwd"),  # the lab refuses to read it, later (test_files.py)
    "data": Link("/mnt/x"),  # the controller's business, inside its sandbox
    "lib": Link("sub"),
    "up": Link("../../.."),
    "sub/x.txt": "x\n",
}


def linked(tmp_path):
    return GitRepo.create(tmp_path / "linked", LINKS)


def assert_links_kept(dest):
    for name, link in LINKS.items():
        if isinstance(link, Link):
            assert os.readlink(dest / name) == link.target, name
    assert (dest / "sub" / "x.txt").read_text() == "x\n"


def test_a_repositorys_links_are_checked_out_as_they_are(tmp_path):
    """Every way of taking code keeps its links, named by their text, and agrees on the tree."""
    repo = linked(tmp_path)
    plain = tmp_path / "plain"
    shutil.copytree(repo.path, plain, symlinks=True, ignore=shutil.ignore_patterns(".git"))
    ways = {
        "url": (repo.url, None),
        "work tree": (str(repo.path), None),
        "ref": (str(repo.path), "main"),
        "plain folder": (str(plain), None),
    }
    trees = set()
    for way, (source, ref) in ways.items():
        dest = tmp_path / "out" / way
        trees.add(checkout(source, ref, dest, tmp_path / "cache").tree)
        assert_links_kept(dest)
    assert len(trees) == 1


def crafted(tmp_path, outside):
    """A repository whose one commit has a link ``a`` and a file ``a/b`` (git fsck would
    complain; git archive writes both), to make an export write through the link."""
    repo = GitRepo.create(tmp_path / "crafted")
    target = repo.git("hash-object", "-w", "--stdin", input=str(outside))
    blob = repo.git("hash-object", "-w", "--stdin", input="pwned\n")
    inner = repo.git("mktree", input=f"100644 blob {blob}\tb\n")
    tree = repo.git("mktree", input=f"120000 blob {target}\ta\n040000 tree {inner}\ta\n")
    commit = repo.git("commit-tree", tree, "-m", "crafted")
    repo.git("update-ref", "refs/heads/main", commit)
    return repo


def test_an_export_never_writes_through_a_link(tmp_path):
    """A tree that would write a file through its own link is a RepositoryError; nothing
    lands outside the checkout."""
    outside = tmp_path / "outside"
    outside.mkdir()
    repo = crafted(tmp_path, outside)
    for n, (source, ref) in enumerate([(repo.url, None), (str(repo.path), "main")]):
        with pytest.raises(RepositoryError, match="a is both a symbolic link and a folder"):
            checkout(source, ref, tmp_path / f"out-{n}", tmp_path / "cache")
    assert list(outside.iterdir()) == []


def test_a_work_tree_is_copied_without_following_its_links(repo, tmp_path):
    """A tracked folder replaced by a link: what lies behind the link is not copied."""
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "x.txt").write_text("the host's\n")
    shutil.rmtree(repo / "sub")
    (repo / "sub").symlink_to(elsewhere)
    source = checkout(str(repo), None, tmp_path / "out", tmp_path / "cache")
    assert source.dirty
    assert os.readlink(tmp_path / "out" / "sub") == str(elsewhere)
    (elsewhere / "x.txt").write_text("changed\n")
    again = checkout(str(repo), None, tmp_path / "again", tmp_path / "cache")
    assert again.tree == source.tree  # what the link points at is no part of the code


def test_the_tree_digest_counts_links_by_their_text(tmp_path):
    """A link (to a file or a folder) counts as its target's text, never what it points at."""
    a, b = tmp_path / "a", tmp_path / "b"
    for folder, content in ((a, "one\n"), (b, "two\n")):
        (folder / "real").mkdir(parents=True)
        (folder / "real" / "f").write_text(content)
    for folder in (a, b):
        (folder / "tree").mkdir()
        (folder / "tree" / "link").symlink_to("../real")
    assert tree_digest(a / "tree") == tree_digest(b / "tree")
    (b / "tree" / "link").unlink()
    (b / "tree" / "link").symlink_to("elsewhere")
    assert tree_digest(a / "tree") != tree_digest(b / "tree")


def test_every_failure_while_checking_out_is_a_repository_error(repo, tmp_path):
    """A checkout that fails on the lab's side (here: no folder to write into) says so."""
    (tmp_path / "a-file").write_text("")
    with pytest.raises(RepositoryError, match="could not be checked out: Not a directory"):
        checkout(str(repo), None, tmp_path / "a-file" / "out", tmp_path / "cache")


def test_the_tree_digest_orders_paths_by_their_components(tmp_path):
    """Entries sort folder by folder ("a/b" before "a-c"), so digests stay as recorded."""
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "b").write_text("1\n")
    (tmp_path / "a-c").write_text("2\n")
    entries = [
        f"{name}\0-\0{hashlib.sha256(content).hexdigest()}\n"
        for name, content in (("a/b", b"1\n"), ("a-c", b"2\n"))
    ]
    expected = "sha256:" + hashlib.sha256("".join(entries).encode()).hexdigest()
    assert tree_digest(tmp_path) == expected


def test_a_commit_over_the_checkout_limit_is_refused_before_anything_is_written(tmp_path):
    """A commit whose files add up past max_checkout_bytes (here 8 paths sharing one
    512 KiB blob: 4 MiB checked out, a few KiB in git) is CheckoutTooLarge, naming the
    commit and the limit, and nothing is written; under the limit it checks out."""
    block = bytes(512 * 1024)
    repo = GitRepo.create(tmp_path / "copies", {f"copy-{n}.bin": block for n in range(8)})
    small = FetchPolicy(schemes=frozenset({"file"}), max_checkout_bytes=1024 * 1024)
    with pytest.raises(CheckoutTooLarge) as caught:
        checkout(str(repo.path), None, tmp_path / "out", tmp_path / "cache", small)
    message = str(caught.value)
    assert repo.rev()[:12] in message and "limit of 1.0 MiB" in message
    assert not (tmp_path / "out").exists()
    enough = FetchPolicy(schemes=frozenset({"file"}), max_checkout_bytes=4 * 1024 * 1024 + 1)
    checkout(str(repo.path), None, tmp_path / "out", tmp_path / "cache", enough)
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == [
        f"copy-{n}.bin" for n in range(8)
    ]


def test_the_expanded_size_counts_every_path_and_no_gitlink(tmp_path):
    """expanded_size adds each path's blob (a shared blob once per path, a link's target
    text), counts a submodule's gitlink as nothing, and stops early past its bound."""
    repo = GitRepo.create(tmp_path / "r", {"a": "12345", "b/c": "12345", "l": Link("a")})
    repo.add_submodule("lib", "../lib", repo.rev())
    git_dir, commit = repo.path / ".git", repo.rev()
    gitmodules = len(repo.git("show", f"{commit}:.gitmodules")) + 1  # and its last newline
    assert expanded_size(git_dir, commit) == Expanded(5 + 5 + 1 + gitmodules, 4)
    assert expanded_size(git_dir, commit, "b") == Expanded(5, 1)
    assert expanded_size(git_dir, commit, stop_past=Expanded(10**9, 0)).files == 1


def test_a_commit_of_too_many_files_is_refused_before_anything_is_written(tmp_path):
    """A tree naming one subtree 300 times, each naming one blob 300 times (90,000 files
    checked out, a few KiB in git), is refused past max_checkout_files without counting
    every path, and nothing is written."""
    repo = GitRepo.create(tmp_path / "bomb", {"lab.toml": ""})
    blob = repo.git("hash-object", "-w", "--stdin", input="x")
    inner = repo.git("mktree", input="".join(f"100644 blob {blob}\tf{n}\n" for n in range(300)))
    outer = repo.git("mktree", input="".join(f"040000 tree {inner}\td{n}\n" for n in range(300)))
    repo.git("read-tree", "--prefix=bomb/", outer)
    repo.git("commit", "-q", "-m", "90,000 files")
    policy = FetchPolicy(schemes=frozenset({"file"}), max_checkout_files=1000)
    with pytest.raises(
        CheckoutTooLarge,
        match=r"more than this lab's limit of 1,000 files \(at least 1,001 files\)",
    ):
        checkout(str(repo.path), None, tmp_path / "out", tmp_path / "cache", policy)
    assert not (tmp_path / "out").exists()


def test_an_export_streams_a_large_file_without_holding_it(tmp_path):
    """A 64 MiB file is checked out whole while the lab's own memory holds at most a few
    MiB of it (git archive is read as a stream, not into a buffer)."""
    size = 64 * 1024 * 1024
    repo = GitRepo.create(tmp_path / "big", {"lab.toml": "", "zeros.bin": bytes(size)})
    policy = FetchPolicy(schemes=frozenset({"file"}))
    fetched_once = checkout(str(repo.path), None, tmp_path / "warm", tmp_path / "cache", policy)
    tracemalloc.start()
    try:
        source = checkout(str(repo.path), None, tmp_path / "out", tmp_path / "cache", policy)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert source.tree == fetched_once.tree
    assert (tmp_path / "out" / "zeros.bin").stat().st_size == size
    assert peak < 8 * 1024 * 1024, f"{peak / 1024 / 1024:.1f} MiB held while checking out"
