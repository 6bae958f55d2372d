"""The lab's own repositories, recorded under its public URL and fetched from where this
process reaches the lab (``FetchPolicy.hosted_at``): a worker's ``--server``, the lab's
own port."""

from __future__ import annotations

from pathlib import Path

import pytest

from labd.commands.worker import hosted
from scheduler.errors import SchemeNotAllowed
from scheduler.fetch import FetchPolicy, mirror_path, resolve
from tests.helpers.githttp import GitHttpServer, GitRepo

PUBLIC = "http://lab.invalid:8080/git"  # RFC 6761: resolves nowhere


def test_a_worker_takes_the_public_prefix_and_fetches_from_its_server():
    """The public prefix the lab's hello names and the worker's own are both the lab's;
    both are fetched from the worker's --server; a lab that names none leaves its own."""
    policy = hosted(FetchPolicy(), "http://lab:8080/", PUBLIC)
    assert policy.hosted == (f"{PUBLIC}/", "http://lab:8080/git/")
    assert policy.hosted_at == "http://lab:8080/git/"
    alone = hosted(FetchPolicy(), "http://lab:8080", None)
    assert (alone.hosted, alone.hosted_at) == (("http://lab:8080/git/",), "http://lab:8080/git/")
    same = hosted(FetchPolicy(), "http://lab:8080", "http://lab:8080/git")
    assert same.hosted == ("http://lab:8080/git/",)


@pytest.mark.integration
def test_a_public_url_that_leads_nowhere_is_fetched_from_the_workers_server(tmp_path: Path):
    """Under the default policy (no http, no private hosts) a repository under the public
    prefix is fetched from the worker's --server on loopback, recorded and mirrored under
    its public URL; a look-alike under the public prefix, and the server's own address
    outside the lab's prefixes, are refused as any http URL is."""
    served = tmp_path / "served"
    repo = GitRepo.create(served / "git" / "alice" / "pg1.git", {"lab.toml": "[controller]\n"})
    cache = tmp_path / "cache"
    with GitHttpServer(served) as server:
        policy = hosted(FetchPolicy(), server.url(""), PUBLIC)
        found = resolve(f"{PUBLIC}/alice/pg1.git", None, cache, policy)
        assert (found.commit, found.repository) == (repo.rev(), f"{PUBLIC}/alice/pg1.git")
        assert mirror_path(cache, f"{PUBLIC}/alice/pg1.git").is_dir()
        assert any(r.path.startswith("/git/alice/pg1.git/") for r in server.requests)
        for url in (
            f"{PUBLIC}/alice/../pg1.git",
            f"{PUBLIC}/alice/pg1.git?x=1",
            f"{PUBLIC.replace('/git', '')}/alice/pg1.git",
            server.url("alice/pg1.git"),
        ):
            with pytest.raises(SchemeNotAllowed, match="scheme 'http' is not allowed"):
                resolve(url, None, cache, policy)
