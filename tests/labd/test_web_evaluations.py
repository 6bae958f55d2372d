"""The evaluations' pages in process: an evaluation's score in words with its intervals
and its grid of episodes (held-out ones without links or seeds), two evaluations
compared (and the 422 of two that do not pair), rerunning from the page, and the task
page's leaderboard of evaluations. (tests/integration/test_evaluation_pages_browser.py
follows an evaluation in Chromium.)

Evaluations are submitted through the API to real git repositories; no workers run, so
episodes are claimed and filed the way a worker files them.
"""

# ruff: noqa: F811 (the API's fixtures, imported from test_api, are the tests' arguments)
from __future__ import annotations

from html.parser import HTMLParser

import httpx
import pytest
from markupsafe import escape

from labd.web import Site, create_app
from labd.web.evaluations import DASH, percent, rounded
from tests.fakes import verify_episodes
from tests.helpers.githttp import GitRepo
from tests.labd.test_api import auth, repo, service, token  # noqa: F401 (fixtures)
from tests.labd.test_api_evaluations import evaluate, file_episodes
from tests.labd.test_web import csrf_of


@pytest.fixture
async def web(service):
    """The API and the pages in process (pages are not in the OpenAPI document, so
    this client is not ``test_api``'s, which holds every answer to it)."""
    app = create_app(service, Site(), on_submit=lambda: None)
    transport = httpx.ASGITransport(app=app)
    async with httpx.AsyncClient(transport=transport, base_url="http://lab.test") as client:
        yield client


@pytest.fixture
def writer(service):
    """A token for a submitter whose daily limit takes several suites' episodes."""
    return service.index.add_user("erin", max_daily=500)


class Elements(HTMLParser):
    """Every element of a page with its attributes and text, in order."""

    def __init__(self, html: str) -> None:
        super().__init__()
        self.found: list[dict[str, str]] = []
        self.open: list[dict[str, str]] = []
        self.feed(html)

    def handle_starttag(self, tag, attrs):
        element = {"tag": tag, **{k: v or "" for k, v in attrs}, "text": ""}
        self.found.append(element)
        if tag not in ("input", "meta", "link", "br", "img"):
            self.open.append(element)

    def handle_endtag(self, tag):
        while self.open and self.open.pop()["tag"] != tag:
            pass

    def handle_data(self, data):
        for element in self.open:
            element["text"] += data

    def having(self, attribute: str) -> list[dict[str, str]]:
        return [e for e in self.found if attribute in e]

    def by_id(self, id_: str) -> dict[str, str]:
        found = [e for e in self.found if e.get("id") == id_]
        assert len(found) == 1, (id_, found)
        return found[0]


async def made(web, token, repo, **body):
    reply = await evaluate(web, token, repo, **body)
    assert reply.status_code == 201, reply.text
    return reply.json()


def trials(evaluation) -> list[int]:
    return [r["trial"] for r in evaluation["rows"]]


async def test_an_evaluation_page_says_its_score_and_links_every_episode(
    web, service, writer, repo
):
    """Part-way, the page says how many episodes have ended and succeeded so far (the
    rate is over the whole suite, so it waits for its end) and counts the running and
    queued; finished, it says "70 % (48 % to 85 %, 95 % Wilson) of 20 episodes",
    the mean reward with its interval, what is missing for it to be verified, and each
    episode is a cell coloured by outcome linking to its trial, its seed in its title."""
    e = await made(web, writer, repo)
    ids = trials(e)
    file_episodes(service, {t: ("success", 1.0) for t in ids[:3]})
    service.queue.check = None
    claim = service.queue.claim("w")
    assert claim is not None and claim.id == ids[3]
    running = Elements((await web.get(f"/evaluations/{e['id']}")).text)
    assert running.by_id("status")["text"] == "running"
    assert running.by_id("rate")["text"] == "3 of 20 episodes ended so far, 3 succeeded"
    counts = {c["data-count"]: c["text"] for c in running.having("data-count")}
    assert counts == {
        "success": "3",
        "fail": "0",
        "error": "0",
        "running": "1",
        "queued": "16",
        "cancelled": "0",
    }
    assert not running.by_id("following").get("hidden")
    service.queue.release_worker("w")  # back to the queue, filed below
    file_episodes(service, {t: ("success", 1.0) for t in ids[3:14]})
    file_episodes(service, {t: ("fail", 0.0) for t in ids[14:]})

    reply = await web.get(f"/evaluations/{e['id']}")
    assert reply.status_code == 200
    page = Elements(reply.text)
    score = (await web.get(f"/api/evaluations/{e['id']}")).json()
    assert page.by_id("status")["text"] == "finished"
    assert page.by_id("rate")["text"] == f"70 % (48 %{DASH}85 %, 95 % Wilson) of 20 episodes"
    low, high = score["reward_interval"]
    assert page.by_id("reward")["text"] == (
        f"mean reward 0.7 ({rounded(low, 3)} to {rounded(high, 3)}, 95 % bootstrap)"
    )
    assert page.by_id("verified")["text"] == (
        "not verified: 0 of 20 replayed identically; 20 not replayed yet"
    )
    assert page.by_id("partial").get("hidden") == ""  # present, and hidden
    assert page.by_id("following").get("hidden") == ""
    links = [a["href"] for a in page.having("href")]
    assert f"/commits/{e['commit']}" in links and "/tasks/icreate-maze" in links
    assert f"/compare?a={e['id']}" in links
    cells = page.having("data-episode")
    assert [c["href"] for c in cells] == [f"/trials/{t}" for t in ids]
    assert [c["class"] for c in cells] == ["cell success"] * 14 + ["cell fail"] * 6
    assert cells[15]["title"] == "episode 15, seed 15: fail, reward 0"
    assert "/static/evaluation.js" in reply.text
    episode = Elements((await web.get(f"/trials/{ids[15]}")).text).by_id("evaluation")
    assert episode["text"] == f"An episode of evaluation #{e['id']} (seed 15)."


