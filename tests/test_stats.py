"""Ensemble statistics against hand-worked answers, scipy, and their degenerate cases."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy import stats as sps

import chipstack.geometry.stats as gs
from chipstack.core.errors import InputError
from chipstack.geometry.stats import (
    Comparison,
    Summary,
    compare,
    hedges_g,
    holm,
    permutation_p,
    summarize,
    welch,
)

# Student-t quantiles from tables, not from scipy, so a wrong quantile call fails.
T975_DF4 = 2.7764451051977987
T95_DF4 = 2.1318467863266495

SAMPLE_PAIRS = [
    ([0.61, 0.63, 0.58, 0.66, 0.60], [0.64, 0.69, 0.67, 0.71, 0.65, 0.70]),
    ([12.0, 15.5, 9.8, 14.1], [10.2, 10.9, 11.4, 10.0, 10.7, 11.1, 10.3, 10.8]),
    ([1.0, 2.0, 3.0, 4.0, 100.0], [2.0, 2.5, 3.0]),
]


# --- summarize -------------------------------------------------------------------------


def test_summarize_known_answer():
    s = summarize([1, 2, 3, 4, 5])
    assert s.n == 5
    assert s.mean == pytest.approx(3.0)
    assert s.sd == pytest.approx(math.sqrt(2.5))
    half = T975_DF4 * math.sqrt(2.5) / math.sqrt(5)
    assert s.ci_low == pytest.approx(3.0 - half)
    assert s.ci_high == pytest.approx(3.0 + half)
    assert half == pytest.approx(1.9632, abs=1e-4)


def test_summarize_other_level_uses_its_quantile():
    s = summarize(np.array([1.0, 2.0, 3.0, 4.0, 5.0]), level=0.90)
    half = T95_DF4 * math.sqrt(2.5) / math.sqrt(5)
    assert (s.ci_low, s.ci_high) == pytest.approx((3.0 - half, 3.0 + half))


def test_summarize_returns_plain_floats_and_is_frozen():
    s = summarize((2.0, 4.0))
    assert isinstance(s, Summary)
    assert type(s.n) is int
    for value in (s.mean, s.sd, s.ci_low, s.ci_high):
        assert type(value) is float
    with pytest.raises(dataclasses.FrozenInstanceError):
        s.mean = 0.0  # type: ignore[misc]


def test_summarize_single_value_has_undefined_spread():
    s = summarize([7.5])
    assert s.n == 1
    assert s.mean == 7.5
    assert math.isnan(s.sd) and math.isnan(s.ci_low) and math.isnan(s.ci_high)


def test_summarize_constant_sample_has_zero_width_interval():
    # 0.1 is inexact in binary: np.mean would give 0.10000000000000002 and a tiny sd.
    s = summarize([0.1, 0.1, 0.1])
    assert s.sd == 0.0
    assert s.mean == s.ci_low == s.ci_high == 0.1


@pytest.mark.parametrize(
    ("values", "fragment"),
    [
        ([], "empty"),
        ([1.0, float("nan"), 2.0], "NaN"),
        ([1.0, float("inf")], "infinite"),
        ([[1.0, 2.0], [3.0, 4.0]], "one-dimensional"),
        (3.0, "one-dimensional"),
        (["a", "b"], "real numbers"),
        ([1.0, None], "real numbers"),
        ([True, False], "real numbers"),
        ([1 + 2j, 3.0], "real numbers"),
    ],
)
def test_summarize_rejects_bad_values(values, fragment):
    with pytest.raises(InputError, match=rf"^values: .*{fragment}"):
        summarize(values)


@pytest.mark.parametrize("level", [0.0, 1.0, 95, -0.5, float("nan"), "0.95", True])
def test_summarize_rejects_bad_level(level):
    with pytest.raises(InputError, match=r"^level: "):
        summarize([1.0, 2.0], level=level)


# --- welch -----------------------------------------------------------------------------


@pytest.mark.parametrize(("a", "b"), SAMPLE_PAIRS)
def test_welch_agrees_with_scipy(a, b):
    expected = sps.ttest_ind(a, b, equal_var=False)
    t, p = welch(a, b)
    assert t == pytest.approx(expected.statistic, rel=1e-12)
    assert p == pytest.approx(expected.pvalue, rel=1e-9)
    assert type(t) is float and type(p) is float


def test_welch_hand_worked():
    # Equal variances 1, n = 3: se = sqrt(2/3), df = (2/3)^2 / (2 * (1/3)^2 / 2) = 4.
    t, p = welch([1, 2, 3], [4, 5, 6])
    assert t == pytest.approx(-3.0 / math.sqrt(2.0 / 3.0))
    assert p == pytest.approx(2.0 * sps.t.sf(3.0 / math.sqrt(2.0 / 3.0), 4))
    assert 0.02 < p < 0.022


# scipy warns about the constant sample's moments; the answer is still right.
@pytest.mark.filterwarnings("ignore:Precision loss occurred:RuntimeWarning")
def test_welch_one_constant_sample_is_ordinary():
    a, b = [5.0, 5.0, 5.0], [4.0, 6.0, 7.0, 5.5]
    expected = sps.ttest_ind(a, b, equal_var=False)
    assert welch(a, b) == pytest.approx((expected.statistic, expected.pvalue))


def test_welch_degenerate_cases():
    assert welch([0.1, 0.1, 0.1], [0.1, 0.1]) == (0.0, 1.0)
    assert welch([2.0, 2.0], [3.0, 3.0, 3.0]) == (-math.inf, 0.0)
    assert welch([3.0, 3.0, 3.0], [2.0, 2.0]) == (math.inf, 0.0)


@pytest.mark.parametrize(
    ("a", "b", "pattern"),
    [
        ([1.0], [1.0, 2.0], r"^a: needs at least 2"),
        ([1.0, 2.0], [3.0], r"^b: needs at least 2"),
        ([], [1.0, 2.0], r"^a: is empty"),
        ([1.0, 2.0], [float("nan"), 1.0], r"^b: contains NaN"),
    ],
)
def test_welch_rejects_bad_samples(a, b, pattern):
    with pytest.raises(InputError, match=pattern):
        welch(a, b)


# --- permutation_p ---------------------------------------------------------------------


def test_permutation_exact_tiny_case_by_hand():
    # Splits of {1,2,3,4} into a pair for a: |mean b - mean a| is 2 for {1,2} and {3,4},
    # 1 for {1,3} and {2,4}, 0 for {1,4} and {2,3}: 2 of the 6 reach the observed 2.
    assert permutation_p([1, 2], [3, 4]) == pytest.approx(2 / 6)


def test_permutation_exact_three_against_three():
    # Only {1,2,3} and {4,5,6} reach |difference| 3, out of C(6, 3) = 20 splits.
    assert permutation_p([1, 2, 3], [4, 5, 6]) == pytest.approx(2 / 20)
    assert permutation_p([4, 5, 6], [1, 2, 3]) == pytest.approx(2 / 20)


def test_permutation_counts_splits_tied_up_to_rounding():
    # |difference| is 0.3 for {0.1, 0.2} and its mirror {0.3, 0.6}, 0.2 or 0.1 for the
    # other 4 splits; in binary the mirror comes out below the observed 0.3 by rounding
    # and must still count.
    assert permutation_p([0.1, 0.2], [0.3, 0.6]) == pytest.approx(2 / 6)


def test_permutation_identical_samples_give_one():
    assert permutation_p([1.0, 2.0, 3.0], [1.0, 2.0, 3.0]) == 1.0
    assert permutation_p([4.0, 4.0], [4.0, 4.0, 4.0], n_resamples=3) == 1.0
    assert permutation_p([0.0, 0.0], [0.0, 0.0]) == 1.0


def test_permutation_monte_carlo_is_deterministic_and_close_to_exact():
    rng = np.random.default_rng(12)
    a = rng.normal(10.0, 1.0, 8)
    b = rng.normal(10.8, 1.0, 8)
    exact = permutation_p(a, b)  # C(16, 8) = 12870 <= 20000 splits
    mc = permutation_p(a, b, n_resamples=5000, seed=3)
    assert mc == permutation_p(a, b, n_resamples=5000, seed=3)
    assert mc != permutation_p(a, b, n_resamples=5000, seed=4)
    assert mc == pytest.approx(exact, abs=0.03)
    assert 0.02 < exact < 0.5  # not a boundary case, where agreement would be trivial


def test_permutation_monte_carlo_never_returns_zero():
    # Only 2 of C(30, 15) ~ 1.6e8 splits reach the observed difference: none is drawn.
    a = np.arange(15.0)
    b = np.arange(15.0) + 100.0
    assert permutation_p(a, b, n_resamples=999) == pytest.approx(1 / 1000)


def test_permutation_monte_carlo_spans_several_blocks():
    a = np.linspace(0.0, 1.0, 15)
    b = np.linspace(0.3, 1.3, 15)
    p = permutation_p(a, b, n_resamples=25_000, seed=1)
    assert p == permutation_p(a, b, n_resamples=25_000, seed=1)
    # The exact p, estimated from 400,000 random splits (measured once: 0.01652; Welch's
    # t gives 0.0157); 25,000 resamples have a standard error of sqrt(p (1 - p) / 25,000)
    # = 0.0008: held to 4 of them (seeds 1 to 5 gave 0.0157 to 0.0167).
    assert p == pytest.approx(0.01652, abs=4 * math.sqrt(0.01652 * (1 - 0.01652) / 25_000))


@pytest.mark.parametrize("n_resamples", [0, -5, 2.5, True, "100"])
def test_permutation_rejects_bad_n_resamples(n_resamples):
    with pytest.raises(InputError, match=r"^n_resamples: "):
        permutation_p([1.0, 2.0], [3.0, 4.0], n_resamples=n_resamples)


@pytest.mark.parametrize("seed", [-1, 0.5, None, "0"])
def test_permutation_rejects_bad_seed(seed):
    with pytest.raises(InputError, match=r"^seed: "):
        permutation_p([1.0, 2.0], [3.0, 4.0], seed=seed)


def test_permutation_rejects_empty_sample():
    with pytest.raises(InputError, match=r"^b: is empty"):
        permutation_p([1.0, 2.0], [])


# --- hedges_g --------------------------------------------------------------------------


def test_hedges_g_hand_worked_equal_sizes():
    # Pooled variance (2 * 1 + 2 * 1) / 4 = 1, d = 3, J = 1 - 3 / (4 * 6 - 9) = 0.8.
    assert hedges_g([1, 2, 3], [4, 5, 6]) == pytest.approx(2.4)
    assert hedges_g([4, 5, 6], [1, 2, 3]) == pytest.approx(-2.4)


def test_hedges_g_hand_worked_unequal_sizes():
    # a: mean 1, variance 2; b: mean 4, variance 1; pooled (1 * 2 + 2 * 1) / 3 = 4 / 3;
    # J = 1 - 3 / (4 * 5 - 9) = 8 / 11.
    assert hedges_g([0, 2], [3, 4, 5]) == pytest.approx(3.0 / math.sqrt(4.0 / 3.0) * 8.0 / 11.0)


def test_hedges_g_degenerate_cases():
    assert hedges_g([0.1, 0.1, 0.1], [0.1, 0.1]) == 0.0
    assert hedges_g([1.0, 1.0], [2.0, 2.0]) == math.inf
    assert hedges_g([2.0, 2.0], [1.0, 1.0]) == -math.inf


def test_hedges_g_needs_two_values_per_sample():
    with pytest.raises(InputError, match=r"^b: needs at least 2"):
        hedges_g([1.0, 2.0], [3.0])


# --- holm ------------------------------------------------------------------------------


def test_holm_hand_worked():
    # Sorted: 0.005 * 4 = 0.02, 0.01 * 3 = 0.03, 0.03 * 2 = 0.06, 0.04 * 1 = 0.04 -> 0.06
    # (monotone), returned in the input order.
    adjusted = holm([0.01, 0.04, 0.03, 0.005])
    assert isinstance(adjusted, np.ndarray)
    np.testing.assert_allclose(adjusted, [0.03, 0.06, 0.06, 0.02])


def test_holm_clips_to_one_and_handles_ties():
    np.testing.assert_allclose(holm([0.6, 0.7]), [1.0, 1.0])
    np.testing.assert_allclose(holm([0.4, 0.9, 0.02]), [0.8, 0.9, 0.06])
    np.testing.assert_allclose(holm([0.01, 0.01]), [0.02, 0.02])
    np.testing.assert_allclose(holm([0.3]), [0.3])


def test_holm_empty_family():
    adjusted = holm([])
    assert adjusted.shape == (0,)


@pytest.mark.parametrize("pvalues", [[0.1, 1.2], [-0.01, 0.5], [0.1, float("nan")], [[0.1]]])
def test_holm_rejects_bad_pvalues(pvalues):
    with pytest.raises(InputError, match=r"^pvalues: "):
        holm(pvalues)


# --- compare ---------------------------------------------------------------------------


def test_compare_matches_the_single_functions():
    a, b = SAMPLE_PAIRS[1]
    c = compare(a, b, seed=5)
    assert isinstance(c, Comparison)
    assert c.mean_a == pytest.approx(np.mean(a))
    assert c.mean_b == pytest.approx(np.mean(b))
    assert c.difference == pytest.approx(np.mean(b) - np.mean(a))
    assert c.hedges_g == hedges_g(a, b)
    assert c.p_welch == welch(a, b)[1]
    assert c.p_permutation == permutation_p(a, b, seed=5)
    for field in dataclasses.fields(c):
        assert type(getattr(c, field.name)) is float


def test_compare_interval_covers_a_constructed_difference():
    # Deviations mirror each other, so the sample difference is exactly the true 10;
    # se = sqrt(1/3 + 1/3) and df = 4 as in test_welch_hand_worked.
    c = compare([9.0, 10.0, 11.0], [19.0, 20.0, 21.0])
    half = T975_DF4 * math.sqrt(2.0 / 3.0)
    assert c.difference == pytest.approx(10.0)
    assert (c.ci_low, c.ci_high) == pytest.approx((10.0 - half, 10.0 + half))
    assert c.ci_low < 10.0 < c.ci_high


def test_compare_interval_has_nominal_coverage():
    # Unequal variances and sizes, where a pooled-variance interval would under-cover.
    rng = np.random.default_rng(2024)
    trials, covered = 400, 0
    for _ in range(trials):
        a = rng.normal(5.0, 0.5, 4)
        b = rng.normal(6.0, 3.0, 3)
        c = compare(a, b)
        covered += c.ci_low <= 1.0 <= c.ci_high
    assert 0.92 <= covered / trials <= 0.99


def test_compare_degenerate_interval_is_the_point():
    c = compare([2.0, 2.0], [3.5, 3.5, 3.5])
    assert c.difference == c.ci_low == c.ci_high == 1.5
    assert c.hedges_g == math.inf
    assert c.p_welch == 0.0


def test_compare_rejects_bad_input():
    with pytest.raises(InputError, match=r"^a: needs at least 2"):
        compare([1.0], [1.0, 2.0])
    with pytest.raises(InputError, match=r"^seed: "):
        compare([1.0, 2.0], [1.0, 2.0], seed=-3)


# --- the whole module ------------------------------------------------------------------


def test_no_function_modifies_its_inputs():
    a = np.array([3.0, 1.0, 2.0, 5.0, 4.0])
    b = np.array([6.5, 4.0, 5.0, 9.0])
    big_a = np.linspace(0.0, 1.0, 12)[::-1].copy()
    big_b = np.linspace(0.5, 1.5, 12)[::-1].copy()
    pvalues = np.array([0.04, 0.01, 0.03])
    arrays = (a, b, big_a, big_b, pvalues)
    before = [x.tobytes() for x in arrays]
    summarize(a)
    welch(a, b)
    permutation_p(a, b)  # exact
    permutation_p(big_a, big_b, n_resamples=500)  # Monte-Carlo
    hedges_g(a, b)
    holm(pvalues)
    compare(a, b)
    compare(big_a, big_b)
    assert [x.tobytes() for x in arrays] == before


def test_read_only_inputs_are_accepted():
    a = np.array([1.0, 2.0, 4.0])
    b = np.array([3.0, 5.0, 6.0, 8.0])
    a.flags.writeable = False
    b.flags.writeable = False
    # The same answers as from writeable copies (the call alone once only had to not raise).
    assert compare(a, b) == compare(a.copy(), b.copy())
    assert permutation_p(a, b, n_resamples=10) == permutation_p(a.copy(), b.copy(), 10)
    p = np.array([0.2, 0.01])
    p.flags.writeable = False
    np.testing.assert_array_equal(holm(p), holm(p.copy()))
    np.testing.assert_allclose(holm(p), [0.2, 0.02])


def test_public_surface_is_documented():
    assert sorted(gs.__all__) == [
        "Comparison",
        "Summary",
        "compare",
        "hedges_g",
        "holm",
        "permutation_p",
        "summarize",
        "welch",
    ]
    assert gs.__doc__
    for name in gs.__all__:
        assert getattr(gs, name).__doc__, name
