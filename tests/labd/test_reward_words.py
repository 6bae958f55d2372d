"""The mean reward in words: the evaluation page's Python and its script say the same,
and say why there is no interval where there is none."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path
from typing import Any

import pytest

from labd.web.evaluations import elsewhere_words, reward_words
from repository.evaluation import Score

SCRIPT = Path(__file__).resolve().parents[2] / "labd" / "web" / "static" / "evaluation-words.js"
# the evaluation page's words (evaluation-words.js, a module with no page) in Node: its
# rewardWords applied to each score given on stdin
RUN = """
const fs = require("fs");
const { pathToFileURL } = require("url");
import(pathToFileURL(process.argv[1]).href).then(({ rewardWords }) => {
  const scores = JSON.parse(fs.readFileSync(0, "utf8"));
  process.stdout.write(JSON.stringify(scores.map((s) => rewardWords(s))));
});
"""


def scored(done: int | None, mean: float | None, interval: tuple[float, float] | None) -> Score:
    return Score(
        episodes=20,
        done=done,
        running=0,
        queued=0,
        successes=done,
        errors=0,
        success_rate=None,
        success_interval=None,
        mean_reward=mean,
        reward_interval=interval,
        verified=False,
        compute_seconds=None,
    )


SCORES = [
    scored(0, None, None),
    scored(1, 17.88, None),
    scored(2, 17.94, None),
    scored(5, 0.5, None),
    scored(20, 0.0, None),
    scored(None, 3.25, None),
    scored(20, 0.7, (0.4975, 0.8825)),
]


def test_no_interval_says_why() -> None:
    """One episode: the mean, and that one is too few for a 95 % interval (six are the
    fewest); twenty of one reward: no interval, and the two reasons there can be."""
    assert reward_words(SCORES[1]) == (
        "mean reward 17.88 (1 episode: too few for a 95 % interval, which takes 6)"
    )
    assert reward_words(SCORES[3]).endswith(
        "(5 episodes: too few for a 95 % interval, which takes 6)"
    )
    assert reward_words(SCORES[4]) == (
        "mean reward 0 (no 95 % interval: the rewards are all the same, or fewer than 6)"
    )
    assert reward_words(SCORES[6]) == "mean reward 0.7 (0.498 to 0.883, 95 % bootstrap)"


@pytest.mark.skipif(shutil.which("node") is None, reason="needs Node.js")
def test_the_pages_script_says_what_the_python_says() -> None:
    """rewardWords in static/evaluation-words.js, run in Node on the API's JSON of each score,
    gives the very words of labd.web.evaluations.reward_words."""
    payload: list[dict[str, Any]] = [s.model_dump(mode="json") for s in SCORES]
    done = subprocess.run(
        ["node", "-e", RUN, str(SCRIPT)],
        input=json.dumps(payload),
        capture_output=True,
        text=True,
        timeout=30,
        check=True,
    )
    assert json.loads(done.stdout) == [reward_words(s) for s in SCORES]


ELSEWHERE = """
const { pathToFileURL } = require("node:url");
import(pathToFileURL(process.argv[1]).href).then(({ elsewhereWords }) => {
  const cases = JSON.parse(require("node:fs").readFileSync(0, "utf8"));
  console.log(JSON.stringify(cases.map(([n, of]) => elsewhereWords(n, of))));
});
"""


def test_verified_elsewhere_is_said_alike_by_the_page_and_the_python() -> None:
    """'verified on another machine: N of M' where a cluster replayed, nothing otherwise,
    in the page's script as in labd.web.evaluations."""
    cases: list[tuple[int | None, int]] = [(18, 20), (0, 3), (None, 20)]
    done = subprocess.run(
        ["node", "-e", ELSEWHERE, str(SCRIPT)],
        input=json.dumps(cases),
        capture_output=True,
        text=True,
        timeout=30,
        check=True,
    )
    said = [elsewhere_words(n, of) for n, of in cases]
    assert json.loads(done.stdout) == said
    assert said == [
        "verified on another machine: 18 of 20",
        "verified on another machine: 0 of 3",
        "",
    ]
