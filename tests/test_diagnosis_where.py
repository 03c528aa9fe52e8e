"""The drop diagnosis's detection and "where": one max-T over the energy statistics and
the targeted ones (every observable per condition and summed over conditions, every
region), the same joint permutations for all, and Westfall-Young adjusted p-values for
the rows it names. Real numbers throughout: synthetic samples through the statistics
functions, and ``locate_gap`` on synthetic drops (no physics simulation)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.distance import cdist

from chipstack.diagnosis.drop_where import gap_family
from chipstack.diagnosis.statistics import (
    energy_statistics,
    exceedance_p,
    max_t_adjusted,
    permutation_masks,
    standardise,
)

FEATURES = 8
SHIFTED = 2


def _condition(rng, shift: float, n: int, m: int, permutations: int):
    """One condition: n experiment and m simulation drops of FEATURES heavy-tailed
    features, feature SHIFTED moved by ``shift`` in the experiment; under every
    labelling its energy statistic (1, R), the standardised mean differences of the
    features (K, R) and of the shares of two regions (2, R)."""
    x, y = rng.standard_t(5, (n, FEATURES)), rng.standard_t(5, (m, FEATURES))
    x[:, SHIFTED] += shift
    pooled = np.vstack([x, y])
    masks = permutation_masks(n, m, permutations, rng)
    a = masks.astype(float)
    differences = a @ pooled / n - (1.0 - a) @ pooled / m
    inside = np.column_stack([pooled[:, 0] > 0, pooled[:, 1] > 0.5]).astype(float)
    shares = a @ inside / n - (1.0 - a) @ inside / m
    energy = standardise(energy_statistics(cdist(pooled, pooled), masks)[None])
    return energy, standardise(differences.T), standardise(shares.T)


def _family(rng, shift: float, conditions=3, n=30, m=45, permutations=999):
    """The labels and statistics of ``gap_family``, and the signed z-scores (C, K, R)."""
    parts = [_condition(rng, shift, n, m, permutations) for _ in range(conditions)]
    energy = sum(p[0] for p in parts)
    labels, family = gap_family(energy, [p[1] for p in parts], [p[2] for p in parts])
    return labels, family, np.array([p[1] for p in parts])


def _detection_p(family: np.ndarray) -> float:
    largest = family.max(axis=0)
    return exceedance_p(largest[1:], largest[0])


def test_max_t_adjusted_p_values_are_at_least_the_raw_ones_and_monotone():
    """Correlated statistics, three of them shifted: each adjusted p-value is at least its
    raw permutation p-value; a larger statistic never gets a larger adjusted p-value;
    step-down never exceeds single-step; the largest statistic's adjusted p-value is the
    max-T test of the whole family."""
    rng = np.random.default_rng(0)
    common = rng.normal(size=(1, 2000))
    statistics = np.abs(0.6 * common + 0.8 * rng.normal(size=(40, 2000)))
    statistics[:3, 0] = [4.5, 3.6, 3.2]
    raw = np.array([exceedance_p(s[1:], s[0]) for s in statistics])
    down = max_t_adjusted(statistics)
    single = max_t_adjusted(statistics, step_down=False)
    assert (down >= raw - 1e-12).all() and (single >= raw - 1e-12).all()
    assert (down <= single + 1e-12).all()
    order = np.argsort(-statistics[:, 0])
    assert (np.diff(down[order]) >= 0).all() and (np.diff(single[order]) >= 0).all()
    largest = statistics.max(axis=0)
    assert down.min() == pytest.approx(exceedance_p(largest[1:], largest[0]))
    assert down[0] < 0.01 and single[0] < 0.01
    # A statistic as large as the null's typical maximum is not flagged, though its raw
    # p-value, alone, would be.
    assert raw[2] < 0.01 and down[2] > raw[2]


@pytest.mark.parametrize("shift", [0.8, -0.8])
def test_a_shift_of_one_observable_in_every_condition_is_detected_and_named(shift):
    """Feature 2 moved by 0.8 (0.6 sd) in each of three conditions and nothing else:
    detected, and the only observable named is feature 2, across the conditions, in the
    direction of the shift."""
    rng = np.random.default_rng(1)
    labels, family, z = _family(rng, shift)
    adjusted = dict(zip(labels, max_t_adjusted(family), strict=True))
    assert _detection_p(family) < 0.01
    named = [label for label, p in adjusted.items() if p < 0.05 and label[0] != "energy"]
    assert ("across conditions", SHIFTED) in named
    assert {label[-1] for label in named if label[0] != "regions"} == {SHIFTED}
    assert not any(label[0] == "regions" for label in named)
    assert np.sign(z[:, SHIFTED, 0].sum()) == np.sign(shift)


def test_the_targeted_statistics_find_a_one_feature_shift_more_often_than_energy_alone():
    """Over 30 datasets with feature 2 moved by 0.7 in every condition: the family's
    max-T detects it more often than the energy statistic alone (the former detection),
    and a feature other than 2 is named no more often than the family-wise error
    allows."""
    rng = np.random.default_rng(4)
    family_hits = energy_hits = wrong = 0
    for _ in range(30):
        labels, family, _ = _family(rng, 0.7, permutations=299)
        energy = family[[i for i, label in enumerate(labels) if label[0] == "energy"]]
        family_hits += _detection_p(family) < 0.05
        energy_hits += _detection_p(energy) < 0.05
        adjusted = max_t_adjusted(family)
        wrong += any(
            p < 0.05 and label[0] in ("across conditions", "per condition") and label[-1] != 2
            for label, p in zip(labels, adjusted, strict=True)
        )
    assert family_hits > energy_hits + 3  # measured: 24 against 19
    # Naming a feature that did not move is a family-wise error: at most 5 % a dataset,
    # so at most 4 of 30 datasets (binomial, 98 %); measured: 1.
    assert wrong <= 4


def test_false_alarms_of_the_detection_and_of_where_stay_at_five_percent():
    """No gap (the same distribution on both sides), 300 small datasets of 3 conditions
    with 199 permutations: the detection's false-alarm rate at 5 % is within the 99.9 %
    binomial band of 5 % (1.7 % to 9.7 %), and "where" flags something exactly when the
    detection fires (its family-wise error is the detection's)."""
    rng = np.random.default_rng(2)
    alarms, flagged = [], []
    for _ in range(300):
        _, family, _ = _family(rng, shift=0.0, n=12, m=18, permutations=199)
        alarms.append(_detection_p(family) <= 0.05)
        flagged.append(bool((max_t_adjusted(family) <= 0.05).any()))
    assert 0.017 <= np.mean(alarms) <= 0.097
    assert flagged == alarms


def test_max_t_of_the_family_on_a_null_case_is_not_significant():
    """The check that reports "significant" above, on the same sizes with no shift."""
    rng = np.random.default_rng(3)
    labels, family, _ = _family(rng, shift=0.0)
    assert _detection_p(family) > 0.05
    assert (max_t_adjusted(family) > 0.05).all()
    assert len(labels) == 1 + FEATURES + 3 * FEATURES + 3 * 2


# -- locate_gap on synthetic drops ---------------------------------------------------------
def _synthetic_where(shift_mm: float | dict, seed: int, drops: int = 60):
    """``locate_gap`` on three conditions of synthetic drops (round normal scatter, its
    spread growing with the height; uniform yaw; small tilts) against simulations drawn
    the same way, the experiment's moved by ``shift_mm`` along x in every condition (or
    by ``shift_mm[condition]``)."""
    from chipstack.diagnosis.drop_simulations import Dataset, DropSimulations
    from chipstack.diagnosis.drop_where import locate_gap
    from chipstack.diagnosis.observables import observable_names
    from chipstack.diagnosis.spec import Condition, DiagnosisSettings, DropData, Experiment
    from chipstack.packing.drop import DropProtocol
    from chipstack.pipeline.scenario_files import load_scenario

    def draw(rng, protocol, n, shift=0.0):
        spread = 6.0 * (protocol.height_mm / 200.0) ** 0.5
        positions = rng.normal(0.0, spread, size=(n, 2)) + [shift, 0.0]
        return DropData(positions, rng.uniform(-180, 180, n), np.abs(rng.normal(0, 1.0, n)))

    def simulate(scenario, protocol, n, strengths, seed, position_sd_mm, angle_sd_deg):
        return draw(np.random.default_rng(seed), protocol, n)

    heights = {"low": 100.0, "mid": 200.0, "high": 400.0}
    experiment = Experiment(
        name="synthetic",
        kind="drop",
        scenario=load_scenario("single-chip-drop"),
        conditions=tuple(Condition(c, protocol=DropProtocol(h)) for c, h in heights.items()),
        observations=None,
        settings=DiagnosisSettings(sim_drops=120, bootstrap=50),
    )
    sims = DropSimulations(
        experiment,
        observable_names(True, True),
        simulate,
        lambda function, calls: [function(**kwargs) for kwargs in calls],
        seed,
        lambda message: None,
    )
    rng = np.random.default_rng([seed, 1])
    shifts = shift_mm if isinstance(shift_mm, dict) else dict.fromkeys(heights, shift_mm)
    data = {c.name: draw(rng, c.protocol, drops, shifts[c.name]) for c in experiment.conditions}
    sims.ensure([sims.baseline(c, None) for c in heights])
    for c in heights:
        sims.set_metric(c, data[c])
    full = {c: Dataset.observe(c, data[c], sims, rng) for c in heights}
    return locate_gap(full, sims, rng, 0.05)


def test_locate_gap_names_a_shifted_mean_position_with_its_direction():
    """Every condition's drops moved 1.8 mm along +x (a fifth to a third of the scatter's
    spread), as a tilted floor would: detected, and "where" names mean_x, across the
    conditions and upwards, and no other observable; the report's rows carry the
    direction, the adjusted p-value (never below the raw one) and the hierarchical list
    per condition."""
    where = _synthetic_where(1.8, seed=5)
    overall = where["overall"]
    assert overall["significant"] and overall["p_value"] < 0.01
    assert set(overall["by_statistic"]) == {
        "energy",
        "across conditions",
        "per condition",
        "regions",
    }
    assert overall["family_size"] == 4 + 12 + 3 * 12 + 3 * 13
    across = [r for r in where["across_conditions"] if r["beyond_noise"]]
    assert [r["observable"] for r in across] == ["mean_x"]
    assert across[0]["direction"] == 1 and across[0]["mean_difference"] > 0
    # The largest standardised statistic: measured, the position block's energy (4.4)
    # just above mean_x across the conditions (4.2).
    assert overall["carried_by"] in (
        "mean_x across the conditions (+)",
        "energy statistic (position) summed over the conditions",
    )
    named = {r["observable"] for r in where["observables"] if r["beyond_noise"]}
    assert named <= {"mean_x"}
    for r in where["observables"] + where["regions"]:
        assert r["p_adjusted"] >= r["p_value"] - 1e-12
        assert r["direction"] == int(np.sign(r["difference"]))
    for t in where["tests"]:
        flagged = [
            r
            for r in where["observables"]
            if r["condition"] == t["condition"] and r["beyond_noise"]
        ]
        flagged.sort(key=lambda r: r["p_adjusted"])
        assert [o["observable"] for o in t["observables_beyond_noise"]] == [
            r["observable"] for r in flagged
        ]


def test_locate_gap_on_drops_without_a_gap_reports_none():
    """The same check on drops drawn like their simulations: no gap detected, nothing
    named."""
    where = _synthetic_where(0.0, seed=6)
    assert not where["overall"]["significant"]
    assert not any(r["beyond_noise"] for r in where["observables"] + where["across_conditions"])
    assert not any(r["notable"] for r in where["regions"])


def test_where_reads_conditions_first_then_the_observables_within_them():
    """Only the highest condition's drops moved (6 mm along +x, 0.7 of its spread): that
    condition's test is significant and lists mean_x, upwards, as what is off in it; the
    others list nothing; the verdict's text names it with its direction and size."""
    from chipstack.diagnosis.verdicts import off_text

    where = _synthetic_where({"low": 0.0, "mid": 0.0, "high": 6.0}, seed=7)
    assert where["overall"]["significant"]
    assert where["overall"]["carried_by"] == "mean_x in high (+)"
    tests = {t["condition"]: t for t in where["tests"]}
    assert tests["high"]["significant"]
    assert not tests["low"]["significant"] and not tests["mid"]["significant"]
    off = tests["high"]["observables_beyond_noise"]
    assert [o["observable"] for o in off] == ["mean_x"] and off[0]["direction"] == 1
    assert off[0]["difference"] > 0 and off[0]["p_adjusted"] < 0.05
    assert (
        tests["low"]["observables_beyond_noise"] == tests["mid"]["observables_beyond_noise"] == []
    )
    assert off_text(where) == f" Still off: mean_x in high ({off[0]['difference']:+.3g} mm)."
