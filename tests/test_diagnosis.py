"""The sim-to-real diagnosis: effects, observables, statistics, specs and observation files,
``pipeline synth`` and ``pipeline diagnose`` end to end on data whose effect is known."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest
from conftest import SMALL_SCENARIO, drop_spec, run_cli
from scipy.spatial.distance import cdist

from chipstack.core.errors import InputError
from chipstack.core.schema import ChipSpec
from chipstack.diagnosis.observables import (
    FeatureMetric,
    drop_features,
    drop_observables,
    observable_names,
)
from chipstack.diagnosis.statistics import (
    energy_statistics,
    exceedance_p,
    max_t,
    mean_cross,
    mean_within,
    permutation_masks,
    resample_weights,
)
from chipstack.packing.effects import EFFECTS, FlightState, check_effects
from chipstack.packing.effects.base import AIR_DENSITY_G_MM3
from chipstack.packing.shapes import make_shape

NAMES = observable_names(True, True)


# -- observables and statistics ------------------------------------------------------------
def test_observables_of_a_known_scatter():
    # 8 drops on the diagonals at 10 mm and 8 on the axes at 20 mm.
    diag = np.radians([45, 135, 225, 315])
    axes = np.radians([0, 90, 180, 270])
    points = np.vstack(
        [
            10 * np.column_stack([np.cos(diag), np.sin(diag)]),
            10 * np.column_stack([np.cos(diag), np.sin(diag)]),
            20 * np.column_stack([np.cos(axes), np.sin(axes)]),
            20 * np.column_stack([np.cos(axes), np.sin(axes)]),
        ]
    )
    yaw = np.full(16, 7.0)
    tilt = np.arange(16, dtype=float)
    values = dict(zip(NAMES, drop_observables(points, yaw, tilt, 0.0, 4, NAMES), strict=True))
    assert values["r_q50"] == pytest.approx(15.0)
    assert values["r95"] == pytest.approx(20.0)
    assert values["mean_x"] == pytest.approx(0.0, abs=1e-12)
    assert values["aniso_c"] == pytest.approx(0.0, abs=1e-12)  # half diagonals, half axes
    assert values["yaw_spread"] == pytest.approx(0.0, abs=1e-12)  # every chip turned alike
    assert values["tilt_q50"] == pytest.approx(7.5)
    only_diagonals = drop_observables(points[:8], yaw[:8], tilt[:8], 0.0, 4, NAMES)
    assert dict(zip(NAMES, only_diagonals, strict=True))["aniso_c"] == pytest.approx(-1.0)
    # Turning the release by 45 deg turns the diagonals into the chip's sides.
    turned = drop_observables(points[:8], yaw[:8], tilt[:8], 45.0, 4, NAMES)
    assert dict(zip(NAMES, turned, strict=True))["aniso_c"] == pytest.approx(1.0)


def test_yaw_spread_of_uniform_yaw_is_one():
    yaw = np.linspace(0, 90, 400, endpoint=False)
    values = drop_observables(np.ones((400, 2)), yaw, np.zeros(400), 0.0, 4, NAMES)
    assert dict(zip(NAMES, values, strict=True))["yaw_spread"] == pytest.approx(1.0, abs=1e-9)


def _energy_p(a: np.ndarray, b: np.ndarray, rng, permutations: int = 199) -> float:
    masks = permutation_masks(len(a), len(b), permutations, rng)
    pooled = np.vstack([a, b])
    stats = energy_statistics(cdist(pooled, pooled), masks)
    return exceedance_p(stats[1:], stats[0])


def test_energy_test_separates_shifted_and_wider_samples_only():
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(60, 2)), rng.normal(size=(80, 2))
    assert _energy_p(a, b, rng) > 0.05
    assert _energy_p(a + [1.0, 0.0], b, rng) < 0.01
    assert _energy_p(3.0 * a, b, rng) < 0.01  # a scale change, as a bouncier chip makes


def test_permutation_null_is_exact_for_small_unequal_samples():
    """Under no difference the p-value is uniform whatever the sample sizes (here 12
    against 40 heavy-tailed drops): the false-alarm rate at 5 % is 5 % within the
    binomial spread of 400 trials (99.9 % band: 1.8 % to 9.0 %)."""
    rng = np.random.default_rng(1)
    p = np.array(
        [
            _energy_p(rng.standard_t(2, (12, 2)), rng.standard_t(2, (40, 2)), rng, 99)
            for _ in range(400)
        ]
    )
    assert 0.018 <= np.mean(p <= 0.05) <= 0.09
    assert 0.4 <= np.mean(p <= 0.5) <= 0.6


def test_energy_distance_u_statistic_and_bootstrap_pairs():
    """The U-statistic of the energy distance averages 0 when the samples share their
    distribution (unlike the V-statistic, biased up by the within-sample terms), and a
    resample's copies of one drop are not counted as a pair."""
    rng = np.random.default_rng(2)

    def energy_u(a, b):
        ones_a, ones_b = np.ones((1, len(a))), np.ones((1, len(b)))
        between = mean_cross(cdist(a, b), ones_a, ones_b)[0]
        return (
            2 * between - mean_within(cdist(a, a), ones_a)[0] - mean_within(cdist(b, b), ones_b)[0]
        )

    same = [energy_u(rng.normal(size=(10, 2)), rng.normal(size=(15, 2))) for _ in range(800)]
    assert abs(np.mean(same)) < 3 * np.std(same) / np.sqrt(len(same))
    shifted = [energy_u(rng.normal(size=(10, 2)) + 2, rng.normal(size=(15, 2))) for _ in range(50)]
    assert np.mean(shifted) > 1.0
    points = np.array([[0.0], [1.0], [3.0]])
    # Drop 0 twice and drop 2 once: the pairs are (0, 2) twice each way, distance 3.
    assert mean_within(cdist(points, points), np.array([[2.0, 0.0, 1.0]]))[0] == pytest.approx(3.0)
    weights = resample_weights(5, 30, rng)
    assert weights.shape == (31, 5) and (weights.sum(axis=1) == 5).all() and (weights[0] == 1).all()


def test_max_t_pays_for_several_statistics_at_once():
    rng = np.random.default_rng(3)
    null = rng.normal(size=(4, 2000))
    t = max_t(null)
    # The largest of 4 independent standard normals exceeds 1.645 far more often than 5 %.
    assert np.mean(t[1:] > 1.645) == pytest.approx(1 - 0.95**4, abs=0.03)
    shifted = null.copy()
    shifted[2, 0] = 10.0
    assert exceedance_p(max_t(shifted)[1:], max_t(shifted)[0]) < 0.002


