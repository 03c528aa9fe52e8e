"""Statistics shared by the diagnoses: energy distances between samples, their exact
permutation tests, proper per-drop scores, bootstrap weights and intervals.

Drops are compared as whole distributions. Each drop is a point of standardised
features (see ``diagnosis.observables.drop_features``) and two samples X (model, m
drops) and Y (experiment, n drops) of a condition are compared by their energy distance
(Szekely and Rizzo 2013),

    E = 2 E|X - Y| - E|X - X'| - E|Y - Y'|,

which is zero exactly when the two distributions are equal. Its U-statistic (pairs of
distinct drops only) is unbiased: it averages 0 when the model is right, whatever the
sample sizes, so it is the gap an effect may close. The energy score of one observed
drop y, ES(y) = E|X - y| - E|X - X'| / 2, is a proper score of the model's predictive
distribution (lower is better), and the mean score difference of two models on the same
drops is half the difference of their energy distances: per-drop scores give paired
comparisons of models on held-out data.

Each drop's features come in blocks (position, yaw, tilt) and the distance between two
drops is the sum of their blocks' distances, so E is the sum of the blocks' energy
distances and no noisy block drowns a clear one; detection takes the largest of the
blocks' and the total's standardised statistics (max-T).

Tests permute the labels (experiment or simulation) of the drops within each condition:
under "the model is right" the drops of a condition are exchangeable, so the permutation
null is exact for any sample sizes, and it does not hinge on one pool of simulations.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.stats import combine_pvalues, norm

from chipstack.geometry.stats import holm

__all__ = [
    "PERMUTATIONS",
    "bootstrap_p",
    "bootstrap_z_p",
    "combined_p",
    "energy_distance",
    "energy_statistics",
    "exceedance_p",
    "holm",
    "interval",
    "mean_cross",
    "max_t",
    "max_t_adjusted",
    "mean_within",
    "permutation_masks",
    "resample_weights",
    "standardise",
]

# Label permutations per test: the smallest attainable p-value is 1 / 1000.
PERMUTATIONS = 999


def resample_weights(n: int, resamples: int, rng: np.random.Generator) -> np.ndarray:
    """(1 + resamples, n) bootstrap counts: row 0 is the sample itself (all ones), each
    further row how often each of the n items is drawn in one resample of size n.

    A resample that draws one item n times (of n >= 2) is drawn again: it holds no pair of
    distinct items, so its within-sample mean distance (``mean_within``) is undefined. That
    happens to one resample in n**(n - 1) (1 in 625 of five drops, half of two); runs
    without one draw exactly what they drew before."""
    draws = rng.integers(0, n, size=(resamples, n))
    if n >= 2:
        single = (draws == draws[:, :1]).all(axis=1)
        while single.any():
            draws[single] = rng.integers(0, n, size=(int(single.sum()), n))
            single = (draws == draws[:, :1]).all(axis=1)
    counts = np.zeros((resamples, n))
    np.add.at(counts, (np.repeat(np.arange(resamples), n), draws.ravel()), 1.0)
    return np.vstack([np.ones((1, n)), counts])


def mean_cross(distances: np.ndarray, weights_a: np.ndarray, weights_b: np.ndarray):
    """Mean distance between the two samples of ``distances`` (n, m) under paired rows of
    bootstrap weights (R, n) and (R, m): (R,)."""
    n, m = distances.shape
    return ((weights_a @ distances) * weights_b).sum(axis=1) / (n * m)


def mean_within(distances: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Mean distance between distinct drops of one sample (U-statistic) under rows of
    bootstrap weights (R, n): (R,). A resample's copies of one drop are not a pair (their
    distance, 0, would bias the resamples' within-sample distance down). A sample or
    resample without a pair of distinct drops (fewer than two) is refused (ValueError):
    its mean is 0 / 0, never returned as NaN."""
    weights = np.asarray(weights, dtype=float)
    pairs = weights.sum(axis=1) ** 2 - (weights**2).sum(axis=1)
    if not (pairs > 0).all():
        rows = np.flatnonzero(~(pairs > 0))
        raise ValueError(
            f"mean_within: {len(rows)} of {len(pairs)} weight rows (first: row {rows[0]}) "
            "hold fewer than two distinct drops; there is no pair to average over"
        )
    return ((weights @ distances) * weights).sum(axis=1) / pairs


def energy_distance(cross: np.ndarray, within_a: np.ndarray, within_b: np.ndarray) -> np.ndarray:
    """The energy distance (U-statistic) from the mean cross distance and the two mean
    within-sample distances (each (R,), from ``mean_cross`` and ``mean_within``): about
    0 when the samples share their distribution, positive when they do not."""
    return 2.0 * cross - within_a - within_b


def permutation_masks(n: int, m: int, permutations: int, rng: np.random.Generator) -> np.ndarray:
    """(1 + permutations, n + m) bool: which of n + m pooled drops are labelled
    "experiment"; row 0 is the observed labelling (the first n)."""
    observed = np.zeros(n + m, dtype=bool)
    observed[:n] = True
    shuffled = np.array([rng.permutation(observed) for _ in range(permutations)])
    return np.vstack([observed, shuffled.reshape(permutations, n + m)])


