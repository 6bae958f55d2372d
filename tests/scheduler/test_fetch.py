"""Fetching under the lab's policy: refs to commits, the mirror cache, limits, credentials."""

from __future__ import annotations

import base64
import fcntl
import os
import socket
import time
from dataclasses import replace
from pathlib import Path

import pytest

from scheduler.errors import (
    FetchTimeout,
    HostNotAllowed,
    RefNotFound,
    RepositoryError,
    SchemeNotAllowed,
    SubmoduleNotAllowed,
    TooLarge,
    Unreachable,
)
from scheduler.fetch import (
    Credential,
    FetchPolicy,
    Location,
    fetch_url,
    git_environment,
    mirror_path,
    resolve,
)
from scheduler.hosts import Pinned
from scheduler.source import checkout
from tests.helpers.githttp import GitHttpServer, GitRepo

TOKEN = "tok-3f9a2c71d0"
SCHEMES = frozenset({"https", "http", "ssh", "git", "file"})
# The git servers of these tests are on 127.0.0.1: private hosts allowed, but where the
# test is about them (test_hosts_that_are_not_public_are_refused_before_any_connection).
POLICY = FetchPolicy(schemes=SCHEMES, private_hosts=True)
MiB = 1024 * 1024


@pytest.fixture
def git_root(tmp_path) -> Path:
    return tmp_path / "served"


@pytest.fixture
def robot_repo(git_root) -> GitRepo:
    """A controller repository: v1 prints 1, main (one commit later) prints 2."""
    repo = GitRepo.create(git_root / "robot", {"lab.toml": "[controller]\n", "c.py": "print(1)\n"})
    repo.tag("v1")
    repo.commit({"c.py": "print(2)\n"}, "two")
    return repo


@pytest.fixture
def git_server(git_root):
    git_root.mkdir(parents=True, exist_ok=True)
    with GitHttpServer(git_root, users={"bot": TOKEN}, private={"secret"}) as running:
        yield running


@pytest.fixture
def lab_cache(tmp_path) -> Path:
    return tmp_path / "cache"


def mirrors(lab_cache: Path) -> list[str]:
    folder = lab_cache / "mirrors"
    return sorted(p.name for p in folder.iterdir()) if folder.exists() else []


def refs_of(repo: GitRepo) -> dict[str | None, str]:
    head = repo.rev()
    return {
        "main": head,
        "v1": repo.rev("v1"),
        head[:7]: head,
        repo.rev("v1"): repo.rev("v1"),
        None: head,
    }


def test_local_path_resolves_branch_tag_short_and_full_commit_and_head(robot_repo, lab_cache):
    """A local repository resolves every kind of ref to its full commit, and is public."""
    for ref, commit in refs_of(robot_repo).items():
        resolved = resolve(f"{robot_repo.path}/", ref, lab_cache, POLICY)
        assert resolved.commit == commit, ref
        assert resolved.repository == str(robot_repo.path.resolve())
        assert resolved.ref == ref and resolved.public
    assert mirrors(lab_cache) == [mirror_path(lab_cache, str(robot_repo.path.resolve())).name]


@pytest.mark.integration
def test_http_resolves_branch_tag_short_and_full_commit_and_head(robot_repo, git_server, lab_cache):
    """Over smart HTTP every kind of ref resolves too, and a public repository is public."""
    for ref, commit in refs_of(robot_repo).items():
        resolved = resolve(git_server.url("robot") + "/", ref, lab_cache, POLICY)
        assert (resolved.commit, resolved.public) == (commit, True), ref
        assert resolved.repository == git_server.url("robot")


