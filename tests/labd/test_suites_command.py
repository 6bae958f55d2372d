"""`labd suites`, the operator's: list the suites, read a held-out suite's seeds (the
lab's secret's, the same the lab queues), retire it, and be told what cannot be done."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from labd.sim import registry
from repository.evaluation import held_out_seeds
from repository.index import Index
from repository.reservations import load_secret

pytestmark = pytest.mark.integration  # the command, in processes of its own


def labd(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "labd", "suites", *args],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )


def test_the_operator_lists_reads_and_retires_suites(tmp_path):
    data = tmp_path / "data"
    data.mkdir()
    Index.open(f"sqlite:///{data / 'index.sqlite'}").close()
    where = ("--data", str(data), "--json")
    listed = json.loads(labd("list", *where).stdout)
    assert {(r["task"], r["suite"], r["held_out"], r["retired"]) for r in listed} == {
        (task, suite, held_out, False)
        for task in registry.names()
        for suite, held_out in (("dev", False), ("test", True))
    }  # every task, the lab's own and the dm_control pack's, has these two
    seeds = json.loads(labd("seeds", "icreate-maze", "test", *where).stdout)["seeds"]
    secret = load_secret(data / "keys" / "suites.secret")
    assert seeds == held_out_seeds(secret, "icreate-maze", "test", 1, 50)
    assert json.loads(labd("seeds", "icreate-maze", "dev", *where).stdout)["seeds"] == list(
        range(20)
    )
    retired = json.loads(labd("retire", "icreate-maze", "test", *where).stdout)
    assert retired == {"task": "icreate-maze", "suite": "test", "version": 1, "public": 0}
    listed = json.loads(labd("list", "icreate-maze", *where).stdout)
    assert [r["retired"] for r in listed] == [False, True]
    public = labd("retire", "icreate-maze", "dev", "--data", str(data))
    assert public.returncode == 2 and "is public: nothing to retire" in public.stderr
    unknown = labd("seeds", "icreate-maze", "nightly", "--data", str(data))
    assert (
        unknown.returncode == 2
        and "has no suite 'nightly'; its suites: dev, test" in unknown.stderr
    )
    nowhere = labd("list", "--data", str(tmp_path / "none"))
    assert nowhere.returncode == 2 and "no archive in" in nowhere.stderr