def test_strength_fit_finds_the_minimum_between_grid_points():
    """The vertex of a parabola sampled on a coarse grid is found exactly, off the grid;
    at the grid's end it stays between the end and its neighbour; a curve with no
    bend keeps the grid's minimum; every column (resample) is fitted."""
    from chipstack.diagnosis.strength_fit import vertex

    grid = [0.0, 0.2, 0.4, 0.6, 0.8]
    x = np.array(grid)
    curves = np.column_stack([(x - 0.33) ** 2, (x - 0.05) ** 2, -x, np.abs(x - 0.6)])
    fitted = vertex(grid, curves, 1e-4)
    assert fitted[0] == pytest.approx(0.33)
    assert 0.0 <= fitted[1] <= 0.2 and fitted[1] == pytest.approx(0.05)  # signed: a vertex
    assert fitted[2] == pytest.approx(0.8)  # still falling at the end: the end
    assert 0.4 <= fitted[3] <= 0.8


def test_a_noisy_strength_curve_is_fitted_on_its_smoothed_shape_not_its_lowest_point():
    """Each grid point of a strength curve is its own simulation. The smoothed minimum
    finds a parabola's vertex exactly (a local quadratic reproduces one), and on curves
    whose grid points carry noise as large as the curve's bend (2,000 draws, minimum
    anywhere in the middle of the prior) it misses the truth by less than the parabola
    through the lowest point and its two neighbours does; on flat noise it does not pile
    up at the ends of the prior; a single low outlier beside the truth does not drag it
    most of a grid step away."""
    from chipstack.diagnosis.strength_fit import smoothed_minimum, vertex

    grid = [0.0, 0.4, 0.8, 1.2, 1.6, 2.0, 2.4, 2.8, 3.2, 3.6, 4.0]
    x = np.array(grid)
    assert smoothed_minimum(grid, (x - 1.37) ** 2, 1e-3)[0] == pytest.approx(1.37, abs=2e-3)
    rng = np.random.default_rng(5)
    truths = rng.uniform(0.5, 3.5, 2000)
    curves = np.column_stack([0.1 * (x - t) ** 2 + rng.normal(0, 0.1, x.size) for t in truths])
    smooth_error = np.sqrt(np.mean((smoothed_minimum(grid, curves, 1e-3) - truths) ** 2))
    vertex_error = np.sqrt(np.mean((vertex(grid, curves, 1e-3) - truths) ** 2))
    # Over 20 seeds of 2,000 draws the ratio was 0.85 to 0.89.
    assert smooth_error < 0.92 * vertex_error
    # On flat noise a parabola fitted at an end of the grid is noisier than mid-grid; an
    # end is kept only where the raw curve is lowest there too (unguarded: 39 % at the
    # ends; the vertex: 17 %).
    flat = smoothed_minimum(grid, rng.normal(0, 0.1, (x.size, 4000)), 1e-3)
    assert np.mean((flat <= 0.0) | (flat >= 4.0)) < 0.22
    outlier = 0.1 * (x - 2.0) ** 2
    outlier[7] -= 0.1  # 2.8 looks lowest, by one point's noise
    assert vertex(grid, outlier, 1e-3)[0] > 2.6
    assert smoothed_minimum(grid, outlier, 1e-3)[0] < 2.4


def test_the_discrepancy_left_is_read_off_the_smoothed_curve_at_its_minimum():
    """The ranking's discrepancy left at the fitted strength: exact on a parabola; on
    grid points with noise as large as the curve's bend (2,000 draws) it is biased low
    by a third of the lowest grid point's bias and varies less (measured: -0.029 and
    0.055 against -0.088 and 0.066 at noise 0.1), so an effect with a jagged curve is
    not ranked first for the luck of one grid point. It is the smoothed curve's value at
    the fitted strength, end guard and all. Its price: a V-shaped valley (slope 3) is
    read 0.62 high on the coarse grid, 0.24 with the strengths refined near it, so a
    steep right model is handicapped against a gentle imitator."""
    from chipstack.diagnosis.strength_fit import (
        SMOOTHING_POINTS,
        _loess_matrix,
        refined_strengths,
        smoothed_minimum,
        smoothed_minimum_value,
    )

    grid = [0.0, 0.4, 0.8, 1.2, 1.6, 2.0, 2.4, 2.8, 3.2, 3.6, 4.0]
    x = np.array(grid)
    assert smoothed_minimum_value(grid, 0.1 * (x - 1.37) ** 2 + 0.2)[0] == pytest.approx(0.2)
    rng = np.random.default_rng(5)
    truths = rng.uniform(0.5, 3.5, 2000)
    curves = np.column_stack(
        [0.1 * (x - t) ** 2 + 0.2 + rng.normal(0, 0.1, x.size) for t in truths]
    )
    left = smoothed_minimum_value(grid, curves) - 0.2
    lowest = curves.min(axis=0) - 0.2
    assert abs(left.mean()) < 0.5 * abs(lowest.mean())
    assert left.std() < lowest.std()
    # The value is the smoothed curve's at the very point the strength is fitted at,
    # also where an end of the grid is refused (flat noise: about a fifth of columns).
    flat = rng.normal(0, 0.1, (x.size, 500))
    smooth = _loess_matrix(tuple(grid), 7) @ flat
    fitted = smoothed_minimum(grid, flat, 1e-12)
    at = np.abs(np.linspace(0.0, 4.0, SMOOTHING_POINTS)[:, None] - fitted).argmin(axis=0)
    assert np.allclose(smoothed_minimum_value(grid, flat), smooth[at, np.arange(500)])
    # What it costs (documented): a V-shaped valley is read high, the more so the
    # steeper; the strengths refined near it cut the lift by about 60 %.
    vee = 3.0 * np.abs(x - 1.9)
    refined = sorted(grid + refined_strengths(grid, vee, 0.0, (0.0, 4.0), 11))
    coarse_lift = smoothed_minimum_value(grid, vee)[0]
    refined_lift = smoothed_minimum_value(refined, 3.0 * np.abs(np.array(refined) - 1.9))[0]
    assert 0.5 < coarse_lift < 0.7 and 0.2 < refined_lift < 0.3