def test_a_local_repository_runs_from_the_mirror_not_the_folder(robot_repo, lab_cache, tmp_path):
    """With the lab's policy the pinned commit is exported, even after the folder is gone."""
    resolved = resolve(str(robot_repo.path), "main", lab_cache, POLICY)
    (robot_repo.path / "c.py").write_text("print('edited')\n")
    robot_repo.path.rename(tmp_path / "moved")
    source = checkout(resolved.repository, resolved.commit, tmp_path / "out", lab_cache, POLICY)
    assert source.commit == resolved.commit and not source.dirty
    assert (tmp_path / "out" / "c.py").read_text() == "print(2)\n"


@pytest.mark.integration
def test_a_pinned_commit_still_runs_after_its_branch_is_force_moved(
    robot_repo, git_server, lab_cache, tmp_path
):
    """After a force push and a refetch, the old commit exports from the mirror, offline."""
    url = git_server.url("robot")
    old = resolve(url, "main", lab_cache, POLICY)
    robot_repo.git("reset", "-q", "--hard", "v1")
    robot_repo.commit({"c.py": "print(3)\n"}, "rewritten")
    new = resolve(url, "main", lab_cache, POLICY)
    assert new.commit == robot_repo.rev() != old.commit
    mirror = mirror_path(lab_cache, url)
    assert robot_repo.git("--git-dir", str(mirror), "rev-parse", "refs/heads/main") == new.commit
    git_server.close()  # nothing below may need the network
    source = checkout(url, old.commit, tmp_path / "old", lab_cache, POLICY)
    assert source.commit == old.commit
    assert (tmp_path / "old" / "c.py").read_text() == "print(2)\n"


