"""The ratings of a ladder: how strong each entry is, from the legs of the matches it played.

A match puts two entries (a controller at a commit; here an opaque string) on the pitch for
one leg or more, each with a result for the pair: A won (score 1), B won (0) or a draw
(0.5: half a win to each). Every entry gets a rating with its 95 % interval (``ladder``).

**The model** is Bradley-Terry on the Elo scale: entry i beats entry j with probability
1 / (1 + 10 ** ((r_j - r_i) / 400)), so 400 points are odds of 10 to 1. The ratings
maximise the likelihood of every leg's score, a draw counting as half a win and half a
loss (as Chatbot Arena counts ties), times the prior.

**The prior** makes every rating independently normal around 0 with a standard deviation
of ``PRIOR_SD`` = 400 points: an L2 penalty of r² / (2 · 400²) on each. Without one, a
perfect record has no maximum: the mover that won every leg against a forfeiter is
infinitely better, and so is a team that beat one other once. The prior is weak: near even
odds a leg tells (ln 10 / 400)² / 4 about a rating difference, so the prior's weight,
1 / 400², is that of 4 / (ln 10)² ≈ 0.75 of a leg; ten wins out of ten against one opponent
put the pair 590 points apart, one win 290. Each leg adds to one rating what it takes from
the other, so at the maximum the prior's pull sums to zero: the ratings of every group of
entries that played one another (connected by legs) average exactly 0, reported as
``CENTRE`` = 1000. Groups that never met are not comparable, and the prior says so by
putting each at 1000 on average. The fit is Newton's method on the log-posterior, concave
and, with the prior, strictly so for any legs, disconnected or not; its steps are halved
where a full one would overshoot, and it stops when a step moves no rating by 2e-8 points:
deterministic.

**The interval** is a percentile bootstrap over matches, as Chatbot Arena's is over battles:
``resamples`` times, draw as many matches as were played, with replacement, each bringing
every one of its legs (a match's legs share a pitch and a day, they are not independent);
refit; take the 2.5th and 97.5th percentiles of each entry's ratings. The generator is
seeded (``seed``), so the same legs always give the same intervals. An entry none of whose
matches a resample drew gets there what the model says of an entry without legs: the
prior's centre, 1000. (Leaving it out of that resample instead, as a fit of the resample's
own entries would, rates one lucky match high in every resample that has it.)

**No rating from one lucky match.** An entry with m of the M matches is left out of a
resample with probability (1 - m/M)^M, about e^-m: at least 1/4 for one match (M ≥ 2),
so the interval of an entry of one match reaches 1000 whatever its record, and it is not
called better or worse than the average; with two or three matches in a large ladder
neither (e^-3 ≈ 5 % > 2.5 %). An entry that won every leg it played is above 1000 in
every resample that has it, so its interval lies at or above 1000; one that lost every leg,
at or below. What the bootstrap cannot see is the spread within a match: one match of a
win and a loss against an average team stays near 1000 in every resample, and its interval
is narrow: it says the entry looks average, not how sure that is. Where every resample is
alike (a ladder of one match, or of two entries whose matches all ended the same), the
intervals have no width at all.

Only the fit needs numpy, and imports it when it runs.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import numpy as np
    from numpy.typing import NDArray

    Array = NDArray[np.float64]
    Indices = NDArray[np.intp]

PRIOR_SD = 400.0  # the prior's standard deviation of a rating, in Elo points
CENTRE = 1000.0  # the reported ratings' mean
RESAMPLES = 1000  # bootstrap resamples by default
LEVEL = 0.95  # every interval here is a 95 % one
SCORES = (0.0, 0.5, 1.0)  # b won, draw, a won

# The fit works in log-odds: r points are r · SCALE, and the prior's precision in those units
# is PRECISION (1 / ln(10)² for 400 points).
SCALE = math.log(10) / 400
PRECISION = 1 / (PRIOR_SD * SCALE) ** 2
TOLERANCE = 1e-10  # log-odds (2e-8 points): the largest last Newton step
MAX_STEPS = 100  # Newton steps; from 0 it takes about 8 (quadratic convergence)
HALVINGS = 30  # of a Newton step that would lower the log-posterior
CELLS = 1 << 22  # Hessian cells (8 bytes each) fitted at once: resamples go in chunks


@dataclass(frozen=True)
class Leg:
    """One leg of match ``match`` between entries ``a`` and ``b``: ``score`` is 1.0 when
    ``a`` won, 0.0 when ``b`` won, 0.5 for a draw."""

    match: str
    a: str
    b: str
    score: float

    def __post_init__(self) -> None:
        if self.a == self.b:
            raise ValueError(f"a leg of match {self.match!r}: {self.a!r} cannot play itself")
        if self.score not in SCORES:
            raise ValueError(
                f"a leg of match {self.match!r}: the score must be 1 (a won), 0 (b won) "
                f"or 0.5 (a draw), not {self.score!r}"
            )


@dataclass(frozen=True)
class Rating:
    """An entry's row of the ladder: its rating (mean ``CENTRE``) with the 95 % bootstrap
    interval, how many distinct matches it played, and its legs won, lost and drawn."""

    entry: str
    rating: float
    interval: tuple[float, float]
    matches: int
    wins: int
    losses: int
    draws: int


def ladder(legs: Sequence[Leg], *, resamples: int = RESAMPLES, seed: int = 0) -> list[Rating]:
    """Every entry of ``legs`` rated, with its interval from ``resamples`` bootstrap
    resamples of the matches drawn by a generator seeded with ``seed``; best first, ties by
    entry. No legs, no rows."""
    if resamples < 1:
        raise ValueError(f"the bootstrap needs at least one resample, not {resamples}")
    if not legs:
        return []
    import numpy as np  # noqa: PLC0415 (slow to load: only where a fit runs)

    games = _Games(legs)
    point = games.fit(np.ones((1, len(games.matches))))[0]
    low, high = games.bootstrap(resamples, seed)
    rows = []
    for k, entry in enumerate(games.entries):
        results = [leg.score if leg.a == entry else 1 - leg.score for leg in games.legs_of[entry]]
        rows.append(
            Rating(
                entry=entry,
                rating=float(point[k]),
                interval=(float(low[k]), float(high[k])),
                matches=len({leg.match for leg in games.legs_of[entry]}),
                wins=results.count(1.0),
                losses=results.count(0.0),
                draws=results.count(0.5),
            )
        )
    return sorted(rows, key=lambda row: (-row.rating, row.entry))


def fit(legs: Sequence[Leg]) -> dict[str, float]:
    """The rating of every entry of ``legs`` (``ladder``'s without the intervals)."""
    if not legs:
        return {}
    import numpy as np  # noqa: PLC0415 (slow to load: only where a fit runs)

    games = _Games(legs)
    point = games.fit(np.ones((1, len(games.matches))))[0]
    return {entry: float(point[k]) for k, entry in enumerate(games.entries)}


class _Games:
    """The legs, summed by pair of entries for the fit: an entry is an index into
    ``entries`` (sorted, so the input's order changes nothing), a pair (i, j) has i < j,
    and a *unit* is a pair's legs in one match (how many, and i's score), the piece a
    resample draws."""

    def __init__(self, legs: Sequence[Leg]) -> None:
        import numpy as np  # noqa: PLC0415

        self.legs_of: dict[str, list[Leg]] = {}
        for leg in legs:
            self.legs_of.setdefault(leg.a, []).append(leg)
            self.legs_of.setdefault(leg.b, []).append(leg)
        self.entries = sorted(self.legs_of)
        self.matches = sorted({leg.match for leg in legs})
        index = {entry: k for k, entry in enumerate(self.entries)}
        match_index = {match: k for k, match in enumerate(self.matches)}
        units: dict[tuple[int, int, int], list[float]] = {}  # (i, j, match) -> [legs, score]
        for leg in legs:
            i, j, score = index[leg.a], index[leg.b], leg.score
            if i > j:
                i, j, score = j, i, 1 - score
            unit = units.setdefault((i, j, match_index[leg.match]), [0.0, 0.0])
            unit[0] += 1
            unit[1] += score
        keys = sorted(units)  # by pair, so each pair's units are consecutive
        pairs = sorted({(i, j) for i, j, _ in keys})
        self.first: Indices = np.array([i for i, _ in pairs], dtype=np.intp)
        self.second: Indices = np.array([j for _, j in pairs], dtype=np.intp)
        self.unit_match: Indices = np.array([m for _, _, m in keys], dtype=np.intp)
        self.unit_legs: Array = np.array([units[key][0] for key in keys])
        self.unit_score: Array = np.array([units[key][1] for key in keys])
        starts = [u for u, key in enumerate(keys) if u == 0 or key[:2] != keys[u - 1][:2]]
        self.pair_start: Indices = np.array(starts, dtype=np.intp)

    def bootstrap(self, resamples: int, seed: int) -> tuple[Array, Array]:
        """Each entry's 2.5th and 97.5th percentile rating over ``resamples`` resamples of
        the matches, fitted in chunks of as many as ``CELLS`` allows."""
        import numpy as np  # noqa: PLC0415

        n, count = len(self.entries), len(self.matches)
        rng = np.random.default_rng(seed)
        chunk = max(1, CELLS // (n * n))
        ratings = []
        for start in range(0, resamples, chunk):
            size = min(chunk, resamples - start)
            picks = rng.integers(0, count, size=(size, count))
            # how often each resample drew each match: one bincount over all rows at once
            rows = np.arange(size)[:, None] * count
            drawn = np.bincount((rows + picks).ravel(), minlength=size * count)
            ratings.append(self.fit(drawn.reshape(size, count).astype(np.float64)))
        low, high = np.quantile(np.concatenate(ratings), [(1 - LEVEL) / 2, (1 + LEVEL) / 2], axis=0)
        return low, high

    def fit(self, drawn: Array) -> Array:
        """The ratings, in points around ``CENTRE``, of each row of ``drawn``: how many
        times each match counts (1 for the legs as played, a bootstrap's draws for a
        resample), shape (resamples, matches) -> (resamples, entries)."""
        import numpy as np  # noqa: PLC0415

        def pairs(per_unit: Array) -> Array:
            return np.add.reduceat(drawn[:, self.unit_match] * per_unit, self.pair_start, axis=1)

        played, won = pairs(self.unit_legs), pairs(self.unit_score)
        theta = np.zeros((len(drawn), len(self.entries)))
        value = self._log_posterior(theta, played, won)
        active = np.arange(len(drawn))  # the rows still moving: the others are left alone
        for _ in range(MAX_STEPS):
            if not active.size:
                return CENTRE + theta / SCALE
            at, games, wins = theta[active], played[active], won[active]
            step = self._newton_step(at, games, wins)
            scale = np.ones((len(active), 1))
            candidate = self._log_posterior(at + step, games, wins)
            for _ in range(HALVINGS):
                # near the maximum, rounding alone may "lower" it by this much: no overshoot
                worse = candidate < value[active] - 1e-12 * (1 + np.abs(value[active]))
                if not worse.any():
                    break
                scale[worse] /= 2
                moved = at[worse] + scale[worse] * step[worse]
                candidate[worse] = self._log_posterior(moved, games[worse], wins[worse])
            theta[active] = at + scale * step
            value[active] = candidate
            active = active[np.abs(scale * step).max(axis=1) >= TOLERANCE]
        raise RuntimeError(f"the ladder's fit did not converge in {MAX_STEPS} Newton steps")

    def _log_posterior(self, theta: Array, played: Array, won: Array) -> Array:
        """Each row's log-likelihood of its legs plus the prior's log-density (up to a
        constant), in log-odds; a draw is half a win and half a loss."""
        import numpy as np  # noqa: PLC0415

        gap = theta[:, self.first] - theta[:, self.second]
        # log P(i beats j) = -log(1 + e^-gap), computed without overflow
        likelihood = -(won * np.logaddexp(0, -gap) + (played - won) * np.logaddexp(0, gap))
        penalty = PRECISION / 2 * (theta * theta).sum(axis=1)
        result: Array = likelihood.sum(axis=1) - penalty
        return result

    def _newton_step(self, theta: Array, played: Array, won: Array) -> Array:
        """The Newton step of each row: the gradient of the log-posterior solved against
        minus its Hessian, ∑ played·p(1-p)·(e_i - e_j)(e_i - e_j)ᵀ + PRECISION·I over pairs,
        positive definite by the prior."""
        import numpy as np  # noqa: PLC0415

        size, n = theta.shape
        gap = theta[:, self.first] - theta[:, self.second]
        p = np.exp(-np.logaddexp(0, -gap))  # P(i beats j), without overflow
        residual = won - played * p  # d log-likelihood / d gap
        weight = played * p * (1 - p)

        def per_entry(per_pair: Array, entries: Indices) -> Array:
            flat = (np.arange(size)[:, None] * n + entries).ravel()
            sums = np.bincount(flat, weights=per_pair.ravel(), minlength=size * n)
            return np.asarray(sums, dtype=np.float64).reshape(size, n)  # float: weighted

        gradient = (
            per_entry(residual, self.first) - per_entry(residual, self.second) - PRECISION * theta
        )
        hessian = np.zeros((size, n, n))
        hessian[:, self.first, self.second] = -weight  # each pair once: no sums needed
        hessian[:, self.second, self.first] = -weight
        diagonal = per_entry(weight, self.first) + per_entry(weight, self.second) + PRECISION
        hessian[:, np.arange(n), np.arange(n)] = diagonal
        return np.asarray(np.linalg.solve(hessian, gradient[..., None])[..., 0], dtype=np.float64)