def test_a_narrow_valley_is_refined_and_fitted_on_its_own_points():
    """A fold's coarse curve measured in a study case (compliant floor, truth 1.67: the
    curve lowest at 1.6 alone, its neighbours far above): the smoothing over seven grid
    points fits it far from the valley (0.48). Strengths near the curve's lowest point
    and smoothed minimum are added; with the valley's values there, the fit lands in it.
    A curve nowhere below its neutral strength adds nothing; no added strength is within
    a sixth of a step of another; all are on the fits' rounding lattice."""
    from chipstack.diagnosis.strength_fit import refined_strengths, smoothed_minimum

    grid = [0.0, 0.2, 0.4, 0.6, 0.8, 1.0, 1.2, 1.4, 1.6, 1.8, 2.0]
    coarse = np.array([0.66, 0.36, 0.31, 0.43, 0.41, 0.45, 1.0, 0.88, 0.05, 0.51, 0.48])
    assert smoothed_minimum(grid, coarse, 2e-3)[0] < 0.6

    def valley(x):  # lowest at 1.65, rising to 0.5 a fifth of a unit away
        return 0.05 + 0.45 * np.minimum(1.0, np.abs(np.asarray(x) - 1.65) / 0.2)

    added = refined_strengths(grid, coarse, 0.0, (0.0, 2.0), 11)
    # Around both the smoothed minimum (0.48) and the lowest grid point (1.6).
    assert [a for a in added if a < 1.0] == [0.35, 0.484, 0.55]
    assert [a for a in added if a > 1.0] == [1.466, 1.534, 1.666, 1.734]
    every = sorted([*grid, *added])
    assert min(np.diff(every)) > 0.2 / 6
    assert all(abs(a / 0.002 - round(a / 0.002)) < 1e-6 for a in added)
    curve = np.array([coarse[grid.index(v)] if v in grid else valley(v) for v in every])
    assert smoothed_minimum(every, curve, 2e-3)[0] == pytest.approx(1.65, abs=0.1)
    rising = np.linspace(0.0, 1.0, 11)  # lowest at the neutral strength: nothing to refine
    assert refined_strengths(grid, rising, 0.0, (0.0, 2.0), 11) == []


def test_the_tie_test_holds_its_level_with_the_simulations_noise_in_it():
    """The tie set's test. Two models equally far from the data (drops shifted by half a
    standard deviation from both), each known only through its own simulation of 120
    drops, scored on 75 held-out drops, the one with the larger held-out gap tested
    against the other: the per-drop paired t-test treats the simulations as exact and
    finds the loser worse in about 70 % of repeats (measured here, two seeds: 68 and
    71 %), though neither is; the bootstrap of the held-out gaps, which resamples the
    simulated drops too, at about its level (3 to 5 %; at most 10 % as the loser is the
    one of two that looks worse). A model twice as far leaves the tie (99 to 100 %)."""
    from chipstack.diagnosis.drop_effects import _p_worse, worse_than_best_p
    from chipstack.diagnosis.statistics import (
        energy_distance,
        mean_cross,
        mean_within,
        resample_weights,
    )

    rng = np.random.default_rng(3)
    n, m, resamples, repeats = 75, 120, 200, 300

    def distances(a, b):
        return np.linalg.norm(a[:, None] - b[None], axis=2)

    out = dict(t_test=0, bootstrap=0, farther=0)
    for _ in range(repeats):
        x = rng.normal(size=(n, 2)) + [0.5, 0.0]
        wx, wy = resample_weights(n, resamples, rng), resample_weights(m, resamples, rng)
        within_x = mean_within(distances(x, x), wx)
        gaps, scores = [], []
        for centre in ([0.0, 0.0], [0.0, 0.0], [-0.5, 0.0]):
            y = rng.normal(size=(m, 2)) + centre
            cross = distances(x, y)
            within_y = mean_within(distances(y, y), wy)
            gaps.append(energy_distance(mean_cross(cross, wx, wy), within_x, within_y))
            scores.append(cross.mean(axis=1) - 0.5 * within_y[0])
        loser = int(gaps[1][0] > gaps[0][0])
        best = 1 - loser
        out["t_test"] += _p_worse(scores[loser] - scores[best]) < 0.05
        out["bootstrap"] += worse_than_best_p(gaps[loser] - gaps[best]) < 0.05
        out["farther"] += worse_than_best_p(gaps[2] - gaps[best]) < 0.05
    assert out["t_test"] / repeats > 0.5
    assert out["bootstrap"] / repeats < 0.1
    assert out["farther"] / repeats > 0.9
    # The p-value is the estimate over its bootstrap sd, against the normal.
    draws = np.concatenate([[0.2], rng.normal(0.2, 0.1, 4000)])
    assert worse_than_best_p(draws) == pytest.approx(0.0228, abs=0.002)
    assert worse_than_best_p(np.zeros(5)) == 1.0 and worse_than_best_p(np.ones(5)) == 0.0


def test_joint_fit_finds_the_minimum_of_a_tilted_bowl_between_grid_points():
    """Strength and tilt together: a quadratic bowl with a cross term (the tilt absorbs
    part of the strength) sampled on the 3 x 3 stencil has its minimum found off both
    grids, where fitting the strength at the middle tilt alone misses it; a minimum
    beyond the box stays on its edge; every column is fitted."""
    from chipstack.diagnosis.strength_fit import quadratic_minimum, vertex

    xs, ys = [0.4, 0.5, 0.6], [3.23, 5.73, 8.23]
    u, v = np.meshgrid(xs, ys, indexing="ij")

    def bowl(s0, t0):
        # Elliptic, with a strong cross term: the valley runs diagonally.
        ds, dt = (u - s0) / 0.1, (v - t0) / 2.5
        return ds**2 + dt**2 + 1.2 * ds * dt

    surface = np.stack([bowl(0.47, 7.0), bowl(0.9, 5.73)], axis=-1)
    s, t = quadratic_minimum(xs, ys, surface)
    assert s[0] == pytest.approx(0.47, abs=0.003) and t[0] == pytest.approx(7.0, abs=0.07)
    # At the middle tilt alone the valley's floor lies elsewhere.
    alone = vertex(xs, bowl(0.47, 7.0)[:, 1], 1e-4)[0]
    assert alone == pytest.approx(0.5005, abs=1e-3)
    assert s[1] == pytest.approx(0.6)  # beyond the box: its edge


def test_plausible_strengths_are_the_grid_points_within_the_fits_interval():
    """The adequacy test also tries the grid's strengths inside the 95 % interval of the
    fit's resamples: none outside it, all inside (its ends included)."""
    from chipstack.diagnosis.strength_fit import within

    resamples = np.linspace(0.9, 2.1, 401)  # 95 % interval 0.93 to 2.07
    fitted = np.concatenate([[1.5], resamples])
    assert within([0.0, 0.8, 1.0, 1.6, 2.0, 2.4], fitted) == [1.0, 1.6, 2.0]
    assert within([0.0, 0.5], fitted) == []


