"""How well a trained model choice does on its own table, from its out-of-fold
predictions: the expected calibration error, the smallest credible set of models, exact
binomial intervals, and the design's checks (accuracy, confusion, the hardest pairs,
calibration, coverage of the credible sets and of the strength intervals).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.stats import binomtest

from chipstack.diagnosis.reference_table import NO_EFFECT
from chipstack.packing.effects import EFFECTS

__all__ = [
    "CREDIBLE",
    "clopper_pearson",
    "credible_set_indices",
    "design_checks",
    "expected_calibration_error",
    "smallest_credible_set",
]

CREDIBLE = 0.95


def expected_calibration_error(probabilities: np.ndarray, truth: np.ndarray, bins: int = 15):
    """Top-label expected calibration error: the mean, weighted by bin size, of
    |accuracy - confidence| over equal-width bins of the highest probability (0 for
    perfectly calibrated probabilities)."""
    confidence = probabilities.max(axis=1)
    correct = probabilities.argmax(axis=1) == truth
    edges = np.linspace(0.0, 1.0, bins + 1)
    which = np.clip(np.digitize(confidence, edges[1:-1]), 0, bins - 1)
    total = 0.0
    for b in range(bins):
        mine = which == b
        if mine.any():
            total += mine.mean() * abs(correct[mine].mean() - confidence[mine].mean())
    return float(total)


def smallest_credible_set(probabilities: dict[str, float], level: float = CREDIBLE) -> list[str]:
    """The fewest models whose probabilities add up to ``level``, most probable first."""
    chosen, total = [], 0.0
    for name, p in sorted(probabilities.items(), key=lambda item: -item[1]):
        chosen.append(name)
        total += p
        if total >= level - 1e-12:
            break
    return chosen


def clopper_pearson(successes: int, trials: int) -> list[float]:
    """The exact (Clopper-Pearson) 95 % interval of a proportion, ``[low, high]``; both
    NaN with no trial."""
    if trials == 0:
        return [math.nan, math.nan]
    ci = binomtest(successes, trials).proportion_ci(0.95, method="exact")
    return [float(ci.low), float(ci.high)]


def design_checks(models, y, groups, strength, votes, calibrated, curve, strengths) -> dict:
    """The design's ceiling and calibration, from the out-of-fold predictions."""
    classes = len(models)
    predicted = calibrated.argmax(axis=1)
    correct = predicted == y
    pools = len(np.unique(groups))
    confusion = np.zeros((classes, classes), dtype=int)
    np.add.at(confusion, (y, predicted), 1)
    upper = np.array(
        [
            m == NO_EFFECT or s >= np.mean(EFFECTS.get(m).prior)
            for m, s in zip((models[k] for k in y), strength, strict=True)
        ]
    )
    in_set = np.array(
        [
            k in credible_set_indices(p) and len(credible_set_indices(p)) <= 2
            for k, p in zip(y, calibrated, strict=True)
        ]
    )
    effects_upper = upper & (y != models.index(NO_EFFECT)) if NO_EFFECT in models else upper
    separations = []
    for a in range(classes):
        for b in range(a + 1, classes):
            both = (y == a) | (y == b)
            mixed = confusion[a, b] + confusion[b, a]
            separations.append(
                dict(
                    pair=[models[a], models[b]],
                    told_apart=float(1 - mixed / max(both.sum(), 1)),
                )
            )
    separations.sort(key=lambda s: s["told_apart"])
    return dict(
        accuracy=float(correct.mean()),
        accuracy_ci95_pools=clopper_pearson(round(correct.mean() * pools), pools),
        accuracy_upper_half=float(correct[upper].mean()) if upper.any() else math.nan,
        identified_upper_half=float(in_set[effects_upper].mean())
        if effects_upper.any()
        else math.nan,
        identified_upper_half_ci95_pools=clopper_pearson(
            round(in_set[effects_upper].mean() * pools * effects_upper.mean()),
            round(pools * effects_upper.mean()),
        )
        if effects_upper.any()
        else [math.nan, math.nan],
        confusion=dict(models=models, counts=confusion.tolist()),
        hardest_pairs=separations[:5],
        expected_calibration_error=expected_calibration_error(calibrated, y),
        expected_calibration_error_votes=expected_calibration_error(votes, y),
        log_loss=float(-np.mean(np.log(np.clip(calibrated[np.arange(len(y)), y], 1e-12, 1)))),
        credible_set_coverage=float(
            np.mean([k in credible_set_indices(p) for k, p in zip(y, calibrated, strict=True)])
        ),
        strength_interval_coverage={m: s.coverage_out_of_fold for m, s in strengths.items()},
        size_curve=curve,
    )


def credible_set_indices(p: np.ndarray) -> list[int]:
    """The indices of the fewest models whose probabilities ``p`` (M,) add up to
    ``CREDIBLE``, most probable first."""
    order = np.argsort(-p)
    total, out = 0.0, []
    for k in order:
        out.append(int(k))
        total += p[k]
        if total >= CREDIBLE - 1e-12:
            break
    return out
