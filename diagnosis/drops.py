"""Sim-to-real diagnosis of single-chip drop experiments.

Three questions, answered with numbers and intervals:

1. Where: every observable of every condition against the baseline simulation, with a
   bootstrap interval and the simulation's own noise floor; rings and sectors of the
   scatter; an overall test per condition.
2. Which: the baseline's own fitted parameter (the release tilt range) is refitted
   first, then every candidate effect's strength is fitted on calibration conditions
   and scored on held-out conditions (leave one condition out; split halves with one
   condition).
3. How far: the held-out gap before and after the best effect, per observable.

Simulations are requested in batches through ``run_many(function, list_of_kwargs)``, so
the caller decides where they run (a Dask cluster in the CLI, a loop in tests).

This module runs the three questions in order and assembles the report; the samples
compared live in ``diagnosis.drop_simulations``, question 1 in ``diagnosis.drop_where``,
questions 2 and 3 in ``diagnosis.drop_effects``.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import numpy as np

from core.schema import Scenario
from diagnosis.drop_effects import TILT_GRID_DEG, EffectRanking, Fold, how_far_best
from diagnosis.drop_simulations import NOISE_POOL, Dataset, DropSimulations
from diagnosis.drop_where import locate_gap
from diagnosis.observables import DROP_OBSERVABLES, observable_names
from diagnosis.spec import DropData, Experiment
from diagnosis.statistics import holm
from diagnosis.verdicts import effect_verdict
from packing.drop import DropProtocol, simulate_drops

__all__ = ["diagnose_drops", "simulate_condition", "TILT_GRID_DEG"]

log = logging.getLogger(__name__)

RunMany = Callable[[Callable, list[dict]], list]


def _sequential(function: Callable, calls: list[dict]) -> list:
    return [function(**kwargs) for kwargs in calls]


def simulate_condition(
    scenario: Scenario,
    protocol: DropProtocol,
    n: int,
    strengths: dict[str, float],
    seed: int,
    position_sd_mm: float = 0.0,
    angle_sd_deg: float = 0.0,
) -> DropData:
    """``n`` simulated drops as an experiment would record them: the measurement noise
    of the spec added (its draws from ``seed`` too)."""
    sample = simulate_drops(scenario, protocol, n, strengths, seed)
    noise = np.random.default_rng([seed, 7])
    positions = sample.positions + noise.normal(0.0, position_sd_mm, size=(n, 2))
    yaw = sample.yaw_deg + noise.normal(0.0, angle_sd_deg, size=n)
    tilt = np.abs(sample.tilt_deg + noise.normal(0.0, angle_sd_deg, size=n))
    return DropData(positions, yaw, np.minimum(tilt, 180.0 - tilt))


class _DropDiagnosis:
    """One drop diagnosis: its observed datasets and folds, the three questions in order
    (they share one random stream, so the order fixes the draws), and the report."""

    def __init__(self, experiment: Experiment, data: dict[str, DropData], run_many, seed, progress):
        self.x = experiment
        self.settings = experiment.settings
        self.data = data
        self.seed = seed
        first = next(iter(data.values()))
        names = observable_names(first.yaw_deg is not None, first.tilt_deg is not None)
        self.sims = DropSimulations(
            experiment,
            names,
            simulate_condition,
            run_many or _sequential,
            seed,
            progress or (lambda message: None),
        )
        self.rng = np.random.default_rng([seed, 11])

    def run(self) -> dict:
        self._simulate_baselines()
        conditions = [c.name for c in self.x.conditions]
        full = dict(zip(conditions, self._datasets([(c, None) for c in conditions]), strict=True))
        where = locate_gap(full, self.sims, self.rng, self.settings.alpha)
        folds = self._folds(full)
        which = EffectRanking(self.sims, folds, full).run()
        how_far = how_far_best(which, folds, self.sims, self.rng)
        verdict = self._verdict(where, which, how_far)
        return {
            "scatter": self._scatter(folds, full, which["best"]),
            **self._description(),
            "where": where,
            "which": which,
            "how_far": how_far,
            "verdict": verdict,
        }

    def _simulate_baselines(self) -> None:
        """Two independent pools at each condition's own tilt (the second measures the
        simulation's noise), and one at every tilt the refit may choose."""
        keys = []
        for c in self.x.conditions:
            tilt = c.protocol.tilt_deg
            keys += [self.sims.baseline(c.name, tilt), self.sims.baseline(c.name, tilt, NOISE_POOL)]
            keys += [self.sims.baseline(c.name, t) for t in self.sims.tilt_grid]
        self.sims.ensure(keys)

    def _datasets(self, parts: list[tuple[str, np.ndarray | None]]) -> list[Dataset]:
        """Datasets of (condition, drop indices or None for all), calibrated. All are
        resampled before any is calibrated: that order fixes the random draws."""
        datasets = [
            Dataset.observe(c, self._drops(c, index), self.sims, self.rng) for c, index in parts
        ]
        for ds in datasets:
            ds.calibrate(self.sims, self.rng)
        return datasets

    def _drops(self, condition: str, index: np.ndarray | None) -> DropData:
        return self.data[condition] if index is None else self.data[condition].take(index)

    def _folds(self, full: dict[str, Dataset]) -> list[Fold]:
        """Leave one condition out; with a single condition, split its drops in halves."""
        conditions = list(full)
        if len(conditions) > 1:
            return [
                Fold(
                    f"hold out {h}",
                    calibration=[full[c] for c in conditions if c != h],
                    held_out=[full[h]],
                )
                for h in conditions
            ]
        (c,) = conditions
        n = full[c].data.n
        order = np.random.default_rng([self.seed, 13]).permutation(n)
        halves = [np.sort(order[: n // 2]), np.sort(order[n // 2 :])]
        a, b = self._datasets([(c, h) for h in halves])
        return [
            Fold("calibrate on half A, judge half B", calibration=[a], held_out=[b]),
            Fold("calibrate on half B, judge half A", calibration=[b], held_out=[a]),
        ]

    def _scatter(self, folds: list[Fold], full: dict[str, Dataset], best: str | None) -> dict:
        """Final positions of each held-out condition: experiment, baseline, best effect
        (none when no candidate effect applies)."""
        scatter = {}
        for fold in folds:
            for ds in fold.held_out:
                if ds.condition in scatter:
                    continue
                tilt0 = self.x.condition(ds.condition).protocol.tilt_deg
                base = self.sims.drops[self.sims.baseline(ds.condition, tilt0)]
                scatter[ds.condition] = {
                    "experiment": np.round(full[ds.condition].data.positions, 2).tolist(),
                    "baseline": np.round(base.positions, 2).tolist(),
                }
                if best is not None:
                    key = self.sims.setting(ds.condition, fold.tilt, best, fold.chosen[best])
                    positions = self.sims.drops[key].positions
                    scatter[ds.condition]["best_effect"] = np.round(positions, 2).tolist()
        return scatter

    def _description(self) -> dict:
        return {
            "experiment": self.x.name,
            "kind": "drop",
            "conditions": [
                {
                    "name": c.name,
                    "height_mm": c.protocol.height_mm,
                    "yaw_deg": c.protocol.yaw_deg,
                    "tilt_deg": c.protocol.tilt_deg,
                    "drops": self.data[c.name].n,
                }
                for c in self.x.conditions
            ],
            "observables": {
                n: {"unit": DROP_OBSERVABLES[n][0], "meaning": DROP_OBSERVABLES[n][1]}
                for n in self.sims.names
            },
            "simulated_drops_per_setting": self.sims.n,
            "bootstrap": self.settings.bootstrap,
            "seed": self.seed,
        }

    def _verdict(self, where: dict, which: dict, how_far: dict) -> dict:
        significant = [t["condition"] for t in where["tests"] if t["significant"]]
        if not significant:
            return dict(
                kind="no significant gap",
                text="The experiment lies within the simulation's noise floor in every condition "
                f"(overall tests, Holm-adjusted p >= {self.settings.alpha}).",
            )
        refit = which["baseline_refit"]
        held_p = holm([r["p_value"] for r in refit["held_out"]])
        if all(p >= self.settings.alpha for p in held_p) and refit["held_out_excess"] <= 0:
            return dict(
                kind="baseline refit",
                text=f"Gap in {', '.join(significant)}; refitting the baseline's release tilt "
                f"({refit['all_conditions_deg']:g} deg) closes it on held-out conditions.",
            )
        return effect_verdict(significant, which, how_far, self.settings.alpha)


def diagnose_drops(
    experiment: Experiment,
    data: dict[str, DropData],
    run_many: RunMany | None = None,
    seed: int = 0,
    progress: Callable[[str], None] | None = None,
) -> dict:
    """The whole diagnosis of a drop experiment as a JSON-ready dict."""
    return _DropDiagnosis(experiment, data, run_many, seed, progress).run()
