"""The lab's hosted repositories (``labd.hosted``), against real git in ``tmp_path``."""

from __future__ import annotations

import re
import subprocess
import threading
from pathlib import Path

import pytest

from labd.errors import GitFailed, HostedError, NotHosted
from labd.hosted import HostedRepos, git_environment

WHEN = 1_700_000_000
FILES = {"lab.toml": b'[controller]\ncommand = ["node", "main.mjs"]\n', "main.mjs": b"run();\n"}


@pytest.fixture
def hosted(tmp_path: Path) -> HostedRepos:
    return HostedRepos(tmp_path / "git")


def git(repo: Path, *args: str) -> str:
    done = subprocess.run(
        ["git", "--git-dir", str(repo), *args],
        capture_output=True,
        text=True,
        check=True,
        env=git_environment(),
    )
    return done.stdout.strip()


def commit(
    hosted: HostedRepos, files: dict[str, bytes], message: str = "m", when: int = WHEN
) -> str:
    return hosted.commit("alice", "robot", files, message, author="alice", when=when)


def test_a_commit_makes_the_repository_and_its_files_read_back(hosted, tmp_path):
    """The first commit makes a bare repository at ROOT/USER/NAME.git, on main, whose
    files, author, committer and dates are what was given."""
    assert not (tmp_path / "git").exists()  # made with the first repository
    sha = commit(hosted, FILES, "first")
    repo = tmp_path / "git" / "alice" / "robot.git"
    assert hosted.path("alice", "robot") == repo
    assert git(repo, "rev-parse", "--is-bare-repository") == "true"
    assert hosted.head("alice", "robot") == sha == git(repo, "rev-parse", "refs/heads/main")
    assert hosted.read("alice", "robot") == FILES
    assert git(repo, "log", "-1", "--format=%an <%ae> %at|%cn <%ce> %ct|%B") == (
        f"alice <alice@users.labd> {WHEN}|alice <alice@users.labd> {WHEN}|first"
    )
    modes = {line.split()[0] for line in git(repo, "ls-tree", "-r", sha).splitlines()}
    assert modes == {"100644"}
    assert git(repo, "config", "http.receivepack") == "false"


def test_the_same_inputs_give_the_same_commit(tmp_path):
    """Two labs committing the same files, message, author and time make the same id."""
    one = HostedRepos(tmp_path / "one").commit("alice", "r", FILES, "m", author="alice", when=5)
    two = HostedRepos(tmp_path / "two").commit("alice", "r", FILES, "m", author="alice", when=5)
    other = HostedRepos(tmp_path / "three").commit("alice", "r", FILES, "m", author="alice", when=6)
    assert one == two != other


def test_a_second_commit_has_the_first_as_parent_and_an_old_one_still_reads(hosted):
    """A commit's parent is main before it; the files of an older commit read back."""
    first = commit(hosted, FILES)
    second = commit(hosted, {**FILES, "main.mjs": b"run(2);\n"}, when=WHEN + 1)
    repo = hosted.path("alice", "robot")
    assert git(repo, "rev-parse", f"{second}^") == first
    assert hosted.head("alice", "robot") == second
    assert hosted.read("alice", "robot", first) == FILES
    assert hosted.read("alice", "robot", first[:8]) == FILES
    assert hosted.read("alice", "robot")["main.mjs"] == b"run(2);\n"


def test_an_unchanged_tree_makes_no_commit(hosted):
    """Committing the head's files again (another message, a later time) returns the
    head, and main does not move."""
    first = commit(hosted, FILES)
    again = commit(hosted, dict(FILES), "another message", when=WHEN + 60)
    assert again == first == hosted.head("alice", "robot")
    assert git(hosted.path("alice", "robot"), "rev-list", "--count", "main") == "1"


def test_nested_paths_make_sub_trees(hosted):
    """Paths with folders become trees in git, and read back as the same paths; bytes
    are kept as given (no line-ending or encoding filter)."""
    files = {
        "lab.toml": b"x\r\n",
        "src/a.mjs": b"a",
        "src/lib/b.mjs": b"\x00\xffb",
        "src/lib/c d.mjs": b"",
        "z/\u00e9t\u00e9.txt": "\u00e9".encode(),
    }
    sha = commit(hosted, files)
    repo = hosted.path("alice", "robot")
    assert git(repo, "cat-file", "-t", f"{sha}:src/lib") == "tree"
    assert git(repo, "ls-tree", "--name-only", sha) == "lab.toml\nsrc\nz"
    assert hosted.read("alice", "robot") == files


@pytest.mark.parametrize(
    ("user", "name", "said"),
    [
        ("alice", "x y", "repository name 'x y': use letters, digits, '.', '_' and '-'"),
        ("alice", "..", "repository name '..': use letters"),
        ("alice", ".hidden", "repository name '.hidden': use letters"),
        ("alice", "a/b", "repository name 'a/b': use letters"),
        ("alice", "", "repository name '': use letters"),
        ("alice", "r" * 65, f"repository name '{'r' * 65}': use letters"),
        ("alice", "robot.git", "repository name 'robot.git': must not end in '.git'"),
        ("alice", "robot.GIT", "repository name 'robot.GIT': must not end in '.git'"),
        ("alice", "caf\u00e9", "repository name 'caf\u00e9': use letters"),
        ("../keys", "robot", "user name '../keys': use letters, digits"),
        ("al ice", "robot", "user name 'al ice': use letters"),
        ("", "robot", "user name '': use letters"),
    ],
)
def test_bad_names_are_refused_with_the_rule(hosted, tmp_path, user, name, said):
    """A user or repository name outside the rule is refused, saying the rule, before
    any file is made; ``path``, ``head``, ``read`` and ``commit`` all refuse it."""
    for attempt in (
        lambda: hosted.path(user, name),
        lambda: hosted.head(user, name),
        lambda: hosted.read(user, name),
        lambda: hosted.commit(user, name, FILES, "m", author="alice", when=WHEN),
    ):
        with pytest.raises(HostedError, match="^" + re.escape(said)):
            attempt()
    assert not (tmp_path / "git").exists()


