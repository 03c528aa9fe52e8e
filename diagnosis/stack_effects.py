"""Which effect, and how far it goes, for stack and container measurements: every
candidate effect's strength is fitted on each fold's calibration conditions, simulated at
that strength and scored on its held-out ones; the effects are ranked by the gap they
close there, with the tie set of the best; and the best one's held-out gap is shown
before and after, per quantity, with the adequacy test that "explained" needs."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from chipstack.diagnosis.ranking import effect_entry, held_out_reduction
from chipstack.diagnosis.statistics import bootstrap_p, holm, interval
from chipstack.diagnosis.strength_fit import STRENGTH_RESOLUTION, vertex, within
from chipstack.diagnosis.verdicts import how_far
from chipstack.packing.effects import EFFECTS

if TYPE_CHECKING:
    from chipstack.diagnosis.stacks import StackRuns, StackScores

__all__ = ["BOOTSTRAP", "StackEffectRanking", "StackFold", "how_far_best", "stack_folds"]

BOOTSTRAP = 400


@dataclass
class StackFold:
    """Conditions to fit on, conditions to judge the fit on, and the strengths fitted."""

    name: str
    calibration: list[str]
    held_out: list[str]
    chosen: dict[str, float] = field(default_factory=dict)
    # effect -> the grid's strengths within the fold's 95 % interval (adequacy).
    plausible: dict[str, list[float]] = field(default_factory=dict)


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
    conditions (vertex of the discrepancy over the grid), simulated there and scored on
    the held-out conditions over the resamples; the ranking and the tie set."""

    def __init__(
        self,
        runs: StackRuns,
        scores: StackScores,
        folds: list[StackFold],
        names: list[str],
        grid_points: int,
        alpha: float,
    ):
        self.runs = runs
        self.scores = scores
        self.folds = folds
        self.names = names
        self.grid_points = grid_points
        self.alpha = alpha

    def run(self, effects: list[str], kind: str) -> dict:
        grids = {e: strength_grid(e, self.grid_points, self.runs.contact) for e in effects}
        for fold in self.folds:
            for effect in effects:
                fitted = self._fit(fold.calibration, effect, grids[effect])
                fold.chosen[effect] = float(fitted[0])
                fold.plausible[effect] = within(grids[effect], fitted)
        # The fitted strengths lie between grid points: simulate them, in one batch.
        self.runs.ensure(
            [
                self.runs.key(c, e, f.chosen[e])
                for f in self.folds
                for e in effects
                for c in f.held_out
            ]
        )
        base = self._held_out(lambda c, fold: self.runs.key(c, None, 0.0))
        results, held = {}, {}
        for effect in effects:
            held[effect] = self._held_out(
                lambda c, fold, e=effect: self.runs.key(c, e, fold.chosen[e])
            )
            closed = base - held[effect]
            per_fold = [dict(fold=f.name, strength=f.chosen[effect]) for f in self.folds]
            fitted = self._fit(self.names, effect, grids[effect]).tolist()
            results[effect] = effect_entry(
                effect, fitted, held_out_reduction(held[effect], base), closed, per_fold
            )
            results[effect]["p_better_than_baseline"] = bootstrap_p(closed[1:])
        # Holm across the effects: the best is chosen on the same held-out measurements.
        raw = [results[e]["p_better_than_baseline"] for e in effects]
        for effect, p in zip(effects, holm(raw), strict=True):
            results[effect]["p_better_than_baseline_holm"] = float(p)
        ranking = sorted(effects, key=lambda e: -results[e]["gap_closed"])
        if ranking:
            self._tie_set(ranking, results, held)
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
            tie_set_size=len(tied),
            telling_apart={e: self._separating_quantity(best, e) for e in tied if e != best},
            folds=[f.name for f in self.folds],
        )

    def _excess(self, conditions: list[str], key_of) -> np.ndarray:
        """Summed G - 1 over ``conditions``, each against the setting ``key_of(c)``, for
        the measurements and every resample (1 + B,)."""
        return sum(self.scores.gap(c, key_of(c)) - 1.0 for c in conditions)

    def _fit(self, conditions: list[str], effect: str, grid: list[float]) -> np.ndarray:
        """The strength fitted on ``conditions``: the vertex of the summed discrepancy
        over the grid for the measurements, then for every resample (1 + B,), so that its
        interval carries the noise of the measurements and of the simulations."""
        curve = np.array(
            [self._excess(conditions, lambda c, s=s: self.runs.key(c, effect, s)) for s in grid]
        )
        lo, hi = EFFECTS.get(effect).prior
        return vertex(grid, curve, STRENGTH_RESOLUTION * (hi - lo))

    def _held_out(self, key_of) -> np.ndarray:
        """The held-out excess gap summed over the folds, for every draw (1 + B,): the
        model's setting ``key_of(condition, fold)`` is fitted once on the measurements and
        held; the held-out measurements and simulations are resampled."""
        return sum(
            self._excess(fold.held_out, lambda c, f=fold: key_of(c, f)) for fold in self.folds
        )

    def _tie_set(self, ranking: list[str], results: dict, held: dict[str, np.ndarray]) -> None:
        """Each effect's one-sided bootstrap test of "worse than the best" on the held-out
        excess, Holm-adjusted across the effects: those not significantly worse are tied
        with the best."""
        best, others = ranking[0], ranking[1:]
        raw = [bootstrap_p(held[e][1:] - held[best][1:]) for e in others]
        results[best]["p_worse_than_best"] = 1.0
        results[best]["indistinguishable_from_best"] = True
        for effect, p in zip(others, holm(raw) if raw else [], strict=True):
            results[effect]["p_worse_than_best"] = float(p)
            results[effect]["indistinguishable_from_best"] = bool(p >= self.alpha)

    def _separating_quantity(self, best: str, other: str) -> dict:
        """The held-out quantity whose predictions under the two effects differ most, in
        units of the standard error of a measured quantity against one of them (the
        scale of the scores)."""
        top = dict(z=0.0)
        for fold in self.folds:
            for c in fold.held_out:
                a_key = self.runs.key(c, best, fold.chosen[best])
                b_key = self.runs.key(c, other, fold.chosen[other])
                for q in self.scores.data[c]:
                    a, b = self.scores.mean(c, a_key, q), self.scores.mean(c, b_key, q)
                    z = abs(float(self.scores.t(c, a_key, q)[0] - self.scores.t(c, b_key, q)[0]))
                    if z > top["z"]:
                        top = dict(
                            z=z, observable=q, condition=c, best_predicts=a, other_predicts=b
                        )
        return top