def test_a_gap_every_held_out_half_sees_a_little_of_is_not_adjusted_away():
    """Four held-out datasets at p = 0.03 each: a Holm adjustment over them would call
    none significant (4 x 0.03 = 0.12), Fisher's combination (p = 0.0005) finds the model
    inadequate; a condition seen in two folds is named when its own combination is
    significant; p-values that look like noise leave nothing still off."""
    from chipstack.diagnosis.statistics import combined_p
    from chipstack.diagnosis.verdicts import _still_off

    rows = [dict(condition=c, p_after=0.03) for c in ("low", "high") for _fold in ("A", "B")]
    assert combined_p([0.03] * 4) == pytest.approx(0.000464, rel=0.01)
    assert _still_off(rows, 0.05) == ["high", "low"]  # each: Fisher of 0.03, 0.03 = 0.0075
    spread = [dict(condition=c, p_after=0.12) for c in ("a", "b", "c", "d", "e", "f")]
    assert combined_p([0.12] * 6) < 0.05  # together off, but no condition alone
    assert _still_off(spread, 0.05) == ["the held-out conditions taken together"]
    calm = [
        dict(condition=c, p_after=p) for c, p in zip("abcd", (0.3, 0.6, 0.9, 0.45), strict=True)
    ]
    assert _still_off(calm, 0.05) == []


def test_the_adequacy_calibrated_by_simulation_decides_over_fishers_combination():
    """Fisher's combination assumes uniform p-values under the model, but each adequacy
    test is a supremum over the plausible strengths, conservative: the combination
    calibrated on pseudo-experiments from the fitted model decides. Held-out p-values of
    0.3 look calm to Fisher (p = 0.35) yet can be rare for a model whose own
    pseudo-experiments give larger ones (calibrated p = 0.025): the model is inadequate,
    taken together; and a calibrated p of 0.5 clears a small Fisher combination."""
    from chipstack.diagnosis.statistics import combined_p
    from chipstack.diagnosis.verdicts import _still_off

    rows = [dict(condition=c, p_after=0.3) for c in ("low", "high")]
    assert combined_p([0.3, 0.3]) > 0.05
    assert _still_off(rows, 0.05) == []
    assert _still_off(rows, 0.05, overall_p=0.025) == ["the held-out conditions taken together"]
    small = [dict(condition=c, p_after=0.01) for c in ("low", "high")]
    assert _still_off(small, 0.05) == ["high", "low"]
    assert _still_off(small, 0.05, overall_p=0.5) == []


def test_drops_named_to_tell_two_models_apart_give_the_tie_test_its_power():
    """The next experiment's drop count is the paired score test's: at the named count, drops of
    one model scored against pools of each (the paired one-sided test on per-drop energy
    scores, 5 %) find the other worse in about 80 % of repeats (measured here; the pools'
    shared noise, which the t test does not see, keeps it a little below for close
    models). Farther models need fewer drops; two samples of one model no finite count;
    held-out drops already judged that lean one way need more (the count holds whichever
    model is true)."""
    from scipy.stats import norm, ttest_1samp

    from chipstack.diagnosis.drop_separation import drops_needed

    rng = np.random.default_rng(4)
    pool = 60

    def model(spread_mm, k):
        positions = rng.normal(scale=spread_mm, size=(k, 2))
        yaw = rng.uniform(0, 360, k)
        return np.column_stack(
            [positions, np.cos(np.radians(4 * yaw)), np.sin(np.radians(4 * yaw)), np.full(k, 1.0)]
        )

    z = norm.ppf(0.95) + norm.ppf(0.8)
    none = np.zeros(0)
    a, close_b, far_b = model(10.0, 600), model(15.0, 600), model(20.0, 600)
    _, far = drops_needed(NAMES, a, far_b, none, z, pool)
    _, close = drops_needed(NAMES, a, close_b, none, z, pool)
    _, same = drops_needed(NAMES, a, model(10.0, 600), none, z, pool)
    assert 40 <= far < close and same == np.inf
    # Held-out drops leaning one way must be overturned if the other model is the true
    # one: the count (for whichever is true) grows with the lean, in either direction.
    lean = rng.normal(0.0, 0.1, 150)
    counts = [
        drops_needed(NAMES, a, close_b, lean - lean.mean() + shift, z, pool)[1]
        for shift in (-0.02, -0.01, 0.0, 0.01, 0.02)
    ]
    assert counts[0] > counts[1] >= counts[2] <= counts[3] < counts[4]

    def score(d, k, lo, hi):
        within = d[lo:hi, lo:hi].sum() / (pool * (pool - 1))
        return d[:k, lo:hi].mean(axis=1) - 0.5 * within

    hits = 0
    for _ in range(200):
        data, a, b = model(10.0, int(far)), model(10.0, pool), model(20.0, pool)
        both = np.vstack([data, a, b])
        metric = FeatureMetric.of(both, "yaw_spread" in NAMES, "tilt_q50" in NAMES)
        d = metric.distances(metric.apply(both)).sum(axis=0)
        k = int(far)
        worse = score(d, k, k + pool, k + 2 * pool) - score(d, k, k, k + pool)
        hits += ttest_1samp(worse, 0.0, alternative="greater").pvalue < 0.05
    assert 0.7 <= hits / 200 <= 0.92


def test_feature_metric_compresses_tails_and_keeps_directions():
    positions = np.array([[3.0, 4.0], [0.0, 0.0], [-2000.0, 0.0], [0.0, 10.0]])
    tilt = np.array([0.5, 90.0, 0.5, 1.0])
    raw = drop_features(positions, np.zeros(4), tilt, 0.0, 4)
    metric = FeatureMetric.of(raw, has_yaw=True, has_tilt=True)
    squeezed = metric.compress(raw)
    r0 = metric.r0_mm  # the median distance, 7.5 mm
    assert r0 == pytest.approx(7.5)
    assert np.hypot(*squeezed[0, :2]) == pytest.approx(r0 * np.log1p(5.0 / r0))
    assert squeezed[0, 0] / squeezed[0, 1] == pytest.approx(0.75)  # the direction kept
    assert np.hypot(*squeezed[2, :2]) < 50  # a 2 m slide no longer dominates
    assert metric.scale[2] == metric.scale[3]  # the yaw circle stays round
    assert list(metric.blocks) == ["position", "yaw", "tilt"]
    assert metric.distances(metric.apply(raw)).shape == (3, 4, 4)


# -- effects -------------------------------------------------------------------------------
def _square():
    return make_shape(ChipSpec(), None, 1.0)


