"""A ladder's ratings, held to the formula: the Bradley-Terry fit with its Gaussian prior is
the maximum SciPy finds; draws count half; a perfect record is finite; the bootstrap over
matches is seeded, and gives one lucky match no rating."""

from __future__ import annotations

import math
import random

import numpy as np
import pytest
from scipy.optimize import minimize

from repository.ladder import CENTRE, PRIOR_SD, Leg, Rating, fit, ladder


def penalised_negative_log_likelihood(legs: list[Leg]) -> tuple[list[str], np.ndarray]:
    """The ratings minimising, by SciPy, minus the log-likelihood of ``legs`` under
    P(a beats b) = 1 / (1 + 10 ** ((r_b - r_a) / 400)), a draw half a win and half a loss,
    plus r² / (2 · PRIOR_SD²) for every rating; shifted by CENTRE."""
    entries = sorted({leg.a for leg in legs} | {leg.b for leg in legs})
    index = {entry: k for k, entry in enumerate(entries)}
    a = np.array([index[leg.a] for leg in legs])
    b = np.array([index[leg.b] for leg in legs])
    y = np.array([leg.score for leg in legs])

    def objective(x: np.ndarray) -> tuple[float, np.ndarray]:
        r = x * PRIOR_SD  # SciPy searches x, of order 1, for its tolerances to mean points
        p = 1 / (1 + 10 ** ((r[b] - r[a]) / 400))
        value = -np.sum(y * np.log(p) + (1 - y) * np.log(1 - p)) + np.sum(r**2) / (2 * PRIOR_SD**2)
        # d/dr_a of y log p + (1 - y) log(1 - p) is (y - p) ln 10 / 400, minus that for r_b
        per_leg = (y - p) * math.log(10) / 400
        gradient = -np.bincount(a, per_leg, len(entries)) + np.bincount(b, per_leg, len(entries))
        return value, (gradient + r / PRIOR_SD**2) * PRIOR_SD

    found = minimize(objective, np.zeros(len(entries)), jac=True, method="BFGS", tol=1e-12)
    assert np.abs(found.jac).max() < 1e-8, found.message
    return entries, CENTRE + found.x * PRIOR_SD


def round_robin(strengths: dict[str, float], matches: int, legs: int, seed: int) -> list[Leg]:
    """``matches`` matches of ``legs`` legs between every two entries, each leg a draw one
    time in five and otherwise won as Bradley-Terry says of ``strengths`` (points)."""
    rng = random.Random(seed)
    entries = sorted(strengths)
    played = []
    for i, a in enumerate(entries):
        for b in entries[i + 1 :]:
            p = 1 / (1 + 10 ** ((strengths[b] - strengths[a]) / 400))
            for m in range(matches):
                for _ in range(legs):
                    score = 0.5 if rng.random() < 0.2 else float(rng.random() < p)
                    played.append(Leg(f"{a}-{b}-{m}", a, b, score))
    return played


def rating_of(rows: list[Rating], entry: str) -> Rating:
    (found,) = [r for r in rows if r.entry == entry]
    return found


def test_the_ratings_are_the_penalised_maximum_likelihood_scipy_finds() -> None:
    """On a ladder with draws, sides both ways and a pair that met nobody else, every rating
    is the minimum of the penalised negative log-likelihood, as SciPy finds it."""
    legs = round_robin({"a": 300, "b": 100, "c": 0, "d": -50, "e": -400}, 3, 2, seed=1)
    legs += [Leg("x1", "x", "y", 1.0), Leg("x1", "y", "x", 0.5), Leg("x2", "y", "x", 1.0)]
    legs += [Leg("x3", "x", "y", 1.0)]
    entries, expected = penalised_negative_log_likelihood(legs)
    got = fit(legs)
    rows = ladder(legs, resamples=20)
    for entry, rating in zip(entries, expected, strict=True):
        assert got[entry] == pytest.approx(rating, abs=1e-4)
        assert rating_of(rows, entry).rating == got[entry]


def test_every_group_that_never_met_another_averages_the_centre() -> None:
    """The prior centres the ratings: those of each group connected by legs average 1000."""
    legs = round_robin({"a": 200, "b": 0, "c": -100}, 2, 3, seed=2)
    legs += [Leg("p", "x", "y", 1.0), Leg("q", "x", "y", 1.0), Leg("r", "y", "x", 0.5)]
    ratings = fit(legs)
    assert np.mean([ratings[e] for e in "abc"]) == pytest.approx(CENTRE, abs=1e-6)
    assert np.mean([ratings[e] for e in "xy"]) == pytest.approx(CENTRE, abs=1e-6)
    assert ratings["x"] > CENTRE > ratings["y"]


def test_a_perfect_record_is_finite_and_hundreds_of_points_clear() -> None:
    """Ten wins of ten against one opponent put the pair hundreds of points apart, not
    infinitely many: the prior's doing, and it is weak (one win is half as many)."""
    ten = fit([Leg(f"m{k}", "mover", "forfeiter", 1.0) for k in range(10)])
    one = fit([Leg("m", "mover", "forfeiter", 1.0)])
    assert 500 < ten["mover"] - ten["forfeiter"] < 700  # 592
    assert 200 < one["mover"] - one["forfeiter"] < 400  # 291


