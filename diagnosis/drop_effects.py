"""Which effect, and how far it goes, for drop experiments. The baseline's own fitted
parameter (the release tilt range) is refitted first; then every candidate effect's
strength is fitted on each fold's calibration data and scored on its held-out data, the
effects are ranked by the gap they close there, and the best one's held-out gap is shown
before and after, per observable."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from diagnosis.drop_simulations import TILT_GRID_DEG, Dataset, DropSimulations
from diagnosis.ranking import effect_entry, held_out_reduction, rank_effects
from diagnosis.statistics import exceedance_p, gap_statistic, interval
from diagnosis.verdicts import applicable_effects, how_far
from packing.effects import EFFECTS

__all__ = ["TILT_GRID_DEG", "EffectRanking", "Fold", "how_far_best"]


@dataclass
class Fold:
    """Datasets to fit on, datasets to judge the fit on, and what was fitted."""

    name: str
    calibration: list[Dataset]
    held_out: list[Dataset]
    refit_tilt: float = math.nan  # the baseline's tilt refitted on this calibration
    tilt: float | None = None  # the tilt the effects are fitted at (None: each condition's)
    base_gap: np.ndarray | None = None  # (1 + B,) held-out G of the baseline
    chosen: dict[str, float] = field(default_factory=dict)  # effect -> fitted strength


def best_tilt(sims: DropSimulations, datasets: list[Dataset]) -> float:
    """The release tilt of ``sims.tilt_grid`` with the least summed gap over ``datasets``."""
    grid = sims.tilt_grid
    gaps = [sum(sims.gap(ds, sims.baseline(ds.condition, t)) for ds in datasets) for t in grid]
    return float(grid[int(np.argmin(gaps))])


class StrengthGrids:
    """The strengths tried for each effect (simulated for every condition at one release
    tilt) and the gap curves over them."""

    def __init__(
        self,
        sims: DropSimulations,
        effects: list[str],
        conditions: list[str],
        tilt: float | None,
        grid_points: int,
    ):
        self.sims = sims
        self.conditions = conditions
        self.tilt = tilt
        self.grids = {effect: self._coarse(effect, grid_points) for effect in effects}

    def _coarse(self, effect: str, points: int) -> list[float]:
        # The neutral strength is always tried: an effect must be able to do nothing.
        e = EFFECTS.get(effect)
        lo, hi = e.prior
        values = set(np.round(np.linspace(lo, hi, points), 12).tolist())
        values.add(round(e.neutral(self.sims.contact), 12))
        return sorted(values)

    def simulate(self) -> None:
        keys = []
        for effect, grid in self.grids.items():
            keys += [
                self.sims.setting(c, self.tilt, effect, s) for s in grid for c in self.conditions
            ]
        self.sims.ensure(keys)

    def curve(
        self, datasets: list[Dataset], tilt: float, effect: str, grid: list[float] | None = None
    ) -> np.ndarray:
        """G summed over ``datasets``, (strengths, 1 + B): the estimate, then per resample."""
        setting = self.sims.setting
        return np.array(
            [
                sum(self.sims.gaps(ds, setting(ds.condition, tilt, effect, s)) for ds in datasets)
                for s in (self.grids[effect] if grid is None else grid)
            ]
        )

    def refine(self, fits: list[tuple[list[Dataset], float]]) -> None:
        """Add the midpoints on either side of the minimum of every fit (datasets, tilt)
        and simulate them: twice the resolution where it matters, for the cost of a few
        more simulations than the coarse grid."""
        for effect, grid in list(self.grids.items()):
            refined = set(grid)
            for datasets, tilt in fits:
                k = int(self.curve(datasets, tilt, effect, grid)[:, 0].argmin())
                if k > 0:
                    refined.add(round((grid[k - 1] + grid[k]) / 2, 12))
                if k < len(grid) - 1:
                    refined.add(round((grid[k] + grid[k + 1]) / 2, 12))
            self.grids[effect] = sorted(refined)
        self.simulate()


class EffectRanking:
    """The "which" section: refits the baseline's release tilt, fits every applicable
    effect's strength on each fold's calibration data, scores it on the held-out data and
    ranks the effects by the gap they close there."""

    def __init__(self, sims: DropSimulations, folds: list[Fold], full: dict[str, Dataset]):
        self.sims = sims
        self.x = sims.x
        self.folds = folds
        self.conditions = list(full)
        self.everything = list(full.values())
        self.resamples = 1 + self.x.settings.bootstrap

    def run(self) -> dict:
        tilt_all = self._refit_tilt()
        effects, skipped = applicable_effects(self.x)
        if not effects:  # nothing can act on these chips: no ranking, the gap unexplained
            base_excess, base_rows = self._score_baseline()
            return dict(
                baseline_refit=self._baseline_refit(tilt_all, base_rows, base_excess),
                ranking=[],
                not_applicable=skipped,
                folds=[f.name for f in self.folds],
                best=None,
                indistinguishable=[],
                telling_apart={},
            )
        points = self.x.settings.grid_points
        grids = StrengthGrids(self.sims, effects, self.conditions, None, points)
        grids.simulate()
        grids.refine([(f.calibration, f.tilt) for f in self.folds] + [(self.everything, None)])
        base_excess, base_rows = self._score_baseline()
        results, closed = {}, {}
        for effect in effects:
            excess, per_fold = self._score_held_out(effect, grids)
            # The gap closed (absolute, in units of G) is what is tested; the reduction
            # (closed over the baseline's excess) is what is reported.
            closed[effect] = base_excess - excess
            fitted = self._fit_on_everything(effect, grids, None)
            reduction = held_out_reduction(excess, base_excess)
            results[effect] = effect_entry(effect, fitted, reduction, closed[effect], per_fold)
        ranking = rank_effects(results, closed)
        best = ranking[0]
        tied = [e for e in ranking if results[e]["indistinguishable_from_best"]]
        return dict(
            baseline_refit=self._baseline_refit(tilt_all, base_rows, base_excess),
            ranking=[results[e] for e in ranking],
            not_applicable=skipped,
            folds=[f.name for f in self.folds],
            best=best,
            indistinguishable=tied,
            telling_apart={e: self._separating_observation(best, e) for e in tied if e != best},
        )

    def _refit_tilt(self) -> float:
        """The baseline refit is a candidate of its own, judged held out (refitted on each
        fold's calibration conditions). The effects are fitted at the release tilt the
        spec states: fitted on top of a tilt refitted first (on every condition, the
        held-out one included), the tilt absorbed part of an effect's signature and leaked
        the held-out data into the fit."""
        for fold in self.folds:
            fold.refit_tilt = best_tilt(self.sims, fold.calibration)
            fold.tilt = None
        return best_tilt(self.sims, self.everything)

    def _score_baseline(self) -> tuple[np.ndarray, list[dict]]:
        """The baseline's held-out excess gap (1 + B,), and the refitted tilt's rows."""
        base_excess = np.zeros(self.resamples)
        rows = []
        for fold in self.folds:
            held = fold.held_out
            g = sum(self.sims.gaps(ds, self.sims.baseline(ds.condition, fold.tilt)) for ds in held)
            fold.base_gap = g
            base_excess += g - sum(ds.expected_null for ds in held)
            rows += [self._refit_row(fold, ds) for ds in held]
        return base_excess, rows

    def _refit_row(self, fold: Fold, ds: Dataset) -> dict:
        g = self.sims.gap(ds, self.sims.baseline(ds.condition, fold.refit_tilt))
        return dict(
            fold=fold.name,
            condition=ds.condition,
            refit_tilt_deg=fold.refit_tilt,
            gap=g,
            null_mean=ds.expected_null,
            p_value=ds.p_value(g),
        )

    def _score_held_out(self, effect: str, grids: StrengthGrids) -> tuple[np.ndarray, list]:
        """The held-out excess gap (1 + B,) with ``effect`` fitted per fold, and the folds'
        rows. Each fold's strength is fitted once on its calibration data and held; the
        held-out data are resampled (a test-set bootstrap). The fit's own uncertainty is in
        the strength's interval (from refits on resampled data), not in the score."""
        excess = np.zeros(self.resamples)
        per_fold = []
        for fold in self.folds:
            k = int(grids.curve(fold.calibration, fold.tilt, effect)[:, 0].argmin())
            chosen = grids.curve(fold.held_out, fold.tilt, effect)[k]
            excess += chosen - sum(ds.expected_null for ds in fold.held_out)
            strength = grids.grids[effect][k]
            per_fold.append(
                dict(
                    fold=fold.name,
                    strength=strength,
                    held_out_gap=float(chosen[0]),
                    baseline_gap=float(fold.base_gap[0]),
                )
            )
            fold.chosen[effect] = strength
        return excess, per_fold

    def _fit_on_everything(
        self, effect: str, grids: StrengthGrids, tilt: float | None
    ) -> list[float]:
        """The strength fitted on all conditions: the estimate, then one per resample."""
        curve = grids.curve(self.everything, tilt, effect)
        return np.array(grids.grids[effect])[curve.argmin(axis=0)].tolist()

    def _baseline_refit(self, tilt_all: float, rows: list[dict], excess: np.ndarray) -> dict:
        return dict(
            parameter="release tilt range (deg), fitted in the paper",
            grid_deg=list(self.sims.tilt_grid),
            all_conditions_deg=tilt_all,
            held_out=rows,
            held_out_excess=float(excess[0]),
            held_out_excess_ci95=list(interval(excess[1:])),
        )

    def _separating_observation(self, best: str, other: str) -> dict:
        """Where the two effects' held-out predictions differ most, in units of the
        experiment's standard error, and how many drops per condition would separate them
        (two-sided 5 %, power 80 %: |z| = 2.8)."""
        top = dict(z=0.0)
        for fold in self.folds:
            for ds in fold.held_out:
                a = self._prediction(ds, fold, best)
                b = self._prediction(ds, fold, other)
                z = np.abs(a - b) / ds.scale
                k = int(np.argmax(z))
                if z[k] > top["z"]:
                    top = dict(
                        z=float(z[k]),
                        observable=self.sims.names[k],
                        condition=ds.condition,
                        best_predicts=float(a[k]),
                        other_predicts=float(b[k]),
                    )
        n = max(ds.data.n for ds in self.everything)
        if top["z"] > 0:
            top["drops_needed_per_condition"] = int(np.ceil(n * (2.8 / top["z"]) ** 2))
        return top

    def _prediction(self, ds: Dataset, fold: Fold, effect: str) -> np.ndarray:
        key = self.sims.setting(ds.condition, fold.tilt, effect, fold.chosen[effect])
        return self.sims.observables[key]


def how_far_best(
    which: dict, folds: list[Fold], sims: DropSimulations, rng: np.random.Generator
) -> dict:
    """The "how far" section: every held-out observable before and after the best effect
    (at the strength its fold fitted), and each held-out condition's gap, with the
    residual test of the best effect: its gap after against the noise floor of the
    fitted model itself (a second, independent simulation of it), since an effect can
    change the spread of what it predicts (a bouncier chip scatters wider)."""
    best = which["best"]
    if best is None:  # no candidate effect applies (as for stacks)
        return {}
    sims.ensure(
        [
            sims.second_pool(sims.setting(ds.condition, f.tilt, best, f.chosen[best]))
            for f in folds
            for ds in f.held_out
        ]
    )
    rows, totals = [], []
    for fold in folds:
        s = fold.chosen[best]
        for ds in fold.held_out:
            before = sims.observables[sims.baseline(ds.condition, fold.tilt)]
            after = sims.observables[sims.setting(ds.condition, fold.tilt, best, s)]
            z0 = (ds.observed - before) / ds.scale
            z1 = (ds.observed - after) / ds.scale
            rows += [
                dict(
                    fold=fold.name,
                    condition=ds.condition,
                    observable=name,
                    experiment=float(ds.observed[k]),
                    before=float(before[k]),
                    after=float(after[k]),
                    z_before=float(z0[k]),
                    z_after=float(z1[k]),
                )
                for k, name in enumerate(sims.names)
            ]
            key = sims.setting(ds.condition, fold.tilt, best, s)
            scale, null, _ = ds.noise_floor(sims, key, sims.second_pool(key), rng)
            g_model = float(gap_statistic(ds.observed, after, scale))
            gap_before = float(np.mean(z0**2))
            totals.append(
                dict(
                    fold=fold.name,
                    condition=ds.condition,
                    strength=s,
                    gap_before=gap_before,
                    gap_after=float(np.mean(z1**2)),
                    null_mean=ds.expected_null,
                    p_before=ds.p_value(gap_before),
                    residual_gap=g_model,
                    residual_null_mean=float(null.mean()),
                    p_after=exceedance_p(null, g_model),
                )
            )
    return how_far(best, which["ranking"][0], rows, totals)
