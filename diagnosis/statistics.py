"""Statistics shared by the diagnoses: gap statistics, noise floors and tests.

The gap between an experiment and a simulation is measured, per condition, by

    G = mean over observables k of ((O_exp,k - O_sim,k) / s_k)^2,

with s_k the standard error of the difference (the experiment's, from a bootstrap,
combined with the simulation's). Under no gap G is about 1; its null distribution is
measured, not assumed, by comparing replicas drawn from an independent simulation with
the simulation (the noise floor). The excess ``G - E0[G]`` is the gap that an effect may
close.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "bootstrap_indices",
    "energy_test",
    "gap_statistic",
    "holm",
    "interval",
]


def bootstrap_indices(n: int, resamples: int, rng: np.random.Generator) -> np.ndarray:
    """(resamples, n) indices drawn with replacement."""
    return rng.integers(0, n, size=(resamples, n))


def gap_statistic(observed: np.ndarray, simulated: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """G of observables (..., K) against simulated (K,) with scales (K,); shape (...)."""
    z = (np.asarray(observed) - simulated) / scale
    return np.mean(z**2, axis=-1)


def holm(p_values: list[float]) -> list[float]:
    """Holm-Bonferroni adjusted p-values (same order)."""
    p = np.asarray(p_values, dtype=float)
    order = np.argsort(p)
    adjusted = np.empty_like(p)
    running = 0.0
    m = len(p)
    for rank, k in enumerate(order):
        running = max(running, min(1.0, (m - rank) * p[k]))
        adjusted[k] = running
    return adjusted.tolist()


def exceedance_p(null: np.ndarray, g: float) -> float:
    """The permutation-style p-value of ``g`` against the null sample: (1 + #{null >= g})
    / (1 + size), never 0."""
    return float((1 + (np.asarray(null) >= g).sum()) / (1 + len(null)))


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


def energy_test(
    a: np.ndarray, b: np.ndarray, permutations: int, rng: np.random.Generator
) -> tuple[float, float]:
    """Two-sample energy-distance test (Szekely & Rizzo) of point sets a (n, d) and
    b (m, d): the statistic and its permutation p-value."""
    pooled = np.vstack([a, b])
    n = len(a)
    distances = np.linalg.norm(pooled[:, None, :] - pooled[None, :, :], axis=-1)

    def statistic(first: np.ndarray) -> float:
        second = ~first
        k, m = first.sum(), second.sum()
        between = distances[np.ix_(first, second)].mean()
        within_a = distances[np.ix_(first, first)].sum() / (k * k)
        within_b = distances[np.ix_(second, second)].sum() / (m * m)
        return float(k * m / (k + m) * (2 * between - within_a - within_b))

    mask = np.zeros(len(pooled), dtype=bool)
    mask[:n] = True
    observed = statistic(mask)
    exceed = 0
    for _ in range(permutations):
        exceed += statistic(rng.permutation(mask)) >= observed
    return observed, (1 + exceed) / (1 + permutations)