async def test_a_held_out_evaluation_shows_its_aggregate_alone(web, service, writer, repo):
    """A held-out evaluation's page shows no episode (no cells, counts, links, seeds or
    compute time) and, while it runs, no progress; once it has ended, its score; its
    episodes appear when the suite version is retired."""
    e = await made(web, writer, repo, suite="test")
    whole = [r.trial for r in service.evaluations.get(e["id"], reveal=True).rows]
    file_episodes(service, {t: ("success", 1.0) for t in whole[:2]})
    seeds = [r.seed for r in service.evaluations.get(e["id"], reveal=True).rows]
    reply = await web.get(f"/evaluations/{e['id']}")
    page = Elements(reply.text)
    assert page.having("data-episode") == [] and page.having("data-count") == []
    assert page.by_id("rate")["text"] == (
        "held out: the score is shown once every episode has ended"
    )
    assert page.by_id("compute")["text"] == "held out"
    assert not any(f"/trials/{t}" in reply.text for t in whole)
    assert not any(str(s) in reply.text for s in seeds)
    assert "(held out)" in page.by_id("summary")["text"]
    rest = {t: ("success" if n < 30 else "fail", 1.0) for n, t in enumerate(whole) if n >= 2}
    file_episodes(service, rest)
    ended = Elements((await web.get(f"/evaluations/{e['id']}")).text)
    assert ended.by_id("rate")["text"].startswith("60 % (")
    assert ended.having("data-episode") == []

    service.evaluations.retire("icreate-maze", "test", 1)
    retired = Elements((await web.get(f"/evaluations/{e['id']}")).text)
    cells = retired.having("data-episode")
    assert cells[0]["href"] == f"/trials/{whole[0]}"
    assert cells[0]["title"] == f"episode 0, seed {seeds[0]}: success, reward 1"


async def test_two_evaluations_compared_and_two_that_do_not_pair(web, service, writer, repo):
    """The compare page says the API's sentence, the two-by-two table and the p-value; with
    only A it offers the same suite version's evaluations as B, with neither a form to
    type both; evaluations of two suites are the API's 422, with its words, as a page."""
    b = await made(web, writer, repo)
    d = await made(web, writer, repo, ref="v1")
    test = await made(web, writer, repo, suite="test")
    file_episodes(
        service, {t: ("success" if n < 18 else "fail", 1.0) for n, t in enumerate(trials(b))}
    )
    file_episodes(
        service, {t: ("success" if n < 8 else "fail", 0.5) for n, t in enumerate(trials(d))}
    )
    api = (await web.get(f"/api/evaluations/compare?a={b['id']}&b={d['id']}")).json()

    reply = await web.get(f"/compare?a={b['id']}&b={d['id']}")
    assert reply.status_code == 200
    page = Elements(reply.text)
    assert page.by_id("said")["text"] == api["said"]
    assert "A (" in api["said"] and "succeeds on 10 episodes where B" in api["said"]
    table = {k: page.by_id(k)["text"] for k in ("both", "only-a", "only-b", "neither")}
    assert table == {"both": "8", "only-a": "10", "only-b": "0", "neither": "2"}
    assert page.by_id("p-value")["text"].startswith("0.002 ")
    assert page.by_id("difference")["text"].startswith(  # every pair differs by 0.5
        "0.5 (no 95 % interval: the differences are all alike, or fewer than 6 pairs)"
    )
    assert (api["reward_difference"], api["reward_difference_interval"]) == (0.5, None)
    assert f"/evaluations/{b['id']}" in reply.text and f"/evaluations/{d['id']}" in reply.text

    choosing = Elements((await web.get(f"/compare?a={b['id']}")).text)
    offered = [o["value"] for o in choosing.found if o["tag"] == "option"]
    assert offered == [str(d["id"])]  # not A itself, nor the test suite's

    across = await web.get(f"/compare?a={b['id']}&b={test['id']}")
    said = (await web.get(f"/api/evaluations/compare?a={b['id']}&b={test['id']}")).json()
    assert across.status_code == 422 and across.headers["content-type"].startswith("text/html")
    assert "<h1>These two do not compare</h1>" in across.text
    assert str(escape(said["error"])) in across.text
    assert (await web.get("/compare?a=424242")).status_code == 404
    typed = Elements((await web.get("/compare")).text).by_id("choose")
    assert (typed["tag"], typed["action"]) == ("form", "/compare")