def test_effect_registry_lists_names_and_checks_priors():
    with pytest.raises(InputError, match="valid names: .*air_drag.*warp"):
        check_effects({"wind": 1.0}, "drop")
    with pytest.raises(InputError, match="outside the prior range"):
        check_effects({"warp": 10.0}, "drop")
    with pytest.raises(InputError, match="finite"):
        check_effects({"friction": math.nan}, "drop")
    with pytest.raises(InputError, match="acts on stack, container"):
        check_effects({"vibration": 100.0}, "drop")
    assert check_effects({"friction": 0.7}, "drop") == {"friction": 0.7}
    for name in EFFECTS:
        effect = EFFECTS.get(name)
        assert effect.prior[0] < effect.prior[1]
        assert len(effect.justification) > 80, name


def test_air_drag_holds_a_flat_chip_at_its_terminal_speed():
    shape = _square()
    mass = 1.70e-3 * shape.volume_mm3
    area = shape.plan_area_mm2
    strength = 2.0
    # Broadside drag coefficient A + B = 2.4: v_t = sqrt(2 m g / (rho S 2.4)).
    v_t = math.sqrt(2 * mass * 9810.0 / (AIR_DENSITY_G_MM3 * strength * area * 2.4))
    state = FlightState(
        positions=np.zeros((1, 3)),
        quaternions=np.array([[0.0, 0.0, 0.0, 1.0]]),
        velocities=np.array([[0.0, 0.0, -v_t]]),
        angular=np.zeros((1, 3)),
        shapes=(shape,),
        masses_g=np.array([mass]),
    )
    forces, torques = EFFECTS.get("air_drag").loads(state, strength)
    assert forces[0] == pytest.approx([0.0, 0.0, mass * 9810.0], rel=1e-9, abs=1e-9)
    assert np.abs(torques).max() < 1e-9  # broadside: no turning moment
    # Tilted 20 deg about x and falling: the Munk moment turns it back towards flat.
    tilted = FlightState(
        positions=np.zeros((1, 3)),
        quaternions=np.array([[math.sin(math.radians(10)), 0.0, 0.0, math.cos(math.radians(10))]]),
        velocities=np.array([[0.0, 0.0, -v_t]]),
        angular=np.zeros((1, 3)),
        shapes=(shape,),
        masses_g=np.array([mass]),
    )
    _, torques = EFFECTS.get("air_drag").loads(tilted, strength)
    assert torques[0, 0] < 0  # the tilt is +20 deg about x


def test_air_drag_face_normals_and_moments_agree_with_scipy():
    """The flight loads' written-out face normal and cross product (they run every step
    of a drop) against scipy's Rotation and numpy's cross on random states."""
    from scipy.spatial.transform import Rotation

    from chipstack.packing.effects.air_drag import _cross, _face_normals

    rng = np.random.default_rng(4)
    quaternions = Rotation.random(50, random_state=5).as_quat()
    expected = Rotation.from_quat(quaternions).apply([0.0, 0.0, 1.0])
    np.testing.assert_allclose(_face_normals(quaternions), expected, atol=1e-12)
    a, b = rng.normal(size=(2, 50, 3))
    np.testing.assert_allclose(_cross(a, b), np.cross(a, b), atol=1e-12)


def test_each_drop_is_independent_of_the_others_simulated_with_it():
    """Drop k lands where it lands whatever else is dropped beside it: its own random
    stream (spin and tilt), and the air's loads until it has landed itself (a drop that
    lands early is not kept under the air by one still falling)."""
    from chipstack.packing.drop import DropProtocol, simulate_drops
    from chipstack.pipeline.scenario_files import load_scenario

    scenario = load_scenario("single-chip-drop")
    protocol = DropProtocol(height_mm=150.0, tilt_deg=10.0)
    strengths = {"air_drag": 3.0, "release_perturbation": 10.0}
    two = simulate_drops(scenario, protocol, 2, strengths, seed=3)
    six = simulate_drops(scenario, protocol, 6, strengths, seed=3)
    np.testing.assert_allclose(six.positions[:2], two.positions, atol=1e-6)
    np.testing.assert_allclose(six.tilt_deg[:2], two.tilt_deg, atol=1e-6)
    assert np.abs(six.positions[2:] - six.positions[0]).max() > 0.1  # not all the same drop


@pytest.mark.xfail(
    strict=True,
    reason="known defect (docs/diagnosis.md, 'Drops are independent'): a warped chip, a "
    "compound of convex pieces, lands elsewhere when another drop lands at the same instant",
)
def test_a_warped_drop_is_independent_of_the_others_simulated_with_it():
    from chipstack.packing.drop import DropProtocol, simulate_drops
    from chipstack.pipeline.scenario_files import load_scenario

    scenario = load_scenario("single-chip-drop")
    protocol = DropProtocol(height_mm=200.0, tilt_deg=10.0)
    one = simulate_drops(scenario, protocol, 1, {"warp": 2.0}, seed=3)
    two = simulate_drops(scenario, protocol, 2, {"warp": 2.0}, seed=3)
    np.testing.assert_allclose(two.positions[:1], one.positions, atol=1e-3)


def test_drops_sharing_a_world_fall_apart_each_at_a_place_of_its_own():
    """Release points: a spiral whose k-th point depends on k alone, no two closer than
    the spacing (so released chips never share Bullet's broad phase), and every drop's
    landing reported from its own point (identical drops land at the same place)."""
    from chipstack.packing.drop import DropProtocol, release_places, simulate_drops
    from chipstack.pipeline.scenario_files import load_scenario

    places = release_places(50, 42.0)
    np.testing.assert_array_equal(places[:7], release_places(7, 42.0))
    gaps = np.linalg.norm(places[:, None] - places[None], axis=2)[np.triu_indices(50, 1)]
    assert gaps.min() == pytest.approx(42.0)
    assert np.abs(places).max() <= 4 * 42.0  # a compact square, not a line

    flat = simulate_drops(load_scenario("single-chip-drop"), DropProtocol(20.0, 0.0, 0.0), 5)
    np.testing.assert_allclose(flat.positions - flat.positions[0], 0.0, atol=1e-6)
    assert np.abs(flat.positions).max() < 5.0  # near its own release point