@pytest.mark.integration
def test_unreachable_repositories_say_so_and_leave_nothing(git_server, lab_cache, tmp_path):
    """A missing repository, a refused connection and a missing folder are Unreachable;
    the network failures in the same words, git's own left out (they go to the log)."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    said = set()
    for url in (git_server.url("nothing-here"), f"http://127.0.0.1:{port}/nothing-here"):
        with pytest.raises(
            Unreachable, match=r"the repository could not be fetched; check the URL"
        ):
            resolve(url, None, lab_cache, POLICY)
        with pytest.raises(Unreachable) as caught:
            resolve(url, None, lab_cache, POLICY)
        assert caught.value.detail and caught.value.detail not in str(caught.value)
        said.add(str(caught.value).replace(url, "URL"))
    assert len(said) == 1, said
    with pytest.raises(Unreachable, match="no such folder"):
        resolve(str(tmp_path / "nowhere"), None, lab_cache, POLICY)
    assert mirrors(lab_cache) == []


def test_a_ref_that_does_not_exist_is_named(robot_repo, lab_cache):
    """A missing ref, or one that is an expression rather than a name, is RefNotFound."""
    pattern = r"'nope' is not a branch, tag or commit of .*robot"
    with pytest.raises(RefNotFound, match=pattern):
        resolve(str(robot_repo.path), "nope", lab_cache, POLICY)
    for ref in ("main~1", "-h", "main..v1", "HEAD@{1}", "0" * 40):
        with pytest.raises(RefNotFound, match="is not a branch, tag or commit"):
            resolve(str(robot_repo.path), ref, lab_cache, POLICY)


def test_an_empty_repository_has_no_head(tmp_path, lab_cache):
    """A repository without commits says so, rather than failing on HEAD."""
    empty = GitRepo.create(tmp_path / "empty")
    with pytest.raises(RefNotFound, match="has no commits"):
        resolve(str(empty.path), None, lab_cache, POLICY)


def test_schemes_outside_the_policy_are_refused_before_any_fetch(robot_repo, lab_cache):
    """Schemes the operator did not list, transports and URLs with secrets are refused."""
    with pytest.raises(
        SchemeNotAllowed,
        match=r"scheme 'ftp' is not allowed here; this lab accepts https, ssh, git URLs$",
    ):
        resolve("ftp://example.org/robot.git", None, lab_cache, FetchPolicy())
    with pytest.raises(SchemeNotAllowed, match="scheme 'http' is not allowed"):
        resolve("http://127.0.0.1:9/robot", None, lab_cache, FetchPolicy())
    with pytest.raises(SchemeNotAllowed, match="scheme 'ext' is not allowed"):
        resolve("ext::sh -c touch% /tmp/owned", None, lab_cache, POLICY)
    https_only = FetchPolicy(schemes=frozenset({"https"}))
    with pytest.raises(SchemeNotAllowed, match="local paths and file:// URLs are not allowed"):
        resolve(str(robot_repo.path), None, lab_cache, https_only)
    with pytest.raises(
        SchemeNotAllowed, match=r"file:// URLs are not allowed.*accepts https URLs$"
    ):
        resolve(robot_repo.url, None, lab_cache, https_only)
    with pytest.raises(SchemeNotAllowed, match="scheme 'ssh'"):
        resolve("git@example.org:team/robot.git", None, lab_cache, https_only)
    with pytest.raises(RepositoryError, match="user name or password") as caught:
        resolve(f"https://bot:{TOKEN}@example.org/robot.git", None, lab_cache, POLICY)
    assert TOKEN not in str(caught.value)
    assert not lab_cache.exists()


def test_local_paths_are_refused_by_default_in_the_same_words_whatever_is_there(
    robot_repo, lab_cache, tmp_path
):
    """By default a local path or file:// URL is refused before anything on the host is
    looked at: a repository, a plain folder and nothing at all get the same words, which
    name the flag that allows them."""
    missing = tmp_path / "nothing-here"
    words = set()
    for source in (
        str(robot_repo.path),
        robot_repo.url,
        str(tmp_path),
        str(missing),
        f"file://{missing}",
    ):
        with pytest.raises(SchemeNotAllowed) as caught:
            resolve(source, None, lab_cache, FetchPolicy())
        assert "--allow-local-repos" in str(caught.value)
        words.add(str(caught.value).replace(source, "PATH", 1))
    assert len(words) == 1, words
    assert not lab_cache.exists()


def test_the_labs_own_folders_are_never_a_repository(robot_repo, lab_cache, tmp_path):
    """With local paths allowed, a path in one of the policy's lab folders (a mirror of
    the cache, by any path that leads there) is refused, and other local paths are not."""
    policy = FetchPolicy(schemes=SCHEMES, lab_folders=(lab_cache,))
    fetched = resolve(str(robot_repo.path), None, lab_cache, policy)
    mirror = mirror_path(lab_cache, fetched.repository)
    (tmp_path / "door").symlink_to(mirror)
    for source in (
        str(mirror),
        f"file://{mirror}",
        str(tmp_path / "door"),
        f"{lab_cache}/../cache",
    ):
        with pytest.raises(RepositoryError, match="is in the lab's own folders"):
            resolve(source, None, lab_cache, policy)


def test_waiting_for_another_fetch_of_the_mirror_counts_against_the_deadline(robot_repo, lab_cache):
    """A fetch that finds its mirror held by another one (a silent server's) ends at its
    own deadline, however long the other holds it."""
    policy = FetchPolicy(schemes=SCHEMES, timeout=0.5)
    name = mirror_path(lab_cache, str(robot_repo.path.resolve())).name
    (lab_cache / "locks").mkdir(parents=True)
    with (lab_cache / "locks" / name).open("a") as held:
        fcntl.flock(held, fcntl.LOCK_EX)
        started = time.monotonic()
        with pytest.raises(FetchTimeout, match=r"limit of 0\.5 s"):
            resolve(str(robot_repo.path), None, lab_cache, policy)
        assert time.monotonic() - started < 5


@pytest.mark.integration
def test_a_submission_resolves_within_the_resolve_timeout(git_server, lab_cache):
    """``resolve`` (a submitter waits) stops at ``resolve_timeout`` when it is the shorter."""
    policy = FetchPolicy(schemes=SCHEMES, timeout=300, resolve_timeout=0.5, private_hosts=True)
    started = time.monotonic()
    with pytest.raises(FetchTimeout, match=r"limit of 0\.5 s"):
        resolve(git_server.stalled_url(), None, lab_cache, policy)
    assert time.monotonic() - started < 10


def big_repository(path: Path, megabytes: int) -> GitRepo:
    return GitRepo.create(path, {"lab.toml": "", "blob.bin": os.urandom(megabytes * MiB)})


def test_a_new_mirror_over_the_size_limit_leaves_nothing(tmp_path, lab_cache):
    """A repository over max_bytes is TooLarge and leaves no mirror, partial or whole."""
    repo = big_repository(tmp_path / "big", 8)
    policy = FetchPolicy(schemes=SCHEMES, max_bytes=1 * MiB)
    with pytest.raises(TooLarge, match=r"larger than this lab's limit of 1\.0 MiB"):
        resolve(str(repo.path), None, lab_cache, policy)
    assert mirrors(lab_cache) == []


def test_an_update_over_the_size_limit_keeps_the_old_mirror_usable(tmp_path, lab_cache):
    """When an update is too large, the commits fetched before still check out."""
    repo = GitRepo.create(tmp_path / "grows", {"lab.toml": "", "c.py": "print(1)\n"})
    policy = FetchPolicy(schemes=SCHEMES, max_bytes=1 * MiB)
    before = resolve(str(repo.path), None, lab_cache, policy)
    repo.commit({"blob.bin": os.urandom(8 * MiB)}, "big")
    with pytest.raises(TooLarge):
        resolve(str(repo.path), None, lab_cache, policy)
    mirror = mirror_path(lab_cache, before.repository)
    leftovers = [p.name for p in mirror.rglob("*") if p.name.startswith("tmp_")]
    assert leftovers == [] and list(mirror.rglob("*.lock")) == []
    source = checkout(before.repository, before.commit, tmp_path / "out", lab_cache, policy)
    assert (tmp_path / "out" / "c.py").read_text() == "print(1)\n"
    assert source.commit == before.commit


@pytest.mark.integration
def test_a_server_that_stalls_hits_the_time_limit(git_server, lab_cache):
    """A fetch that gets no answer is stopped at the time limit, and leaves nothing."""
    policy = FetchPolicy(schemes=SCHEMES, timeout=0.5, private_hosts=True)
    started = time.monotonic()
    with pytest.raises(FetchTimeout, match=r"took longer than this lab's limit of 0\.5 s"):
        resolve(git_server.stalled_url(), None, lab_cache, policy)
    assert time.monotonic() - started < 10
    assert mirrors(lab_cache) == []


def files_holding(folder: Path, secrets: list[bytes]) -> list[str]:
    found = []
    for path in folder.rglob("*"):
        if path.is_file() and any(secret in path.read_bytes() for secret in secrets):
            found.append(str(path))
    return found


@pytest.mark.integration
def test_a_private_repository_needs_the_lab_token_which_stays_out_of_everything(
    robot_repo, git_root, git_server, lab_cache, tmp_path
):
    """A token opens a private repository (not public); it is in no file, record or message."""
    secret = GitRepo.create(git_root / "secret", {"lab.toml": "", "c.py": "print('s')\n"})
    url = git_server.url("secret")
    with pytest.raises(Unreachable, match="private and this lab has no credential") as caught:
        resolve(url, None, lab_cache, POLICY)
    assert caught.value.auth
    wrong = FetchPolicy(
        schemes=SCHEMES,
        credentials=(Credential(git_server.url(""), token="not-" + TOKEN, username="bot"),),
        private_hosts=True,
    )
    with pytest.raises(Unreachable, match="no credential") as caught:
        resolve(url, None, lab_cache, wrong)
    assert "not-" + TOKEN not in str(caught.value)
    policy = FetchPolicy(
        schemes=SCHEMES,
        credentials=(Credential(git_server.url(""), token=TOKEN, username="bot"),),
        private_hosts=True,
    )
    resolved = resolve(url, "main", lab_cache, policy)
    assert resolved.commit == secret.rev() and not resolved.public
    source = checkout(url, resolved.commit, tmp_path / "out", lab_cache, policy)
    assert (tmp_path / "out" / "c.py").read_text() == "print('s')\n"
    basic = base64.b64encode(f"bot:{TOKEN}".encode())
    assert files_holding(tmp_path, [TOKEN.encode(), basic]) == []
    assert TOKEN not in repr(resolved) + repr(source) + repr(policy)
    assert any(r.user == "bot" for r in git_server.requests)
    # The token goes only where it is needed: a public repository is fetched without it.
    git_server.requests.clear()
    assert resolve(git_server.url("robot"), None, lab_cache, policy).public
    assert git_server.requests and not any(r.authorization for r in git_server.requests)


@pytest.mark.integration
def test_submodules_are_followed_only_from_the_allow_list(
    git_root, git_server, lab_cache, tmp_path
):
    """A submodule outside the allow-list is refused by name; an allowed one is exported."""
    lib = GitRepo.create(git_root / "lib", {"lib.py": "VALUE = 7\n"})
    robot = GitRepo.create(git_root / "parent", {"lab.toml": "", "c.py": "import lib\n"})
    robot.add_submodule("vendor/lib", "../lib", lib.rev())
    url = git_server.url("parent")
    with pytest.raises(
        SubmoduleNotAllowed,
        match=r"submodule 'vendor/lib' \(http://127.0.0.1:\d+/lib\) is not allowed here; this"
        " lab follows no submodules",
    ):
        resolve(url, None, lab_cache, POLICY)
    elsewhere = FetchPolicy(
        schemes=SCHEMES, submodules=("https://example.org/",), private_hosts=True
    )
    with pytest.raises(SubmoduleNotAllowed, match=r"only from https://example\.org/\. Copy"):
        resolve(url, None, lab_cache, elsewhere)
    allowed = FetchPolicy(schemes=SCHEMES, submodules=(git_server.url(""),), private_hosts=True)
    resolved = resolve(url, None, lab_cache, allowed)
    assert resolved.commit == robot.rev() and resolved.public
    lib.commit({"lib.py": "VALUE = 8\n"})  # the submodule's pin, not its branch, is run
    source = checkout(url, resolved.commit, tmp_path / "out", lab_cache, allowed)
    assert (tmp_path / "out" / "vendor" / "lib" / "lib.py").read_text() == "VALUE = 7\n"
    assert source.commit == resolved.commit


def test_no_hooks_run_while_fetching(tmp_path, lab_cache):
    """Hooks in the mirror (which git would run on ref updates) never run while fetching."""
    repo = GitRepo.create(tmp_path / "hooked", {"lab.toml": ""})
    resolved = resolve(str(repo.path), None, lab_cache, POLICY)
    mirror = mirror_path(lab_cache, resolved.repository)
    marker = tmp_path / "hook-ran"
    hook = mirror / "hooks" / "reference-transaction"
    hook.parent.mkdir(exist_ok=True)
    hook.write_text(f"#!/bin/sh\necho ran >> {marker}\n")
    hook.chmod(0o755)
    repo.git("--git-dir", str(mirror), "update-ref", "refs/probe", resolved.commit)
    assert marker.exists(), "the hook must be live, or this test proves nothing"
    marker.unlink()
    repo.commit({"c.py": "print(1)\n"})
    assert resolve(str(repo.path), None, lab_cache, POLICY).commit == repo.rev()
    assert not marker.exists()


def test_credentials_reach_only_their_urls_through_git_config_in_the_environment():
    """A token becomes an extraHeader for its prefix only; an ssh key, a strict ssh command."""
    policy = FetchPolicy(
        credentials=(
            Credential("https://git.example.org/team/", token=TOKEN),
            Credential("git@git.example.org:", ssh_key=Path("/keys/deploy key")),
        )
    )
    team = Location("https://git.example.org/team/robot", "https")
    env = git_environment(team, policy, policy.credential_for(team))
    config = {
        env[f"GIT_CONFIG_KEY_{i}"]: env[f"GIT_CONFIG_VALUE_{i}"]
        for i in range(int(env["GIT_CONFIG_COUNT"]))
    }
    basic = base64.b64encode(f"x-access-token:{TOKEN}".encode()).decode()
    header = config["http.https://git.example.org/team/robot.extraHeader"]
    assert header == f"Authorization: Basic {basic}"
    assert config["protocol.allow"] == "never" and config["core.hooksPath"] == "/dev/null"
    assert env["GIT_CONFIG_GLOBAL"] == "/dev/null" and env["GIT_TERMINAL_PROMPT"] == "0"
    other = Location("https://git.example.org/others/robot", "https")
    assert policy.credential_for(other) is None
    ssh = Location("git@git.example.org:team/robot.git", "ssh")
    command = git_environment(ssh, policy, policy.credential_for(ssh))["GIT_SSH_COMMAND"]
    assert "-i '/keys/deploy key'" in command
    assert "IdentitiesOnly=yes" in command and "BatchMode=yes" in command
    assert TOKEN not in repr(policy) and TOKEN not in str(git_environment(other, policy, None))


def test_the_labs_own_repositories_are_fetched_over_http_and_nothing_else_is(
    git_root, git_server, lab_cache
):
    """Under an https-only policy, a URL under the lab's hosted prefix of the form
    USER/NAME.git is fetched over http; its look-alikes (another path, a '..', another
    host, a query) are refused as any http URL is."""
    hosted = GitRepo.create(git_root / "alice" / "maze.git", {"lab.toml": "[controller]\n"})
    prefix = git_server.url("")
    policy = FetchPolicy(schemes=frozenset({"https"}), hosted=(prefix,))
    found = resolve(f"{prefix}alice/maze.git", None, lab_cache, policy)
    assert found.commit == hosted.rev()
    env = git_environment(Location(f"{prefix}alice/maze.git", "http"), policy, None)
    allowed = {env[f"GIT_CONFIG_KEY_{i}"] for i in range(int(env["GIT_CONFIG_COUNT"]))}
    assert "protocol.http.allow" in allowed
    other = git_environment(Location(f"{prefix}robot", "http"), policy, None)
    assert "protocol.http.allow" not in {
        other[f"GIT_CONFIG_KEY_{i}"] for i in range(int(other["GIT_CONFIG_COUNT"]))
    }
    for url in (
        f"{prefix}robot",
        f"{prefix}alice/../robot.git",
        f"{prefix}alice/maze.git?x=1",
        f"{prefix}alice/sub/maze.git",
        prefix.replace("127.0.0.1", "localhost") + "alice/maze.git",
    ):
        with pytest.raises(SchemeNotAllowed, match="scheme 'http' is not allowed"):
            resolve(url, None, lab_cache, policy)


@pytest.mark.integration
def test_hosts_that_are_not_public_are_refused_before_any_connection(
    robot_repo, git_server, lab_cache
):
    """By default a repository on a loopback host, by address or by a name that resolves
    to one, is refused naming the flag that allows it, and git never connects; the lab's
    own repositories (above) are the exception."""
    policy = FetchPolicy(schemes=SCHEMES)
    port = git_server.port
    for url, said in (
        (git_server.url("robot"), "is a loopback address"),
        (f"http://localhost:{port}/robot", "resolves to a loopback address"),
        (f"http://127.1:{port}/robot", "is a loopback address"),
        (f"http://[::ffff:127.0.0.1]:{port}/robot", "is a loopback address"),
        (f"git://127.0.0.1:{port}/robot", "is a loopback address"),
        (f"ssh://git@127.0.0.1:{port}/robot", "is a loopback address"),
        ("git@127.0.0.1:robot", "is a loopback address"),
        ("https://10.1.2.3/robot.git", "is a private address"),
        ("https://169.254.169.254/robot.git", "is a link-local address"),
    ):
        with pytest.raises(HostNotAllowed, match=said) as caught:
            resolve(url, None, lab_cache, policy)
        assert "--allow-private-hosts" in str(caught.value)
    assert git_server.requests == [] and mirrors(lab_cache) == []
    assert resolve(
        git_server.url("robot"), None, lab_cache, replace(policy, private_hosts=True)
    ).public


def config_of(env: dict[str, str]) -> dict[str, str]:
    return {
        env[f"GIT_CONFIG_KEY_{i}"]: env[f"GIT_CONFIG_VALUE_{i}"]
        for i in range(int(env["GIT_CONFIG_COUNT"]))
    }


def test_git_connects_to_the_address_that_was_checked_and_follows_no_redirect():
    """A checked name is pinned to its address for curl and ssh, and a git:// URL is
    given with the address; no redirect is followed; nothing is pinned for an address."""
    policy = FetchPolicy()
    https = Location("https://git.example.org/team/robot.git", "https")
    pinned = Pinned("git.example.org", 443, ("198.51.100.7",), name=True)
    config = config_of(git_environment(https, policy, None, pinned))
    assert config["http.curloptResolve"] == "git.example.org:443:198.51.100.7"
    assert config["http.followRedirects"] == "false"
    six = Pinned("git.example.org", 8443, ("2001:db8::7",), name=True)
    config = config_of(git_environment(https, policy, None, six))
    assert config["http.curloptResolve"] == "git.example.org:8443:[2001:db8::7]"
    ssh = Location("ssh://git@git.example.org:2222/team/robot.git", "ssh")
    env = git_environment(
        ssh, policy, None, Pinned("git.example.org", 2222, ("198.51.100.7",), True)
    )
    assert (
        "-o HostName=198.51.100.7 -o 'HostKeyAlias=[git.example.org]:2222'"
        in (env["GIT_SSH_COMMAND"])
    )
    daemon = Location("git://git.example.org:9419/robot.git", "git")
    assert fetch_url(daemon, Pinned("git.example.org", 9419, ("198.51.100.7",), True)) == (
        "git://198.51.100.7:9419/robot.git"
    )
    assert fetch_url(https, pinned) == https.url  # curl is told instead: TLS names the host
    literal = Pinned("198.51.100.7", 443, ("198.51.100.7",), name=False)
    config = config_of(git_environment(https, policy, None, literal))
    assert "http.curloptResolve" not in config and config["http.followRedirects"] == "false"
    assert "http.followRedirects" not in config_of(git_environment(https, policy, None))


@pytest.mark.integration
def test_git_fetches_from_the_pinned_address_not_from_its_own_lookup(
    robot_repo, git_server, lab_cache, monkeypatch
):
    """Git connects where the check looked, whatever the system's resolver says when
    git asks: a name no resolver knows is fetched from its pinned address, and a name
    that resolved to a public address for the check but resolves to loopback for git (a
    DNS rebinding) never reaches the loopback server."""
    policy = FetchPolicy(schemes=SCHEMES, timeout=5)
    pinned = Pinned("robot.invalid", git_server.port, ("127.0.0.1",), name=True)
    monkeypatch.setattr("scheduler.fetch.pin", lambda source, host, port: pinned)
    found = resolve(f"http://robot.invalid:{git_server.port}/robot", None, lab_cache, policy)
    assert found.commit == robot_repo.rev()
    monkeypatch.undo()
    git_server.requests.clear()
    monkeypatch.setattr("scheduler.hosts.resolve_name", lambda host, port: ["9.9.9.9"])
    with pytest.raises((Unreachable, FetchTimeout)):
        resolve(f"http://localhost:{git_server.port}/robot", None, lab_cache, policy)
    assert git_server.requests == []
