"""Statistics for comparing ensembles of repeated simulations.

Each sample is a 1-D sequence of finite real numbers, typically 2 to 30 repeated runs of
one scenario (a packing density, a height, a wall time ...). Everything returned is in the
same units as the values unless it is a p-value, a t statistic or an effect size, which
are dimensionless.

- :func:`summarize` -> :class:`Summary`: n, mean, sample sd and a Student-t confidence
  interval of the mean.
- :func:`welch`: Welch's unequal-variance t statistic and two-sided p-value.
- :func:`permutation_p`: two-sided permutation p-value of the difference of means, exact
  when the splits are few enough to enumerate, Monte-Carlo otherwise.
- :func:`hedges_g`: standardized mean difference with the small-sample correction.
- :func:`holm`: Holm-Bonferroni adjusted p-values for a family of comparisons.
- :func:`compare` -> :class:`Comparison`: all of the above for two samples at once.

Bad input (empty or too small samples, NaN, infinity, non-numbers, more than one
dimension, out-of-range parameters) raises :class:`core.errors.InputError` whose
message starts with the argument's name. No function modifies its inputs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from itertools import combinations
from numbers import Integral, Real

import numpy as np
from numpy.typing import ArrayLike
from scipy import stats as _sps

from chipstack.core.errors import InputError

__all__ = [
    "Comparison",
    "Summary",
    "compare",
    "hedges_g",
    "holm",
    "permutation_p",
    "summarize",
    "welch",
]

# Resamples drawn per block in the Monte-Carlo permutation test: bounds memory to
# _MC_BLOCK * (na + nb) floats however large n_resamples is.
_MC_BLOCK = 10_000


@dataclass(frozen=True)
class Summary:
    """One sample described: size, mean, sample sd and a confidence interval of the mean.

    ``mean``, ``sd``, ``ci_low`` and ``ci_high`` are in the same units as the values.
    With a single value the spread is unknown, so ``sd``, ``ci_low`` and ``ci_high`` are
    ``nan``.
    """

    n: int
    mean: float
    sd: float
    ci_low: float
    ci_high: float


@dataclass(frozen=True)
class Comparison:
    """Sample b against sample a.

    ``mean_a``, ``mean_b``, ``difference`` (mean_b - mean_a), ``ci_low`` and ``ci_high``
    (the Welch-Satterthwaite 95 % confidence interval of the difference) are in the same
    units as the values; ``hedges_g`` is dimensionless and positive when b is larger;
    ``p_welch`` and ``p_permutation`` are two-sided p-values.
    """

    mean_a: float
    mean_b: float
    difference: float
    ci_low: float
    ci_high: float
    hedges_g: float
    p_welch: float
    p_permutation: float


def _sample(values: ArrayLike, name: str, min_n: int) -> np.ndarray:
    """The values as a 1-D float array (possibly a view: callers must not write to it)."""
    try:
        raw = np.asarray(values)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name}: not a sequence of numbers ({exc})") from None
    # Booleans, strings, objects (None, ragged lists) and complex numbers are not
    # measurements; numpy would otherwise coerce some of them silently.
    if raw.dtype.kind not in "iuf":
        raise InputError(f"{name}: must be real numbers, got dtype {raw.dtype}")
    if raw.ndim != 1:
        raise InputError(f"{name}: must be one-dimensional, got shape {raw.shape}")
    if raw.size == 0 and min_n > 0:
        raise InputError(f"{name}: is empty")
    if raw.size < min_n:
        raise InputError(f"{name}: needs at least {min_n} values, got {raw.size}")
    x = np.asarray(raw, dtype=float)
    if np.isnan(x).any():
        raise InputError(f"{name}: contains NaN")
    if np.isinf(x).any():
        raise InputError(f"{name}: contains an infinite value")
    return x


def _mean_var(x: np.ndarray) -> tuple[float, float]:
    """Mean and ddof=1 variance, exact for a constant sample.

    np.mean of [0.1, 0.1, 0.1] is 0.10000000000000002, which would give a variance of
    ~1e-33 instead of 0 and turn the degenerate cases into huge finite statistics.
    """
    if (x == x[0]).all():
        return float(x[0]), 0.0
    var = float(np.var(x, ddof=1)) if x.size > 1 else math.nan
    return float(np.mean(x)), var


def _level(level: float) -> float:
    if isinstance(level, bool) or not isinstance(level, Real):
        raise InputError(f"level: must be a number strictly between 0 and 1, got {level!r}")
    if not 0.0 < float(level) < 1.0:
        raise InputError(f"level: must be strictly between 0 and 1, got {level!r}")
    return float(level)


def summarize(values: ArrayLike, level: float = 0.95) -> Summary:
    """Size, mean, sample standard deviation and confidence interval of the mean.

    mean = sum of the values / n; sd = sqrt(sum of squared deviations from the mean /
    (n - 1)); the two-sided confidence interval at ``level`` is mean -/+ t * sd / sqrt(n),
    t being the (1 + level) / 2 quantile of Student's t with n - 1 degrees of freedom.
    All but ``n`` are in the same units as the values. With n == 1 the sd and the interval
    are undefined and returned as ``nan``; a constant sample has sd 0 and an interval of
    zero width.

    Raises InputError if ``values`` is empty, contains NaN or infinity or is not a 1-D
    sequence of real numbers, or if ``level`` is not strictly between 0 and 1.
    """
    level = _level(level)
    x = _sample(values, "values", 1)
    n = x.size
    mean, var = _mean_var(x)
    if n == 1:
        return Summary(n=1, mean=mean, sd=math.nan, ci_low=math.nan, ci_high=math.nan)
    sd = math.sqrt(var)
    half = float(_sps.t.ppf((1.0 + level) / 2.0, n - 1)) * sd / math.sqrt(n)
    return Summary(n=n, mean=mean, sd=sd, ci_low=mean - half, ci_high=mean + half)


@dataclass(frozen=True)
class _WelchParts:
    mean_a: float
    mean_b: float
    se: float  # standard error of mean_b - mean_a, same units as the values
    df: float  # Welch-Satterthwaite degrees of freedom; nan when se == 0


def _welch_parts(a: np.ndarray, b: np.ndarray) -> _WelchParts:
    mean_a, var_a = _mean_var(a)
    mean_b, var_b = _mean_var(b)
    va, vb = var_a / a.size, var_b / b.size
    se2 = va + vb
    if se2 == 0.0:
        return _WelchParts(mean_a, mean_b, 0.0, math.nan)
    df = se2 * se2 / (va * va / (a.size - 1) + vb * vb / (b.size - 1))
    return _WelchParts(mean_a, mean_b, math.sqrt(se2), df)


def welch(a: ArrayLike, b: ArrayLike) -> tuple[float, float]:
    """Welch's unequal-variance t test: (t statistic, two-sided p-value).

    t = (mean(a) - mean(b)) / sqrt(var(a) / na + var(b) / nb) with ddof=1 variances, in
    the sign convention of scipy.stats.ttest_ind(a, b, equal_var=False) (so t < 0 when b
    is larger, unlike :func:`hedges_g` and :attr:`Comparison.difference`). The degrees
    of freedom are Welch-Satterthwaite's, (va + vb)^2 / (va^2 / (na - 1) + vb^2 / (nb - 1))
    with va = var(a) / na and vb = var(b) / nb; p = 2 * P(T_df > |t|). Both are
    dimensionless.

    Degenerate cases, where scipy returns nan: if both samples are constant and equal the
    result is (0.0, 1.0); if both are constant and different it is (+inf or -inf, 0.0),
    the sign being that of mean(a) - mean(b).

    Raises InputError unless both samples have at least 2 finite real values.
    """
    x = _sample(a, "a", 2)
    y = _sample(b, "b", 2)
    parts = _welch_parts(x, y)
    diff = parts.mean_a - parts.mean_b
    if parts.se == 0.0:
        if diff == 0.0:
            return 0.0, 1.0
        return math.copysign(math.inf, diff), 0.0
    t = diff / parts.se
    return float(t), float(2.0 * _sps.t.sf(abs(t), parts.df))


def _count_integer(value: object, name: str, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, Integral) or value < minimum:
        raise InputError(f"{name}: must be an integer >= {minimum}, got {value!r}")
    return int(value)


def permutation_p(a: ArrayLike, b: ArrayLike, n_resamples: int = 20000, seed: int = 0) -> float:
    """Two-sided permutation p-value of the difference of means (dimensionless).

    The statistic is |mean(b) - mean(a)|. The values of both samples are pooled and
    re-split into groups of na and nb. If the number of splits, C(na + nb, na), is at most
    ``n_resamples`` every split is enumerated and p is the fraction of them whose statistic
    is at least the observed one (the observed split included, so p >= 1 / C). Otherwise
    ``n_resamples`` random splits are drawn with numpy.random.default_rng(seed) and
    p = (count + 1) / (n_resamples + 1), count being how many reach the observed statistic;
    this estimator never returns 0 and is a valid p-value. The result is deterministic for
    a given seed. Statistics within 1e-10 * max|value| of the observed one count as
    reaching it, so that splits tied in exact arithmetic are not lost to rounding.

    Raises InputError if a sample is empty or has NaN, infinity or non-numbers, if
    ``n_resamples`` is not an integer >= 1 or ``seed`` not an integer >= 0.
    """
    x = _sample(a, "a", 1)
    y = _sample(b, "b", 1)
    n_resamples = _count_integer(n_resamples, "n_resamples", 1)
    seed = _count_integer(seed, "seed", 0)
    na, nb = x.size, y.size
    pooled = np.concatenate([x, y])
    total = float(pooled.sum())
    # Every split's statistic, the observed one included, comes from the sum of its a
    # group by the same formula; the tolerance absorbs what summation order still changes.
    observed = abs((total - float(x.sum())) / nb - float(x.sum()) / na)
    tol = 1e-10 * float(np.abs(pooled).max())
    threshold = observed - tol

    def reaching(sum_a: np.ndarray) -> int:
        stat = np.abs((total - sum_a) / nb - sum_a / na)
        return int(np.count_nonzero(stat >= threshold))

    n_splits = math.comb(na + nb, na)
    if n_splits <= n_resamples:
        index = np.fromiter(
            (i for split in combinations(range(na + nb), na) for i in split),
            dtype=np.intp,
            count=n_splits * na,
        ).reshape(n_splits, na)
        return reaching(pooled[index].sum(axis=1)) / n_splits

    rng = np.random.default_rng(seed)
    count = 0
    for start in range(0, n_resamples, _MC_BLOCK):
        rows = min(_MC_BLOCK, n_resamples - start)
        shuffled = rng.permuted(np.broadcast_to(pooled, (rows, na + nb)), axis=1)
        count += reaching(shuffled[:, :na].sum(axis=1))
    return (count + 1) / (n_resamples + 1)


def hedges_g(a: ArrayLike, b: ArrayLike) -> float:
    """Hedges' g: bias-corrected standardized mean difference of b from a (dimensionless).

    g = J * (mean(b) - mean(a)) / s_p, where the pooled sd is
    s_p = sqrt(((na - 1) * var(a) + (nb - 1) * var(b)) / (na + nb - 2)) with ddof=1
    variances, and J = 1 - 3 / (4 * (na + nb) - 9) corrects the upward bias of Cohen's d in
    small samples. If s_p is 0 (both samples constant) g is 0.0 when the means are equal
    and +inf or -inf, with the sign of mean(b) - mean(a), otherwise.

    Raises InputError unless both samples have at least 2 finite real values.
    """
    x = _sample(a, "a", 2)
    y = _sample(b, "b", 2)
    mean_a, var_a = _mean_var(x)
    mean_b, var_b = _mean_var(y)
    na, nb = x.size, y.size
    diff = mean_b - mean_a
    pooled_var = ((na - 1) * var_a + (nb - 1) * var_b) / (na + nb - 2)
    if pooled_var == 0.0:
        return 0.0 if diff == 0.0 else math.copysign(math.inf, diff)
    correction = 1.0 - 3.0 / (4.0 * (na + nb) - 9.0)
    return float(correction * diff / math.sqrt(pooled_var))


def holm(pvalues: ArrayLike) -> np.ndarray:
    """Holm-Bonferroni adjusted p-values, in the order given (dimensionless).

    With the m p-values sorted ascending, p_(1) <= ... <= p_(m), the adjusted value of
    p_(i) is max over j <= i of (m - j + 1) * p_(j), clipped to 1; rejecting the hypotheses
    whose adjusted p is <= alpha controls the family-wise error rate at alpha. The result
    is a new float array of the input's length; an empty input gives an empty array.

    Raises InputError if ``pvalues`` is not a 1-D sequence of numbers in [0, 1].
    """
    # No hypotheses, nothing to adjust: not an error, unlike an empty sample.
    p = _sample(pvalues, "pvalues", 0)
    if ((p < 0.0) | (p > 1.0)).any():
        raise InputError("pvalues: must lie in [0, 1]")
    m = p.size
    if m == 0:
        return np.zeros(0)
    order = np.argsort(p, kind="stable")
    scaled = (m - np.arange(m)) * p[order]
    adjusted = np.empty(m)
    adjusted[order] = np.minimum(np.maximum.accumulate(scaled), 1.0)
    return adjusted


def compare(a: ArrayLike, b: ArrayLike, seed: int = 0) -> Comparison:
    """Sample b against sample a: means, difference with its 95 % CI, effect size, p-values.

    difference = mean(b) - mean(a), in the same units as the values; its Welch-Satterthwaite
    95 % confidence interval is difference -/+ t * se with se = sqrt(var(a) / na +
    var(b) / nb) and t the 0.975 quantile of Student's t with the Welch-Satterthwaite
    degrees of freedom (see :func:`welch`); when both samples are constant se is 0 and the
    interval is the single point ``difference``. ``hedges_g`` is :func:`hedges_g` (a, b),
    ``p_welch`` the p-value of :func:`welch` (a, b) and ``p_permutation``
    :func:`permutation_p` (a, b, seed=seed) with its default number of resamples.

    Raises InputError unless both samples have at least 2 finite real values, or if
    ``seed`` is not an integer >= 0.
    """
    x = _sample(a, "a", 2)
    y = _sample(b, "b", 2)
    seed = _count_integer(seed, "seed", 0)
    parts = _welch_parts(x, y)
    difference = parts.mean_b - parts.mean_a
    if parts.se == 0.0:
        ci_low = ci_high = difference
    else:
        half = float(_sps.t.ppf(0.975, parts.df)) * parts.se
        ci_low, ci_high = difference - half, difference + half
    return Comparison(
        mean_a=parts.mean_a,
        mean_b=parts.mean_b,
        difference=difference,
        ci_low=ci_low,
        ci_high=ci_high,
        hedges_g=hedges_g(x, y),
        p_welch=welch(x, y)[1],
        p_permutation=permutation_p(x, y, seed=seed),
    )