def test_an_effect_that_leaves_a_significant_gap_is_only_partly_explained():
    """'Explained' needs the held-out data to be consistent with the best effect: a
    residual gap beyond the noise floor after it (Holm across held-out conditions) makes
    the verdict 'partly explained', naming where."""
    from chipstack.diagnosis.verdicts import effect_verdict

    top = dict(
        effect="warp",
        held_out_reduction=0.6,
        held_out_reduction_ci95=[0.3, 0.8],
        gap_closed=1.2,
        gap_closed_ci95=[0.5, 2.0],
        p_better_than_baseline_holm=0.001,
        strength=0.4,
        unit="mm",
    )
    which = dict(ranking=[top], indistinguishable=["warp"])

    def residual(*p_after):
        rows = [dict(condition=f"c{k}", p_after=p) for k, p in enumerate(p_after)]
        return effect_verdict(["c0", "c1"], which, dict(conditions=rows), 0.05)

    assert residual(0.4, 0.6)["kind"] == "explained"
    partly = residual(0.001, 0.6)
    assert partly["kind"] == "partly explained" and partly["still_off"] == ["c0"]
    assert "remains after it in c0" in partly["text"]
    # Holm across the held-out conditions: 0.03 and 0.04 are not both below 0.05 / 2.
    assert residual(0.03, 0.6)["kind"] == "explained"
    # An effect that closes nothing for sure: unexplained, naming what is still off.
    weak = dict(top, gap_closed_ci95=[-0.1, 0.5], p_better_than_baseline_holm=0.3)
    where = dict(
        observables=[
            dict(condition="c0", observable="r_q90", beyond_noise=True),
            dict(condition="c1", observable="r_q50", beyond_noise=False),
        ],
        regions=[dict(condition="c1", region="ring", where="> 40 mm", notable=True)],
    )
    verdict = effect_verdict(["c0"], dict(which, ranking=[weak]), dict(conditions=[]), 0.05, where)
    assert verdict["kind"] == "unexplained"
    assert verdict["text"].endswith("Still off: r_q90 in c0, ring > 40 mm in c1.")
    # The verdict decides on the test against the baseline (Holm across the effects), not
    # on the bootstrap interval, which resamples the simulations too.
    paired = dict(weak, p_better_than_baseline_holm=0.01)
    assert effect_verdict(["c0"], dict(which, ranking=[paired]), {}, 0.05)["kind"] == "explained"
    luck = dict(top, p_better_than_baseline_holm=0.2)
    assert effect_verdict(["c0"], dict(which, ranking=[luck]), {}, 0.05)["kind"] == "unexplained"
    assert (
        "(best: warp, 60 % [30 %, 80 %])"
        in effect_verdict(["c0"], dict(which, ranking=[luck]), {}, 0.05)["text"]
    )
    # When even the top of the ranking closes nothing (an effect fitted to its neutral
    # strength is the baseline itself), no effect is named as the best.
    none = dict(luck, gap_closed=0.0, held_out_reduction=0.0, held_out_reduction_ci95=[0, 0])
    text = effect_verdict(["c0"], dict(which, ranking=[none]), {}, 0.05)["text"]
    assert "no candidate effect closes any of it" in text and "warp" not in text
    # The top of a whole-data ranking that does not close the held-out gap, with another
    # effect that does: unexplained, and the text does not claim that none closes it.
    closer = dict(top, effect="friction", p_better_than_baseline_holm=0.01)
    split = effect_verdict(["c0"], dict(which, ranking=[luck, closer]), {}, 0.05)
    assert split["kind"] == "unexplained"
    assert "warp fits the data best" in split["text"] and "friction does" in split["text"]


def test_rounded_chip_volume_matches_the_minkowski_formula():
    shape = _square()  # 20 x 20 x 2 mm
    r = 0.5
    rounded = EFFECTS.get("edge_rounding").shape(shape, r)
    a, b, c = 20 - 2 * r, 20 - 2 * r, 2 - 2 * r
    exact = a * b * c + 2 * r * (a * b + b * c + c * a) + math.pi * r**2 * (a + b + c)
    exact += 4 / 3 * math.pi * r**3
    # The hull samples the sphere at 10 deg: a little less than the exact rounded box.
    assert rounded.volume_mm3 == pytest.approx(exact, rel=0.01)
    assert rounded.volume_mm3 < shape.volume_mm3
    assert rounded.half_extents == pytest.approx(shape.half_extents, abs=1e-9)
    assert np.allclose(rounded.vertices.mean(axis=0), 0.0, atol=1e-6)


def test_warped_chip_keeps_its_volume_and_rises_at_its_ends():
    shape = _square()
    bow = 2.0
    warped = EFFECTS.get("warp").shape(shape, bow)
    assert warped.volume_mm3 == pytest.approx(shape.volume_mm3, rel=0.005)
    assert len(warped.convex_pieces) == 8
    # Arc of 20 mm rising 2 mm: the ends turn by theta with R (1 - cos theta) = 2, R theta = 10,
    # so the top corners at the ends stand bow + (T / 2)(1 + cos theta) above the bottom.
    theta = next(t for t in np.linspace(1e-3, 1.5, 150001) if 10 / t * (1 - np.cos(t)) >= bow)
    z = np.vstack(warped.convex_pieces)[:, 2]
    assert np.ptp(z) == pytest.approx(bow + 1.0 + np.cos(theta), abs=1e-3)
    # Mass properties about the centre of mass: the pieces are re-centred.
    assert np.allclose(np.vstack(warped.convex_pieces).mean(axis=0)[:2], 0.0, atol=1e-9)
    with pytest.raises(InputError, match="flat convex chips"):
        EFFECTS.get("warp").shape(make_shape(ChipSpec(shape="star"), None, 1.0), 1.0)


def test_effects_change_simulated_drops_the_way_physics_says():
    from chipstack.packing.drop import DropProtocol, simulate_drops
    from chipstack.pipeline.scenario_files import load_scenario

    scenario = load_scenario("single-chip-drop")
    protocol = DropProtocol(200.0, 0.0, 5.7296)

    def median_distance(strengths):
        sample = simulate_drops(scenario, protocol, 60, strengths, seed=4)
        assert sample.settled.all()
        return float(np.median(np.hypot(*sample.positions.T))), sample

    base, base_sample = median_distance({})
    bouncy, _ = median_distance({"restitution": 0.7})
    soft, _ = median_distance({"compliant_floor": 2.0})
    _, warped = median_distance({"warp": 2.5})
    assert bouncy > 2 * base  # more bounce, farther travel
    assert soft < base  # a soft floor swallows the bounce
    # A bowed chip often comes to rest tilted on its curved face (about 40 % of drops over
    # seeds 4 to 6), a flat one almost never.
    assert np.mean(warped.tilt_deg > 1.0) > 0.25
    assert np.mean(base_sample.tilt_deg > 1.0) < 0.1


def test_stack_deposition_with_effects(small_scenario):
    from chipstack.packing.deposition import deposit
    from chipstack.pipeline.scenario_files import load_scenario

    scenario = load_scenario(small_scenario)
    base = deposit(scenario)
    for strengths in ({"vibration": 200.0}, {"cohesion": 10.0}, {"friction": 0.9}):
        stack = deposit(scenario, effects=strengths)
        assert stack.n_chips == base.n_chips
        assert np.isfinite(stack.positions).all()
        assert not np.allclose(stack.positions, base.positions), strengths


