"""The stack and container diagnosis's statistics on cases with known answers.

The depositions are replaced by a linear model of the quantities in the effects'
strengths with Gaussian repeat-to-repeat noise (common random numbers: a repeat's noise
does not depend on the setting), so the right answers are known exactly and hundreds of
cases take seconds. The real depositions go through the same code in
``tests/test_diagnosis.py::test_stack_diagnosis_end_to_end``.
"""

from __future__ import annotations

import dataclasses
import zlib
from pathlib import Path

import numpy as np

from chipstack.diagnosis.spec import Condition, DiagnosisSettings, Experiment, QuantityData
from chipstack.diagnosis.stacks import diagnose_stacks
from chipstack.pipeline.scenario_files import load_scenario

FRICTION0, RESTITUTION0 = 0.5, 0.3  # the default preset's (the effects' neutral strengths)
# Per condition: how strongly friction moves the volume fraction and restitution the
# height (the conditions differ, so a strength fitted on two predicts the third).
FACTORS = {"a": 1.0, "b": 1.5, "c": 2.0}
NOISE = {"volume_fraction": 0.004, "height_mean_mm": 0.1, "contacts_per_chip": 0.05}
REPEATS = 3


def model_mean(condition: str, strengths: dict) -> dict[str, float]:
    """The quantities' expected values under ``strengths``."""
    k = FACTORS[condition]
    df = strengths.get("friction", FRICTION0) - FRICTION0
    de = strengths.get("restitution", RESTITUTION0) - RESTITUTION0
    return {
        "volume_fraction": 0.50 - 0.10 * df * k + 0.02 * de,
        "height_mean_mm": 10.0 + 3.0 * df + 4.0 * de * k,
        "contacts_per_chip": 3.0 + 0.8 * df - 1.5 * de,
    }


def fake_run_many(_function, calls: list[dict]) -> list[dict]:
    """Stands in for the depositions: the model's mean plus the repeat's noise."""
    out = []
    for call in calls:
        condition = call["scenario"].name
        rng = np.random.default_rng([call["seed"], zlib.crc32(condition.encode())])
        mean = model_mean(condition, call["strengths"])
        out.append({q: mean[q] + NOISE[q] * rng.normal() for q in NOISE})
    return out


def experiment(effects=("friction", "restitution")) -> Experiment:
    base = load_scenario("paper-squares")
    conditions = tuple(
        Condition(name, scenario=dataclasses.replace(base, name=name), repeats=REPEATS)
        for name in FACTORS
    )
    return Experiment(
        name="analytic stacks",
        kind="stack",
        scenario=base,
        conditions=conditions,
        observations=Path("quantities.csv"),
        settings=DiagnosisSettings(effects=tuple(effects), grid_points=5),
    )


def measured(truth: dict, rng, n: int = 5, shift: dict | None = None) -> dict:
    """Each quantity as the mean and sd of ``n`` measurements, scattered as the repeats."""
    data = {}
    for condition in FACTORS:
        mean = model_mean(condition, truth)
        data[condition] = {}
        for q in NOISE:
            values = mean[q] + (shift or {}).get(q, 0.0) + NOISE[q] * rng.normal(size=n)
            data[condition][q] = QuantityData(values.mean(), values.std(ddof=1), n)
    return data


def test_effect_free_measurements_are_passed_at_the_nominal_rate():
    """300 effect-free datasets: the share called a gap is about alpha (Bonferroni within
    a condition and Holm across conditions bound it by 5 %; measured 16 of 300), and the
    same datasets shifted by 4 standard errors in one quantity are found."""
    x = experiment()
    rng = np.random.default_rng(5)
    alarms = found = 0
    cases = 300
    for seed in range(cases):
        data = measured({}, rng)
        report = diagnose_stacks(x, data, fake_run_many, seed=seed)
        if report["verdict"]["kind"] == "no significant gap":
            assert report["which"] is None  # effect-free data stop after the detection
        else:
            alarms += 1
        se = np.sqrt(NOISE["height_mean_mm"] ** 2 * (1 / 5 + 1 / REPEATS))
        shifted = measured({}, rng, shift={"height_mean_mm": 4 * se})
        found += diagnose_stacks(x, shifted, fake_run_many, seed=seed)["verdict"]["kind"] != (
            "no significant gap"
        )
    # 300 cases at a true rate of 5 %: above 9 % has probability 0.002.
    assert alarms / cases <= 0.09, alarms
    assert found / cases >= 0.8, found  # measured: 16 alarms, 298 found


def test_withheld_friction_is_explained_with_its_strength():
    x = experiment()
    truth = 0.85
    report = diagnose_stacks(
        x, measured({"friction": truth}, np.random.default_rng(1)), fake_run_many
    )
    which = report["which"]
    assert report["verdict"]["kind"] == "explained", report["verdict"]
    assert which["best"] == "friction"
    assert which["indistinguishable"] == ["friction"]
    top = which["ranking"][0]
    lo, hi = top["strength_ci95"]
    assert lo <= truth <= hi and hi - lo < 0.2, (lo, hi)
    assert abs(top["strength"] - truth) < 0.05
    assert top["p_better_than_baseline_holm"] < 0.05
    # Fitted off the grid (0.1, 0.325, 0.5, 0.55, 0.775, 1.0), then simulated there.
    assert all(0.8 <= f["strength"] <= 0.9 for f in top["folds"])
    assert report["how_far"]["reduction"] > 0.8
    rest = next(r for r in which["ranking"] if r["effect"] == "restitution")
    assert not rest["indistinguishable_from_best"] and rest["p_worse_than_best"] < 0.05