def how_far_best(which: dict, folds: list[StackFold], runs: StackRuns, scores: StackScores) -> dict:
    """The "how far" section: every held-out quantity before and after the best effect
    (at the strength its fold fitted), and each held-out condition's gap with the
    adequacy test of the best effect: the measurements' test against the simulations at
    the fitted strength and at every grid strength within the fold's 95 % interval, the
    largest p-value (Berger and Boos's supremum over a confidence set, as for drops)."""
    best = which.get("best")
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
                    before=scores.mean(c, before_key, q),
                    after=scores.mean(c, after_key, q),
                    z_before=before[q],
                    z_after=after[q],
                )
                for q in scores.data[c]
            ]
            tested = [s, *(v for v in fold.plausible.get(best, []) if v != s)]
            p = [scores.test(c, runs.key(c, best, v)) for v in tested]
            k = int(np.argmax(p))
            totals.append(
                dict(
                    fold=fold.name,
                    condition=c,
                    strength=s,
                    gap_before=mean_square(before),
                    gap_after=mean_square(after),
                    null_mean=1.0,
                    p_before=scores.test(c, before_key),
                    p_after=p[k],
                    p_after_at_fitted=p[0],
                    most_consistent_strength=tested[k],
                )
            )
    return how_far(best, which["ranking"][0], rows, totals)


def mean_square(z: dict[str, float]) -> float:
    """G of a condition: the mean squared z of its quantities (about 1 without a gap)."""
    return float(np.mean(np.array(list(z.values())) ** 2))