# -- end to end ----------------------------------------------------------------------------
def test_synth_writes_observations_reproducibly(tmp_path):
    spec = drop_spec(tmp_path)
    a, b = tmp_path / "a.csv", tmp_path / "b.csv"
    for path in (a, b):
        result = run_cli(
            "synth",
            str(spec),
            "--effect",
            "friction=0.9",
            "--seed",
            "5",
            "--drops",
            "12",
            "-o",
            str(path),
            "--workers",
            "1",
        )
        assert result.returncode == 0, result.stderr
    assert a.read_text() == b.read_text()
    rows = list(csv.DictReader(a.open()))
    assert len(rows) == 24
    assert list(rows[0]) == ["condition", "drop", "x_mm", "y_mm", "yaw_deg", "tilt_deg"]
    assert {r["condition"] for r in rows} == {"low", "high"}
    again = run_cli("synth", str(spec), "--seed", "5", "-o", str(a))
    assert again.returncode == 2 and "file exists" in again.stderr


@pytest.mark.slow
def test_diagnose_finds_a_withheld_effect_and_no_gap_without_one(tmp_path):
    spec = drop_spec(tmp_path)
    data = tmp_path / "data.csv"
    made = run_cli(
        "synth",
        str(spec),
        "--effect",
        "restitution=0.7",
        "--seed",
        "11",
        "-o",
        str(data),
        "--workers",
        "2",
    )
    assert made.returncode == 0, made.stderr
    out = tmp_path / "report"
    result = run_cli("diagnose", str(spec), "--out", str(out), "--seed", "2", "--workers", "2")
    assert result.returncode == 0, result.stderr
    report = json.loads((out / "diagnosis.json").read_text())
    assert report["verdict"]["kind"] == "explained"
    assert "restitution" in report["which"]["indistinguishable"]
    top = {e["effect"]: e for e in report["which"]["ranking"]}["restitution"]
    assert top["held_out_reduction"] > 0.5
    # The strength made is 0.7; the fit is biased low (docs/diagnosis.md). Measured with
    # synth seeds 11 to 14 (diagnosis seed 2, 2026-12-02): 0.612, 0.622, 0.648, 0.632, a
    # mean of 0.629 and an sd of 0.015: held to the mean within 3 sd (was 0.4 to 0.8).
    assert top["strength"] == pytest.approx(0.629, abs=3 * 0.015)
    # The reported strength is fitted on the coarse grid (4 points, a step of 0.267)
    # refined near the whole data's minimum: strengths off the coarse grid within a step
    # of the fit (the neutral strength, off it too, is at most one of them).
    coarse = np.linspace(0.0, 0.8, 4)
    added = [v for v in top["strengths_tried"] if np.abs(coarse - v).min() > 1e-9]
    assert sum(abs(v - top["strength"]) < 0.267 for v in added) >= 3
    assert all(t["significant"] for t in report["where"]["tests"])
    for name in ("diagnosis.md", "fig_scatter.png", "fig_effects.png", "manifest.json"):
        assert (out / name).stat().st_size > 0
    assert "## 3. How far" in (out / "diagnosis.md").read_text()
    # The right model's adequacy, calibrated on pseudo-experiments drawn from it.
    adequacy = report["how_far"]["adequacy"]
    assert adequacy["replicates"] == 39 and adequacy["p_calibrated"] >= 0.05
    assert "calibrated by simulation" in (out / "diagnosis.md").read_text()
    # A tie names one next experiment (a release, its drops, their power); none without.
    joint = report["which"]["next_experiment"]
    if len(report["which"]["indistinguishable"]) >= 2:
        assert set(joint["separates"]) == set(report["which"]["indistinguishable"]) - {
            report["which"]["best"]
        }
        assert joint["power"] == 0.8 and "Next experiment" in (out / "diagnosis.md").read_text()
    else:
        assert joint is None

    # The same data with the true effect taken out of the library: friction closes part of
    # the gap, but the held-out data are not consistent with it (never "explained").
    outside = tmp_path / "outside.toml"
    outside.write_text(
        spec.read_text().replace('"restitution", "friction"', '"friction"'), encoding="utf-8"
    )
    result = run_cli("diagnose", str(outside), "--out", str(tmp_path / "o2"), "--workers", "2")
    assert result.returncode == 0, result.stderr
    verdict = json.loads((tmp_path / "o2" / "diagnosis.json").read_text())["verdict"]
    assert verdict["kind"] in ("partly explained", "unexplained"), verdict

    made = run_cli("synth", str(spec), "--seed", "12", "-o", str(data), "--overwrite")
    assert made.returncode == 0, made.stderr
    result = run_cli("diagnose", str(spec), "--out", str(out), "--overwrite", "--workers", "2")
    assert result.returncode == 0, result.stderr
    report = json.loads((out / "diagnosis.json").read_text())
    assert report["verdict"]["kind"] == "no significant gap"


STACK_SPEC = """
kind = "stack"
name = "small stacks"
observations = "quantities.csv"
[diagnosis]
effects = ["friction", "restitution"]
grid_points = 3
[[condition]]
name = "a"
scenario = "small.toml"
repeats = 2
[[condition]]
name = "b"
scenario = "small40.toml"
repeats = 2
"""


@pytest.mark.slow
def test_stack_diagnosis_end_to_end(tmp_path):
    (tmp_path / "small.toml").write_text(SMALL_SCENARIO)
    (tmp_path / "small40.toml").write_text(SMALL_SCENARIO.replace("chips = 24", "chips = 36"))
    spec = tmp_path / "spec.toml"
    spec.write_text(STACK_SPEC)
    data = tmp_path / "quantities.csv"
    made = run_cli(
        "synth", str(spec), "--effect", "friction=0.1", "-o", str(data), "--workers", "2"
    )
    assert made.returncode == 0, made.stderr
    rows = list(csv.DictReader(data.open()))
    assert {r["quantity"] for r in rows} >= {
        "volume_fraction",
        "contacts_per_chip",
        "layer_filling_0",
    }
    out = tmp_path / "report"
    result = run_cli("diagnose", str(spec), "--out", str(out), "--workers", "2")
    assert result.returncode == 0, result.stderr
    report = json.loads((out / "diagnosis.json").read_text())
    # Friction at 0.1 flattens the stacks (measured: G about 190 in both conditions).
    assert report["verdict"]["kind"] == "explained", report["verdict"]
    assert report["which"]["best"] == "friction"
    assert report["which"]["indistinguishable"] == ["friction"]
    lo, hi = report["which"]["ranking"][0]["strength_ci95"]
    assert lo <= 0.1 <= hi
    assert (out / "diagnosis.md").read_text().startswith("# Sim-to-real diagnosis")
    bad = tmp_path / "bad.csv"
    bad.write_text("condition,quantity,value\na,porosity,0.5\n")
    spec.write_text(STACK_SPEC.replace("quantities.csv", "bad.csv"))
    result = run_cli("diagnose", str(spec), "--out", str(tmp_path / "x"))
    assert result.returncode == 2
    assert "unknown quantity 'porosity'; valid: volume_fraction" in result.stderr