def test_a_mover_that_won_every_leg_against_a_forfeiter_is_above_it_interval_and_all() -> None:
    """An entry that won every leg is above 1000 in every resample that has it and at 1000
    in the others, so its interval lies at or above 1000, above the forfeiter's rating;
    the forfeiter's, which lost every leg, at or below, under the mover's."""
    legs = round_robin({"a": 150, "b": 0, "c": -150}, 3, 2, seed=3)
    legs += [Leg(f"mf{k}", "mover", "forfeiter", 1.0) for k in range(10)]
    legs += [Leg(f"{e}f", e, "forfeiter", 1.0) for e in "abc"]  # it forfeits everything
    rows = ladder(legs)
    mover, forfeiter = rating_of(rows, "mover"), rating_of(rows, "forfeiter")
    assert (mover.wins, mover.losses, mover.draws, mover.matches) == (10, 0, 0, 10)
    assert (forfeiter.wins, forfeiter.losses, forfeiter.matches) == (0, 13, 13)
    assert mover.rating - forfeiter.rating > 300
    assert all(math.isfinite(end) for end in mover.interval + forfeiter.interval)
    assert mover.interval[0] >= CENTRE - 1e-9 and forfeiter.interval[1] <= CENTRE + 1e-9
    assert mover.interval[0] > forfeiter.rating and forfeiter.interval[1] < mover.rating
    assert mover.interval[0] <= mover.rating <= mover.interval[1]


def test_a_draw_counts_half_a_win_to_each() -> None:
    """Two teams that drew every leg are rated alike, and a win and a loss weigh as two
    draws; the rows count the legs as they were."""
    drawn = ladder([Leg(f"m{k}", "a", "b", 0.5) for k in range(6)], resamples=50)
    assert [r.rating for r in drawn] == pytest.approx([CENTRE, CENTRE], abs=1e-9)
    assert [(r.wins, r.losses, r.draws, r.matches) for r in drawn] == [(0, 0, 6, 6)] * 2
    split = fit([Leg("m", "a", "c", 1.0), Leg("m", "a", "c", 0.0), Leg("n", "a", "b", 1.0)])
    halves = fit([Leg("m", "a", "c", 0.5), Leg("m", "c", "a", 0.5), Leg("n", "a", "b", 1.0)])
    assert split == pytest.approx(halves, abs=1e-9)


def test_who_beats_whom_mostly_is_ranked_in_that_order() -> None:
    """A beats B mostly and B beats C mostly: A > B > C, best first."""
    legs = []
    for k in range(8):
        legs.append(Leg(f"ab{k}", "A", "B", 0.0 if k == 0 else 1.0))
        legs.append(Leg(f"bc{k}", "C", "B", 1.0 if k < 2 else 0.0))
    legs.append(Leg("ca", "C", "A", 0.5))
    assert [r.entry for r in ladder(legs)] == ["A", "B", "C"]


def test_the_intervals_are_seeded() -> None:
    """The same legs give the same intervals every time, in any order; another seed moves
    them a little and the ratings not at all."""
    legs = round_robin({"a": 200, "b": 100, "c": 0, "d": -200}, 4, 2, seed=4)
    first = ladder(legs)
    assert ladder(legs) == first
    assert ladder(random.Random(5).sample(legs, len(legs))) == first
    other = ladder(legs, seed=1)
    assert [r.rating for r in other] == [r.rating for r in first]
    assert [r.interval for r in other] != [r.interval for r in first]
    for mine, theirs in zip(first, other, strict=True):
        assert theirs.interval == pytest.approx(mine.interval, abs=40)


def test_one_lucky_match_gives_no_rating() -> None:
    """An entry that won its one match is at 1000 in every resample without it (a third of
    them), so its interval reaches down to 1000, and is wider than with ten matches of the
    same record, whose interval lies clear above 1000."""
    base = round_robin({"b": 100, "c": 0, "d": -50, "e": -100}, 10, 1, seed=6)
    once = rating_of(ladder([*base, Leg("n", "new", "b", 1.0), Leg("n", "b", "new", 0.0)]), "new")
    tenfold = ladder(base + [Leg(f"n{k}", "new", "b", s) for k in range(10) for s in (1.0, 1.0)])
    ten = rating_of(tenfold, "new")
    assert once.interval[0] == pytest.approx(CENTRE, abs=1e-9)
    assert once.rating > CENTRE
    assert ten.interval[0] > CENTRE
    assert once.interval[1] - once.interval[0] > ten.interval[1] - ten.interval[0]


def test_rows_are_best_first_then_by_entry_and_no_legs_make_no_rows() -> None:
    rows = ladder([Leg("m", "b", "a", 0.5), Leg("n", "c", "d", 1.0)], resamples=10)
    assert [r.entry for r in rows] == ["c", "a", "b", "d"]
    assert ladder([]) == [] and fit([]) == {}


@pytest.mark.parametrize("score", [0.7, 2.0, -1.0, math.nan])
def test_a_score_other_than_a_win_a_draw_or_a_loss_is_refused(score: float) -> None:
    with pytest.raises(ValueError, match=r"match 'm1': the score must be 1 \(a won\)"):
        Leg("m1", "a", "b", score)


def test_an_entry_playing_itself_or_a_bootstrap_without_resamples_is_refused() -> None:
    with pytest.raises(ValueError, match="'a' cannot play itself"):
        Leg("m1", "a", "a", 1.0)
    with pytest.raises(ValueError, match="at least one resample"):
        ladder([Leg("m1", "a", "b", 1.0)], resamples=0)
