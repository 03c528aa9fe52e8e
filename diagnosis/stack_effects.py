"""Which effect, and how far it goes, for stack and container measurements: every
candidate effect's strength is fitted on each fold's calibration conditions and scored on
its held-out ones, the effects are ranked by the gap they close there, and the best one's
held-out gap is shown before and after, per quantity."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from scipy.stats import chi2

from diagnosis.ranking import effect_entry, held_out_reduction, rank_effects
from diagnosis.statistics import interval
from diagnosis.verdicts import how_far
from packing.effects import EFFECTS

if TYPE_CHECKING:
    from diagnosis.stacks import StackRuns, StackScores

__all__ = ["BOOTSTRAP", "StackEffectRanking", "StackFold", "how_far_best", "stack_folds"]

BOOTSTRAP = 400
# The measurements themselves (None), then every resample.
DRAWS = [None, *range(BOOTSTRAP)]


@dataclass
class StackFold:
    """Conditions to fit on, conditions to judge the fit on, and the strengths fitted."""

    name: str
    calibration: list[str]
    held_out: list[str]
    chosen: dict[str, float] = field(default_factory=dict)


def stack_folds(names: list[str]) -> list[StackFold]:
    """Leave one condition out; a single condition can only be scored in-sample."""
    if len(names) > 1:
        return [
            StackFold(f"hold out {h}", calibration=[c for c in names if c != h], held_out=[h])
            for h in names
        ]
    return [
        StackFold(
            "in-sample (one condition: nothing to hold out)", calibration=names, held_out=names
        )
    ]


def strength_grid(effect: str, grid_points: int, contact) -> list[float]:
    """Strengths tried across the effect's prior, its neutral one included. At most five
    points: every point costs a full set of depositions per condition and repeat."""
    lo, hi = EFFECTS.get(effect).prior
    points = max(3, min(grid_points, 5))
    values = set(np.round(np.linspace(lo, hi, points), 12).tolist())
    values.add(round(EFFECTS.get(effect).neutral(contact), 12))
    return sorted(values)


class StackEffectRanking:
    """The "which" section: every effect's strength fitted per fold on the calibration
    conditions and held, its held-out excess gap over the resamples, and the ranking."""

    def __init__(
        self,
        runs: StackRuns,
        scores: StackScores,
        folds: list[StackFold],
        names: list[str],
        grid_points: int,
    ):
        self.runs = runs
        self.scores = scores
        self.folds = folds
        self.names = names
        self.grid_points = grid_points

    def run(self, effects: list[str], kind: str) -> dict:
        base = np.array(
            [sum(self._excess(f.held_out, None, 0.0, d) for f in self.folds) for d in DRAWS]
        )
        results, closed = {}, {}
        for effect in effects:
            grid = strength_grid(effect, self.grid_points, self.runs.contact)
            held, per_fold = self._score_held_out(effect, grid)
            closed[effect] = base - held
            fitted = self._fit_per_draw(effect, grid)
            reduction = held_out_reduction(held, base)
            results[effect] = effect_entry(effect, fitted, reduction, closed[effect], per_fold)
        ranking = rank_effects(results, closed)
        best = ranking[0] if ranking else None
        tied = [e for e in ranking if results[e]["indistinguishable_from_best"]]
        return dict(
            baseline_refit=dict(
                parameter=f"none: the baseline has no fitted parameter for {kind} scenarios",
                held_out=[],
                held_out_excess=float(base[0]),
                held_out_excess_ci95=list(interval(base[1:])),
            ),
            ranking=[results[e] for e in ranking],
            best=best,
            indistinguishable=tied,
            telling_apart={e: self._separating_quantity(best, e) for e in tied if e != best},
            folds=[f.name for f in self.folds],
        )

    def _excess(self, conditions: list[str], effect, strength: float, draw) -> float:
        """Summed G - 1 over ``conditions`` with ``effect`` at ``strength``."""
        return sum(
            self.scores.gap(c, self.runs.key(c, effect, strength), draw) - 1.0 for c in conditions
        )

    def _score_held_out(self, effect: str, grid: list[float]) -> tuple[np.ndarray, list[dict]]:
        """The held-out excess gap per draw with the strength fitted once on each fold's
        calibration conditions and held; only the held-out data are resampled."""
        held = np.zeros(len(DRAWS))
        per_fold = []
        for fold in self.folds:
            cal = [self._excess(fold.calibration, effect, s, None) for s in grid]
            s = grid[int(np.argmin(cal))]
            for j, d in enumerate(DRAWS):
                held[j] += self._excess(fold.held_out, effect, s, d)
            per_fold.append(dict(fold=fold.name, strength=s))
            fold.chosen[effect] = s
        return held, per_fold

    def _fit_per_draw(self, effect: str, grid: list[float]) -> list[float]:
        """The strength fitted on all conditions, for the measurements and each resample."""
        fitted = []
        for d in DRAWS:
            cal = [self._excess(self.names, effect, s, d) for s in grid]
            fitted.append(grid[int(np.argmin(cal))])
        return fitted

    def _separating_quantity(self, best: str, other: str) -> dict:
        """The held-out quantity whose predictions under the two effects differ most, in
        units of the simulations' standard error."""
        top = dict(z=0.0)
        for fold in self.folds:
            for c in fold.held_out:
                for q in self.scores.data[c]:
                    a, sa, ra = self.runs.moments(self.runs.key(c, best, fold.chosen[best]), q)
                    b, sb, rb = self.runs.moments(self.runs.key(c, other, fold.chosen[other]), q)
                    z = abs(a - b) / max(math.sqrt(sa**2 / ra + sb**2 / rb), 1e-12)
                    if z > top["z"]:
                        top = dict(
                            z=z, observable=q, condition=c, best_predicts=a, other_predicts=b
                        )
        return top


def how_far_best(which: dict, folds: list[StackFold], runs: StackRuns, scores: StackScores) -> dict:
    """The "how far" section: every held-out quantity before and after the best effect
    (at the strength its fold fitted), and each held-out condition's gap."""
    best = which["best"]
    if best is None:
        return {}
    rows, totals = [], []
    for fold in folds:
        s = fold.chosen[best]
        for c in fold.held_out:
            before_key, after_key = runs.key(c, None, 0.0), runs.key(c, best, s)
            before, after = scores.z(c, before_key), scores.z(c, after_key)
            rows += [
                dict(
                    fold=fold.name,
                    condition=c,
                    observable=q,
                    experiment=scores.data[c][q].value,
                    before=runs.moments(before_key, q)[0],
                    after=runs.moments(after_key, q)[0],
                    z_before=before[q],
                    z_after=after[q],
                )
                for q in scores.data[c]
            ]
            totals.append(_gap_before_after(fold.name, c, s, before, after))
    return how_far(best, which["ranking"][0], rows, totals)


def _gap_before_after(fold: str, condition: str, strength: float, before: dict, after: dict):
    g0, g1, k = mean_square(before), mean_square(after), len(before)
    return dict(
        fold=fold,
        condition=condition,
        strength=strength,
        gap_before=g0,
        gap_after=g1,
        null_mean=1.0,
        p_before=float(chi2.sf(g0 * k, k)),
        p_after=float(chi2.sf(g1 * k, k)),
    )


def mean_square(z: dict[str, float]) -> float:
    """G of a condition: the mean squared z of its quantities (about 1 without a gap)."""
    return float(np.mean(np.array(list(z.values())) ** 2))