async def test_rerunning_from_the_page_needs_a_signed_in_person(web, service, writer, repo):
    """The rerun button of a signed-in person's page queues every episode again as a new
    evaluation and goes to its page, which says it is a rerun; anyone else is sent to
    sign in, and back to the evaluation after."""
    e = await made(web, writer, repo)
    file_episodes(service, {t: ("success", 1.0) for t in trials(e)})
    anonymous = await web.get(f"/evaluations/{e['id']}")
    assert 'id="rerun"' not in anonymous.text
    csrf = csrf_of(anonymous.text)
    refused = await web.post(f"/evaluations/{e['id']}/rerun", data={"csrf": csrf})
    assert refused.status_code == 303
    assert refused.headers["location"] == f"/session?then=/evaluations/{e['id']}"
    signed = await web.post("/session", data={"token": writer, "csrf": csrf})
    assert signed.status_code == 303
    own = await web.get(f"/evaluations/{e['id']}")
    assert 'id="rerun"' in own.text
    again = await web.post(f"/evaluations/{e['id']}/rerun", data={"csrf": csrf_of(own.text)})
    assert again.status_code == 303
    rerun_id = int(again.headers["location"].rsplit("/", 1)[1])
    rerun = service.evaluations.get(rerun_id)
    assert rerun.rerun_of == e["id"] and len(rerun.rows) == 20
    page = Elements((await web.get(f"/evaluations/{rerun_id}")).text)
    assert page.by_id("reproduced")["text"] == "pending: 0 of 20 episodes rerun so far"


async def test_the_task_page_ranks_evaluations_with_their_ties(web, service, writer, repo):
    """The task page ranks each commit's evaluation of the chosen suite (dev by default)
    by success rate, an overlapping interval marked "≈"; a single trial is not ranked;
    its suites are listed; a suite without evaluations says how to make one, and an
    unknown suite is the API's 404."""
    git = GitRepo(repo)
    first = await made(web, writer, repo, ref="v1")
    second = await made(web, writer, repo)
    git.commit({"c.py": "print('three')\n"}, "three")
    third = await made(web, writer, repo)
    assert len({first["commit"], second["commit"], third["commit"]}) == 3
    rates = {first["id"]: 8, second["id"]: 18, third["id"]: 17}
    for e in (first, second, third):
        wins = rates[e["id"]]
        file_episodes(
            service,
            {t: ("success" if n < wins else "fail", n / 20) for n, t in enumerate(trials(e))},
        )
    single = (
        await web.post(
            "/api/trials",
            json={"repository": str(repo), "task": "icreate-maze", "seed": 3},
            headers=auth(writer),
        )
    ).json()
    file_episodes(service, {single["id"]: ("success", 9.0)})

    reply = await web.get("/tasks/icreate-maze")
    assert reply.status_code == 200
    page = Elements(reply.text)
    rows = [r for r in page.found if r["tag"] == "tr" and "data-evaluation" in r]
    unranked = [r["text"] for r in rows]
    assert [int(r["data-evaluation"]) for r in rows] == [second["id"], third["id"], first["id"]]
    assert all("not ranked: its episodes' replays" in text for text in unranked)
    for e in (first, second, third):  # the lab's replays verify them: now they are ranked
        verify_episodes(service, trials(e))
    reply = await web.get("/tasks/icreate-maze")
    page = Elements(reply.text)
    rows = [r for r in page.found if r["tag"] == "tr" and "data-evaluation" in r]
    assert [int(r["data-evaluation"]) for r in rows] == [second["id"], third["id"], first["id"]]
    assert [r.get("class") for r in rows] == [None, None, None]
    ties = [e for e in page.found if e.get("class") == "tie"]
    assert [t["text"] for t in ties] == ["≈"] and "overlaps the row above" in ties[0]["title"]
    assert "≈" in rows[1]["text"] and "≈" not in rows[0]["text"] + rows[2]["text"]
    assert f'href="/evaluations/{second["id"]}"' in reply.text
    assert f"90 % (70 %{DASH}97 %)" in rows[0]["text"]
    assert f"{percent(8 / 20)}" in rows[2]["text"]
    assert f"/trials/{single['id']}" in reply.text  # among the recent trials, not ranked
    assert "public: seeds 0 to 19" in reply.text
    assert "held out: its seeds are the lab&#39;s secret" in reply.text

    empty = await web.get("/tasks/icreate-maze?suite=test")
    assert empty.status_code == 200
    assert "No evaluations of this suite yet: <code>labd evaluate REPO --suite test</code>" in (
        empty.text
    )
    unknown = await web.get("/tasks/icreate-maze?suite=nightly")
    assert unknown.status_code == 404
    assert "has no suite &#39;nightly&#39;; its suites: dev, test" in unknown.text
