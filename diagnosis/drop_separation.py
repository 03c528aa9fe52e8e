"""Which release condition would tell two tied models apart, and with how many drops.

Each model (an effect at the strength fitted on every condition) is simulated at every
candidate release (heights and yaws around the spec's, at its release tilt). The count
is the one the paired score test needs (the tie decision of methods 7 to 10): an effect
leaves the tie when the one-sided paired test on the held-out drops' energy scores,
Holm-adjusted over the tied effects, finds it worse than the best. The tie decision
(``EffectRanking._tie_set``) now also carries the simulations' noise, a floor that more
observed drops do not lower: for it the count is a lower bound. At each candidate release the
per-drop score difference between the two models is measured on drops of each model in
turn (the one taken as true scored against a leave-one-out sample of itself and against
the other's sample): its mean grows with the models' energy distance, its spread sets
the noise. The new condition's drops join the held-out drops the tie was judged on (their
score differences, ``held_out``, counted as they are), and the count is the least at
which the paired t statistic reaches z(1 - alpha / tied) + z(power) whichever of the two
models is true. A two-sample energy test (the previous rule) needs drops in proportion to
1 / distance, the paired score test in proportion to 1 / distance squared: for close
models it named counts an order of magnitude too small (4 to 40 drops where following
them with 50 resolved 2 of 18 ties in the calibration study).

What the count leaves out: the effects are refitted on the new data, and the simulations'
noise in the tie test; both favour the tie, so the count is a lower bound for the
fitted strengths.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from scipy.stats import norm

from chipstack.diagnosis.drop_simulations import DropSimulations
from chipstack.diagnosis.observables import FeatureMetric
from chipstack.diagnosis.statistics import energy_distance, mean_cross, mean_within

__all__ = [
    "CANDIDATE_HEIGHTS_MM",
    "CANDIDATE_YAWS_DEG",
    "MOST_DROPS",
    "drops_needed",
    "separating_releases",
]

CANDIDATE_HEIGHTS_MM = (150.0, 300.0, 600.0, 1000.0)
CANDIDATE_YAWS_DEG = (0.0, 45.0)
SEPARATION_DROPS = 60  # simulated drops per model and candidate release
POWER = 0.8
# Counts beyond this are not named ("no candidate release separates them"): a drop
# experiment of thousands of drops in one condition is not the next experiment.
MOST_DROPS = 5000


def separating_releases(
    sims: DropSimulations,
    strengths: dict[str, float],
    best: str,
    offsets: dict[str, float] | None = None,
    held_out: dict[str, np.ndarray] | None = None,
    alpha: float = 0.05,
) -> tuple[dict[str, dict], dict]:
    """For every model of ``strengths`` (effect -> fitted strength) other than ``best``:
    the candidate release that separates it from ``best`` with the fewest drops, by the
    paired score test (module docstring); and the one release that separates
    ``best`` from all of them with the fewest drops (the next experiment). Each model is
    released at the spec's tilt plus its fitted offset (``offsets``, deg); ``held_out``
    (effect -> per-drop held-out score of the effect minus the best's) are the drops the
    tie was judged on, which the new condition's join; ``alpha`` is the test's level,
    Bonferroni-adjusted over the effects compared with the best (as the tie test of
    methods 7 to 10 was, by Holm; a count that holds for the stricter test)."""
    spec = sims.x.conditions[0].protocol
    candidates = [
        replace(spec, height_mm=h, yaw_deg=y)
        for h in CANDIDATE_HEIGHTS_MM
        for y in CANDIDATE_YAWS_DEG
    ]
    index, calls = [], []
    for j, protocol in enumerate(candidates):
        for effect, strength in strengths.items():
            index.append((j, effect))
            calls.append(
                dict(
                    scenario=sims.x.scenario,
                    protocol=replace(
                        protocol, tilt_deg=protocol.tilt_deg + (offsets or {}).get(effect, 0.0)
                    ),
                    n=SEPARATION_DROPS,
                    strengths={effect: strength},
                    # Common random numbers across the models of one release.
                    seed=int(sims.seed) * 1000 + 500 + 10 * j + 3,
                    position_sd_mm=sims.x.position_sd_mm,
                    angle_sd_deg=sims.x.angle_sd_deg,
                )
            )
    sims.progress(f"simulating {len(calls)} x {SEPARATION_DROPS} drops at candidate releases")
    drops = dict(zip(index, sims.run_many(sims.simulate, calls), strict=True))
    others = [e for e in strengths if e != best]
    z = norm.ppf(1 - alpha / max(len(others), 1)) + norm.ppf(POWER)
    counts = np.full((len(others), len(candidates)), math.inf)
    distances = np.zeros_like(counts)
    for i, other in enumerate(others):
        before = np.zeros(0) if held_out is None else np.asarray(held_out[other], dtype=float)
        for j, protocol in enumerate(candidates):
            a = sims.release_features(drops[(j, best)], protocol.yaw_deg)
            b = sims.release_features(drops[(j, other)], protocol.yaw_deg)
            distances[i, j], counts[i, j] = drops_needed(sims.names, a, b, before, z, sims.grid_n)

    def release(j: int, needed: float, **extra) -> dict:
        return dict(
            height_mm=candidates[j].height_mm,
            yaw_deg=candidates[j].yaw_deg,
            tilt_deg=candidates[j].tilt_deg,
            drops_needed_per_condition=None if math.isinf(needed) else int(needed),
            power=POWER,
            **extra,
        )

    out = {}
    for i, other in enumerate(others):
        j = int(np.argmin(counts[i]))
        out[other] = release(j, counts[i, j], energy_distance=float(distances[i, j]))
    # One condition that tells the best from every tied effect: the release whose
    # hardest separation needs the fewest drops.
    hardest = counts.max(axis=0)
    j = int(np.argmin(hardest))
    return out, release(j, hardest[j], separates=others)


def drops_needed(
    names: list[str], a: np.ndarray, b: np.ndarray, before: np.ndarray, z: float, pool: int
) -> tuple[float, float]:
    """The energy distance (U-statistic, standardised features) between two models' drops
    ``a`` and ``b`` (raw features) at one release, and the drops a new condition there
    needs (inf beyond ``MOST_DROPS``) for the paired score test to reach ``z`` whichever
    model is true: on drops of the true model, each drop's energy score under the other
    model minus its score under the true one (a leave-one-out sample of itself), joined to
    ``before``, the held-out differences (the other effect minus the best) already judged
    on, signed for the model taken as true."""
    metric = FeatureMetric.of(np.vstack([a, b]), "yaw_spread" in names, "tilt_q50" in names)
    distances = metric.distances(metric.apply(np.vstack([a, b]))).sum(axis=0)
    n = len(a)
    one_a, one_b = np.ones((1, n)), np.ones((1, len(b)))
    aa, bb, ab = distances[:n, :n], distances[n:, n:], distances[:n, n:]
    distance = float(
        energy_distance(
            mean_cross(ab, one_a, one_b), mean_within(aa, one_a), mean_within(bb, one_b)
        )[0]
    )
    # True model a: the best (the held-out differences count as they are); true b: the
    # other effect (they count against it).
    needed = max(
        _least_drops(_score_differences(aa, bb, ab, pool), distance, before, z),
        _least_drops(_score_differences(bb, aa, ab.T, pool), distance, -before, z),
    )
    return distance, needed


def _score_differences(
    own: np.ndarray, other: np.ndarray, cross: np.ndarray, pool: int
) -> tuple[np.ndarray, np.ndarray]:
    """Per drop of the true model: its energy score under the other model minus under its
    own, the own model's sample the other drops of it (leave-one-out); and the variance a
    model sample of ``pool`` drops adds to each difference (the tie test scores against
    simulated pools of that size). ``own`` and ``other``: distances within each model's
    drops; ``cross``: true drops x other's."""
    k, m = len(own), len(other)
    other_within = other.sum() / (m * (m - 1))
    # Each drop's distances to the other k - 1 of its own (the diagonal is 0).
    row_sum = own.sum(axis=1)
    # Leaving drop i out of its own sample changes its pairs too: the mean over the rest.
    loo_within = (own.sum() - 2.0 * row_sum) / ((k - 1) * (k - 2))
    under_own = row_sum / (k - 1) - 0.5 * loo_within
    under_other = cross.mean(axis=1) - 0.5 * other_within
    own_spread = ((own**2).sum(axis=1) - row_sum**2 / (k - 1)) / (k - 2)
    cross_spread = cross.var(axis=1, ddof=1)
    differences = under_other - under_own
    # The differences' spread holds these samples' own noise (k - 1 and m drops), which
    # the tie test's pools replace by theirs (``pool`` drops each).
    sampled = own_spread / (k - 1) + cross_spread / m
    pool_variance = (own_spread + cross_spread) / pool - sampled
    return differences, pool_variance


def _least_drops(
    new: tuple[np.ndarray, np.ndarray], distance: float, before: np.ndarray, z: float
) -> float:
    """The least n (up to ``MOST_DROPS``) at which ``before`` joined by n drops like
    ``new`` (score differences and the variance their model pools add) gives a paired t
    statistic of at least ``z``; inf if none. The new drops' mean difference is half the
    models' energy distance (what a drop's score difference averages to), estimated on
    both models' drops rather than on the true model's alone."""
    differences, pool_variance = new
    var = max(float(differences.var(ddof=1) + pool_variance.mean()), 1e-12)
    mean = 0.5 * distance
    if mean <= 0:
        return math.inf
    n = np.arange(1, MOST_DROPS + 1)
    spread = float(((before - before.mean()) ** 2).sum()) if len(before) else 0.0
    t = (before.sum() + n * mean) / np.sqrt(spread + n * var)
    reached = np.flatnonzero(t >= z)
    return float(n[reached[0]]) if len(reached) else math.inf
