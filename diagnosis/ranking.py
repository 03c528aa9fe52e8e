"""Bookkeeping both diagnoses (drops, stacks) share between their statistics and the
report: multiplicity-adjusted overall tests and an effect's ranking entry."""

from __future__ import annotations

import numpy as np

from chipstack.diagnosis.statistics import holm, interval
from chipstack.packing.effects import EFFECTS

__all__ = ["adjust_tests", "effect_entry", "held_out_reduction"]


def adjust_tests(tests: list[dict], alpha: float) -> None:
    """Add each condition's Holm-adjusted p-value, whether it is significant, and its
    share of the total excess gap (the gap beyond the null mean)."""
    adjusted = holm([t["p_value"] for t in tests])
    for t, p in zip(tests, adjusted, strict=True):
        t["p_holm"] = p
        t["significant"] = p < alpha
    total = sum(max(t["gap"] - t["null_mean"], 0.0) for t in tests)
    for t in tests:
        t["share_of_gap"] = max(t["gap"] - t["null_mean"], 0.0) / total if total > 0 else 0.0


def effect_entry(
    effect: str,
    fitted: list,
    reduction: np.ndarray,
    closed: np.ndarray,
    folds: list[dict],
) -> dict:
    """An effect's ranking entry. ``fitted`` (strengths) and the arrays hold the estimate
    first, then one value per bootstrap resample (which give the intervals)."""
    e = EFFECTS.get(effect)
    return dict(
        effect=effect,
        parameter=e.parameter,
        unit=e.unit,
        prior=list(e.prior),
        strength=fitted[0],
        strength_ci95=list(interval(fitted[1:])),
        held_out_reduction=float(reduction[0]),
        held_out_reduction_ci95=list(interval(reduction[1:])),
        gap_closed=float(closed[0]),
        gap_closed_ci95=list(interval(closed[1:])),
        folds=folds,
    )


def held_out_reduction(excess: np.ndarray, base_excess: np.ndarray) -> np.ndarray:
    """1 - excess gap with the effect / without, nan where there is no excess to close."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(base_excess > 0, 1 - excess / base_excess, np.nan)