def test_a_gap_no_candidate_effect_can_act_on_is_unexplained(tmp_path):
    """Star chips, whose only candidate (a warp) needs a flat convex chip, dropped with a
    withheld restitution: the gap is found and called unexplained, with the report
    written (no ranking to show), not a traceback."""
    import dataclasses

    from chipstack.pipeline.scenario_files import dumps_toml, load_scenario

    star = dataclasses.replace(load_scenario("single-chip-drop"), chip=ChipSpec(shape="star"))
    (tmp_path / "star.toml").write_text(dumps_toml(star))
    spec = drop_spec(tmp_path, effects=("warp",), sim=20)
    spec.write_text(spec.read_text().replace('"single-chip-drop"', '"star.toml"'))
    data = tmp_path / "data.csv"
    made = run_cli(
        "synth", str(spec), "-o", str(data), "--seed", "1", "--effect", "restitution=0.8"
    )
    assert made.returncode == 0, made.stderr
    out = tmp_path / "report"
    result = run_cli("diagnose", str(spec), "--out", str(out))
    assert result.returncode == 0, result.stderr
    report = json.loads((out / "diagnosis.json").read_text())
    assert report["verdict"]["kind"] == "unexplained"
    assert "no candidate effect applies" in report["verdict"]["text"]
    assert report["which"]["ranking"] == [] and report["which"]["best"] is None
    assert "warp" in report["which"]["not_applicable"]
    assert "No candidate effect can act on these chips" in (out / "diagnosis.md").read_text()
    assert (out / "fig_scatter.png").stat().st_size > 0


def test_effects_that_cannot_act_on_the_chip_are_set_aside():
    from chipstack.diagnosis.spec import Condition, Experiment
    from chipstack.diagnosis.verdicts import applicable_effects
    from chipstack.packing.drop import DropProtocol
    from chipstack.pipeline.scenario_files import load_scenario

    base = load_scenario("single-chip-drop")
    star = base.__class__(**{**base.__dict__, "chip": ChipSpec(shape="star")})
    experiment = Experiment(
        name="star",
        kind="drop",
        scenario=star,
        conditions=(Condition("a", protocol=DropProtocol()),),
        observations=Path("x.csv"),
    )
    usable, skipped = applicable_effects(experiment)
    assert set(skipped) == {"edge_rounding", "warp"}
    assert "flat convex chips" in skipped["warp"]
    assert "air_drag" in usable and "friction" in usable


@pytest.mark.slow
def test_release_tilt_fitted_jointly_finds_the_tilt_that_made_the_data(tmp_path):
    """Drops made with restitution 0.7 at a release tilt 2.5 deg above the spec's. Fitted
    jointly, the release tilt's offset is found (+2.5 deg, its interval holding it) and
    restitution is still named; with the tilt known the offset stays at 0. Measured with
    seeds 11 to 14 (2026-11-27): the offset +2.5 in 4 of 4, restitution best in 8 of 8.
    The strength is fitted low in every one (0.49 to 0.63 for 0.7, both ways; the joint
    interval holds 0.7 in 2 of 4, the known one in 3 of 4), so no claim on the strength
    interval is made here: an earlier version asserted that the joint interval widens and
    holds the truth, which was one seed's luck."""
    spec = drop_spec(tmp_path, effects=("restitution", "friction"))
    text = spec.read_text()
    made = tmp_path / "made.toml"
    made.write_text(
        text.replace("height_mm = 200", "height_mm = 200\ntilt_deg = 8.2296").replace(
            "height_mm = 600", "height_mm = 600\ntilt_deg = 8.2296"
        )
    )
    fitted = tmp_path / "fitted.toml"
    fitted.write_text(text.replace("[diagnosis]", '[diagnosis]\nrelease_tilt = "fitted"'))
    data = tmp_path / "data.csv"
    result = run_cli(
        "synth", str(made), "--effect", "restitution=0.7", "--seed", "11", "-o", str(data)
    )
    assert result.returncode == 0, result.stderr
    entries = {}
    for name, path in (("known", spec), ("fitted", fitted)):
        out = tmp_path / name
        result = run_cli("diagnose", str(path), "--out", str(out), "--workers", "2")
        assert result.returncode == 0, result.stderr
        report = json.loads((out / "diagnosis.json").read_text())
        assert report["which"]["best"] == "restitution"
        entries[name] = report["which"]["ranking"][0]
    known, joint = entries["known"], entries["fitted"]
    assert known["release_tilt_offset_deg"] == 0.0
    # The offset is the fit's, snapped to 0.1 deg: +2.5 in 4 of 4 seeds (11 to 14), so held
    # to that step (was +-1.25, half the offsets' grid step). Measured again 2026-12-02 with
    # seeds 11 and 12, and with the data made 1.5 deg above the spec instead: +2.5 there
    # too, so the offset is resolved to its grid step (2.5 deg), no finer.
    assert joint["release_tilt_offset_deg"] == pytest.approx(2.5, abs=0.1)
    low, high = joint["release_tilt_offset_ci95"]
    assert low <= 2.5 <= high


def test_simulation_batches_go_longest_first_and_come_back_in_order():
    """A batch's calls are handed to the workers longest first (air drag from high up
    before a short drop without it: a long call left to the end idles the other worker),
    and every result comes back in the caller's order."""
    from types import SimpleNamespace

    from chipstack.diagnosis.drop_simulations import _longest_first

    seen = []

    def run_many(function, calls):
        seen.extend(c["name"] for c in calls)
        return [function(**c) for c in calls]

    calls = [
        dict(name="short", n=60, protocol=SimpleNamespace(height_mm=200.0), strengths={}),
        dict(
            name="air",
            n=60,
            protocol=SimpleNamespace(height_mm=1000.0),
            strengths={"air_drag": 2.0},
        ),
        dict(name="high", n=60, protocol=SimpleNamespace(height_mm=1000.0), strengths={}),
        dict(name="many", n=120, protocol=SimpleNamespace(height_mm=200.0), strengths={}),
    ]
    results = _longest_first(run_many)(lambda **c: c["name"], calls)
    assert results == ["short", "air", "high", "many"]
    assert seen == ["air", "many", "high", "short"]  # cost 388, 240, 194, 120