def energy_statistics(distances: np.ndarray, masks: np.ndarray) -> np.ndarray:
    """The two-sample energy statistic n m / (n + m) * E (V-statistic) of the pooled
    drops' ``distances`` (N, N) under each labelling of ``masks`` (R, N): (R,)."""
    a = masks.astype(float)
    n = a[0].sum()
    m = len(distances) - n
    ad = a @ distances
    within_a = (ad * a).sum(axis=1)
    between = (ad * (1.0 - a)).sum(axis=1)
    within_b = distances.sum() - within_a - 2.0 * between
    e = 2.0 * between / (n * m) - within_a / n**2 - within_b / m**2
    return n * m / (n + m) * e


def standardise(statistics: np.ndarray) -> np.ndarray:
    """Statistics (S, R) computed under the same labellings (row 0 of each: the observed
    one), each standardised by its permutation null's mean and sd."""
    null = statistics[:, 1:]
    sd = np.maximum(null.std(axis=1, keepdims=True), 1e-300)
    return (statistics - null.mean(axis=1, keepdims=True)) / sd


def max_t(statistics: np.ndarray) -> np.ndarray:
    """The max-T statistic (R,) of several statistics (S, R): the largest standardised
    one. Its permutation p-value tests all S at once, the multiplicity paid for exactly."""
    return standardise(statistics).max(axis=0)


def max_t_adjusted(statistics: np.ndarray, step_down: bool = True) -> np.ndarray:
    """Westfall-Young max-T adjusted p-values (S,) of statistics (S, R) on a common scale
    (standardised; two-sided ones as absolute values), computed under the same
    labellings (column 0: the observed one, the others the permutation null).

    A statistic's adjusted p-value is the share of null labellings whose largest
    statistic of the family is at least as large as it, counted as in ``exceedance_p``
    ((1 + #) / (1 + null labellings), never 0). Rejecting where it is below alpha keeps
    the family-wise error at alpha however the statistics correlate: the null of the
    maximum is their joint one.
    Step-down (the default): the k-th largest is compared with the null maximum over
    itself and the smaller ones only, and the p-values are made monotone in the
    statistic (never below a larger statistic's); single-step compares every statistic
    with the maximum over the whole family. The largest statistic's adjusted p-value is
    the max-T test of the whole family either way."""
    statistics = np.asarray(statistics, dtype=float)
    observed, null = statistics[:, 0], statistics[:, 1:]
    order = np.argsort(-observed, kind="stable")
    if step_down:
        # Row j: the null maximum over the statistics ranked j and below.
        ceiling = np.maximum.accumulate(null[order][::-1], axis=0)[::-1]
    else:
        ceiling = np.broadcast_to(null.max(axis=0), null.shape)
    exceed = (ceiling >= observed[order][:, None]).sum(axis=1)
    ranked = np.maximum.accumulate((1.0 + exceed) / (1.0 + null.shape[1]))
    adjusted = np.empty_like(ranked)
    adjusted[order] = ranked
    return adjusted


def exceedance_p(null: np.ndarray, g: float) -> float:
    """The permutation-style p-value of ``g`` against the null sample: (1 + #{null >= g})
    / (1 + size), never 0."""
    return float((1 + (np.asarray(null) >= g).sum()) / (1 + len(null)))


def bootstrap_p(differences: np.ndarray) -> float:
    """One-sided bootstrap p-value of "the difference is positive" from its resamples:
    the share of resamples at or below 0, counted as (1 + k) / (1 + B), never 0."""
    d = np.asarray(differences, dtype=float)
    return float((1 + (d <= 0).sum()) / (1 + len(d)))


def bootstrap_z_p(difference: np.ndarray) -> float:
    """One-sided p-value of "the difference is positive" from the estimate and its
    resamples (1 + B,): the estimate over the resamples' sd, against the normal (unlike
    ``bootstrap_p``, not bounded below by 1 / (1 + B)). 1 when the resamples do not vary
    and the estimate is not positive, 0 when they do not vary and it is; 1 (no evidence
    either way) when either is not finite."""
    estimate, spread = float(difference[0]), float(np.std(difference[1:], ddof=1))
    if not (math.isfinite(estimate) and math.isfinite(spread)):
        return 1.0
    if spread == 0.0:
        return 1.0 if estimate <= 0.0 else 0.0
    return float(norm.sf(estimate / spread))


def interval(samples: np.ndarray, level: float = 0.95) -> tuple[float, float]:
    """Percentile interval of bootstrap samples.

    A resample whose value is undefined (NaN: a ratio with nothing to divide) is not
    dropped, which would leave an interval conditional on the ratio being defined: it
    counts as below the lower bound and above the upper one, so the interval can only
    widen, and is unbounded (-inf or inf) once more than the tail's share is undefined.
    """
    samples = np.asarray(samples, dtype=float)
    if samples.size == 0 or np.isnan(samples).all():
        return (float("nan"), float("nan"))
    tail = (1 - level) / 2 * 100
    undefined = np.isnan(samples)
    lo = np.percentile(np.where(undefined, -np.inf, samples), tail, method="lower")
    hi = np.percentile(np.where(undefined, np.inf, samples), 100 - tail, method="higher")
    return float(lo), float(hi)


def combined_p(p_values: list[float]) -> float:
    """Fisher's combination of independent p-values (one when there are none)."""
    if not p_values:
        return 1.0
    if len(p_values) == 1:
        return float(p_values[0])
    return float(combine_pvalues(p_values, method="fisher").pvalue)