def test_a_gap_no_effect_makes_is_not_explained():
    """Friction withheld, and the contacts counted 10 standard deviations high in every
    condition, which neither candidate does along with the rest: friction closes part of
    the gap but the held-out measurements are still off."""
    x = experiment()
    data = measured({"friction": 0.85}, np.random.default_rng(2), shift={"contacts_per_chip": 0.5})
    report = diagnose_stacks(x, data, fake_run_many)
    assert report["verdict"]["kind"] in ("partly explained", "unexplained"), report["verdict"]
    off = [r for r in report["where"]["observables"] if r["beyond_noise"]]
    assert {r["observable"] for r in off} >= {"contacts_per_chip"}


def test_effects_the_data_cannot_tell_apart_are_tied(monkeypatch):
    """When restitution moves every quantity exactly as friction does (on its own
    scale), the two are tied and the verdict names both."""

    def mirrored(condition, strengths):
        f = strengths.get("friction", FRICTION0) - FRICTION0
        e = strengths.get("restitution", RESTITUTION0) - RESTITUTION0
        return original(condition, {"friction": FRICTION0 + f + e})

    original = model_mean
    monkeypatch.setattr(f"{__name__}.model_mean", mirrored)
    report = diagnose_stacks(
        experiment(), measured({"friction": 0.8}, np.random.default_rng(3)), fake_run_many
    )
    assert sorted(report["which"]["indistinguishable"]) == ["friction", "restitution"]
    assert report["verdict"]["kind"] == "explained"
    assert report["verdict"]["indistinguishable"]


def independent_run_many(_function, calls: list[dict]) -> list[dict]:
    """As ``fake_run_many``, but every setting's noise is its own (no common random
    numbers: a chaotic deposition that a different effect sends elsewhere)."""
    out = []
    for call in calls:
        condition = call["scenario"].name
        setting = repr(sorted(call["strengths"].items()))
        rng = np.random.default_rng(
            [call["seed"], zlib.crc32(condition.encode()), zlib.crc32(setting.encode())]
        )
        mean = model_mean(condition, call["strengths"])
        out.append({q: mean[q] + NOISE[q] * rng.normal() for q in NOISE})
    return out


def test_the_share_of_noise_settings_have_in_common_is_measured():
    """Noise that repeats with the seed in every setting is shared (1); noise of each
    setting's own is not (about 0)."""
    from chipstack.diagnosis.stacks import StackRuns, StackScores

    x = experiment()
    data = measured({"friction": 0.8}, np.random.default_rng(4))
    for run_many, low, high in ((fake_run_many, 0.99, 1.0), (independent_run_many, 0.0, 0.3)):
        runs = StackRuns(x, run_many, 0, lambda message: None)
        runs.ensure(
            [runs.key(c, None, 0.0) for c in FACTORS]
            + [
                runs.key(c, e, s)
                for c in FACTORS
                for e, s in (("friction", 0.7), ("friction", 0.9), ("restitution", 0.5))
            ]
        )
        scores = StackScores(data, runs, 0)
        scores.freeze()
        assert all(low <= scores.shared[("a", q)] <= high for q in NOISE), scores.shared


def test_strength_intervals_cover_the_truth():
    """200 datasets, friction drawn between grid points, simulations without common random
    numbers: the 95 % strength intervals hold the truth at a rate the diagnosis's target
    allows, 90 to 98 % (docs/measured.md): the count is not in the binomial 5 % tail below
    200 draws at 90 %, nor in that above 200 draws at 98 % (it passes 173 to 199 of 200),
    so intervals too narrow or too wide (every one covering) fail. Measured 181 of 200
    (90.5 %), every dataset fitted; the 40 datasets of before gave 39 of 40, which could
    not tell 80 % from 95 %."""
    from scipy.stats import binom

    x = experiment()
    covered = fitted = 0
    n = 200
    for i in range(n):
        rng = np.random.default_rng(100 + i)
        truth = float(rng.uniform(0.6, 0.95))
        report = diagnose_stacks(
            x, measured({"friction": truth}, rng), independent_run_many, seed=i
        )
        if report["which"] is None:
            continue
        lo, hi = {e["effect"]: e for e in report["which"]["ranking"]}["friction"]["strength_ci95"]
        fitted += 1
        covered += lo <= truth <= hi
    assert fitted >= 0.95 * n, fitted  # measured: 200 of 200
    assert binom.cdf(covered, fitted, 0.90) >= 0.05, (covered, fitted)
    assert binom.sf(covered - 1, fitted, 0.98) >= 0.05, (covered, fitted)