@pytest.mark.parametrize(
    ("path", "said"),
    [
        ("", "a file's path must not be empty"),
        ("/etc/passwd", "must be relative (no leading '/')"),
        ("../x", "must not have '.', '..' or empty parts"),
        ("a/../../x", "must not have '.', '..' or empty parts"),
        ("./a", "must not have '.', '..' or empty parts"),
        ("a//b", "must not have '.', '..' or empty parts"),
        ("a/", "must not have '.', '..' or empty parts"),
        (".git/config", "must not have a '.git' part"),
        ("src/.GIT/hooks/x", "must not have a '.git' part"),
        ("a\nb", "must not hold control characters"),
    ],
)
def test_bad_paths_are_refused(hosted, path, said):
    """A file's path that is empty, absolute, climbs, or names .git is refused with what
    is wrong, and nothing is committed."""
    with pytest.raises(HostedError) as refused:
        commit(hosted, {**FILES, path: b"x"})
    assert refused.value.what == f"path {path!r}"
    assert refused.value.reason == said
    assert hosted.head("alice", "robot") is None


def test_a_path_that_is_both_a_file_and_a_folder_is_refused(hosted):
    with pytest.raises(HostedError, match="path 'src': is a file and also the folder of 'src/a'"):
        commit(hosted, {"src": b"x", "src/a": b"y"})


def test_a_bad_author_time_or_message_is_refused(hosted):
    """The author is a user name (it makes the address); the time is whole seconds; the
    message has no NUL (git would refuse it)."""
    with pytest.raises(HostedError, match="user name 'a <b>'"):
        hosted.commit("alice", "robot", FILES, "m", author="a <b>", when=WHEN)
    with pytest.raises(HostedError, match="time -1: must be whole seconds"):
        hosted.commit("alice", "robot", FILES, "m", author="alice", when=-1)
    with pytest.raises(HostedError, match="commit message: must be text without NUL"):
        hosted.commit("alice", "robot", FILES, "a\0b", author="alice", when=WHEN)
    assert hosted.head("alice", "robot") is None


def test_two_threads_committing_at_once_lose_no_commit(hosted):
    """Two threads committing 20 times each to one repository: main's history holds all
    40 commits, one after the other."""
    start = threading.Barrier(2)
    made: dict[str, list[str]] = {"a": [], "b": []}

    def writer(who: str) -> None:
        start.wait()
        for i in range(20):
            files = {**FILES, f"{who}.txt": str(i).encode()}
            made[who].append(commit(hosted, files, f"{who} {i}", when=WHEN + i))

    threads = [threading.Thread(target=writer, args=(who,)) for who in made]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(60)
    history = git(hosted.path("alice", "robot"), "rev-list", "main").split()
    assert len(history) == 40
    assert set(history) == set(made["a"]) | set(made["b"])
    assert hosted.head("alice", "robot") in (made["a"][-1], made["b"][-1])


def test_names_lists_a_users_repositories(hosted):
    """``names`` lists the user's repositories, sorted; nobody's else, no lock files."""
    assert hosted.names("alice") == []
    for name in ("zeta", "alpha", "m.2"):
        hosted.commit("alice", name, FILES, "m", author="alice", when=WHEN)
    hosted.commit("bob", "other", FILES, "m", author="bob", when=WHEN)
    assert hosted.names("alice") == ["alpha", "m.2", "zeta"]
    assert hosted.names("bob") == ["other"]
    assert hosted.names("carol") == []


def test_unknown_repositories_and_commits(hosted):
    """No repository: head is None and read is NotHosted; a commit not in it, or not a
    commit id at all, is refused."""
    assert hosted.head("alice", "robot") is None
    with pytest.raises(NotHosted, match=r"^repository alice/robot: is not on this lab$"):
        hosted.read("alice", "robot")
    commit(hosted, FILES)
    missing = "0123456789abcdef0123456789abcdef01234567"
    with pytest.raises(NotHosted, match=f"^repository alice/robot: has no commit {missing}$"):
        hosted.read("alice", "robot", missing)
    with pytest.raises(HostedError, match="commit '--all': give 4 to 64 hexadecimal digits"):
        hosted.read("alice", "robot", "--all")
    blob = git(hosted.path("alice", "robot"), "rev-parse", "HEAD:main.mjs")
    with pytest.raises(NotHosted, match="has no commit"):
        hosted.read("alice", "robot", blob)  # an object, but no commit


def test_a_git_failure_says_gits_last_line_and_main_is_not_overwritten(hosted):
    """When git itself fails (here main names an object that is not there, so the lab
    sees no head, and update-ref's compare-and-swap finds main taken), the error names
    the command and the repository, carries git's own last line, and main is left."""
    commit(hosted, FILES)
    repo = hosted.path("alice", "robot")
    (repo / "refs" / "heads" / "main").write_text("1" * 40 + "\n")
    with pytest.raises(GitFailed) as failed:
        commit(hosted, {"other": b"x"})
    assert (failed.value.command, failed.value.repository) == ("update-ref", str(repo))
    assert "refs/heads/main" in failed.value.stderr
    assert str(failed.value) == f"git update-ref in {repo}: {failed.value.stderr}"
    assert (repo / "refs" / "heads" / "main").read_text() == "1" * 40 + "\n"
