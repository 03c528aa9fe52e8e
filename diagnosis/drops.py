"""Sim-to-real diagnosis of single-chip drop experiments.

Three questions, answered with numbers and intervals:

1. Where: exact permutation tests, the labels (experiment, simulation) permuted within
   each condition, the same permutations for every statistic. The detection is one
   max-T over a family of standardised statistics: the energy statistics of the whole
   distribution of drops (position, yaw, tilt, all) summed over conditions, each
   observable's standardised difference summed over conditions (a shift in the same
   direction everywhere), and every observable's, ring's and sector's standardised
   difference in every condition. Each condition also gets its energy test (Holm across
   conditions), and every member of the family a Westfall-Young max-T adjusted p-value
   from the same permutations: the observables and regions named beyond the noise, with
   their direction and size, keep the family-wise error at alpha. With the amortised
   method the detection also asks the model choice (``[diagnosis] detection =
   "combined"``, the default): the data's posterior probability of "no effect" against
   effect-free simulated datasets of the design, the two tests joined by Simes's rule.
   Without a significant gap the diagnosis stops there.
2. Which: the refitted baseline (its release tilt range) and every candidate effect,
   each fitted on calibration drops and scored drop by drop on held-out ones (halves of
   every condition's drops, or whole conditions left out: ``[diagnosis] held_out``),
   with the tie set of the best effect.
3. How far: the held-out gap before and after the best effect, per observable, and
   whether the held-out drops are consistent with it.

Simulations are requested in batches through ``run_many(function, list_of_kwargs)``, so
the caller decides where they run (a Dask cluster in the CLI, a loop in tests).

This module runs the three questions in order and assembles the report; the samples
compared live in ``diagnosis.drop_simulations``, question 1 in ``diagnosis.drop_where``,
questions 2 and 3 in ``diagnosis.drop_effects`` and ``diagnosis.drop_adequacy``.
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Callable

import numpy as np

from chipstack.core.schema import Scenario
from chipstack.diagnosis.drop_adequacy import how_far_best
from chipstack.diagnosis.drop_choice import (
    choose_effect,
    design_model_choice,
    learned_detection,
)
from chipstack.diagnosis.drop_effects import EffectRanking, Fold
from chipstack.diagnosis.drop_simulations import TILT_GRID_DEG, Dataset, DropSimulations
from chipstack.diagnosis.drop_where import locate_gap
from chipstack.diagnosis.model import DropData, Experiment
from chipstack.diagnosis.observables import DROP_OBSERVABLES, observable_names
from chipstack.diagnosis.reference_table import NO_EFFECT, MemoryStore, TableStore
from chipstack.diagnosis.verdicts import applicable_effects, effect_verdict, off_text
from chipstack.packing.drop import DropProtocol, simulate_drops

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

    def __init__(
        self,
        experiment: Experiment,
        data: dict[str, DropData],
        run_many,
        seed,
        progress,
        tables: TableStore | None = None,
    ):
        self.x = experiment
        self.settings = experiment.settings
        self.data = data
        self.seed = seed
        self.tables = tables if tables is not None else MemoryStore()
        self.run_many = run_many or _sequential
        self.progress = progress or (lambda message: None)
        first = next(iter(data.values()))
        names = observable_names(first.yaw_deg is not None, first.tilt_deg is not None)
        self.sims = DropSimulations(
            experiment,
            names,
            simulate_condition,
            run_many or _sequential,
            seed,
            progress or (lambda message: None),
            self.tables,
        )
        self.rng = np.random.default_rng([seed, 11])
        self.choice = None  # the design's trained model choice, once the detection has it

    def run(self, detect_only: bool = False) -> dict:
        conditions = [c.name for c in self.x.conditions]
        self.sims.ensure([self.sims.baseline(c, None) for c in conditions])
        for c in conditions:
            self.sims.set_metric(c, self.data[c])
        full = dict(zip(conditions, self._datasets([(c, None) for c in conditions]), strict=True))
        where = locate_gap(full, self.sims, self.rng, self.settings.alpha)
        detection = self._detection(where)
        p = detection["p_value"]
        if not detection["significant"] or detect_only:
            # Nothing (more) to do: no effect is fitted, which keeps an effect-free
            # experiment's diagnosis short.
            if detection["significant"]:
                carried = where["overall"]["carried_by"]
                verdict = dict(
                    kind="gap detected",
                    text=f"Detection p = {p:.3g} ({detection['text']}; largest statistic "
                    f"of the exact test: {carried}); no effect fitted.{off_text(where)}",
                )
            else:
                verdict = dict(
                    kind="no significant gap",
                    text="The experiment is consistent with the baseline simulation: "
                    f"{detection['text']}, detection p = {p:.3g} >= {self.settings.alpha}.",
                )
            return self._report(where, [], full, None, {}, verdict, detection)
        if self.settings.method == "amortised":
            return self._amortised(where, full, detection)
        folds = self._folds(full)
        which = EffectRanking(self.sims, folds, full, self.rng).run()
        how_far = how_far_best(which, folds, self.sims, self.rng)
        return self._report(
            where,
            folds,
            full,
            which,
            how_far,
            self._verdict(where, which, how_far),
            detection,
        )

    @functools.cached_property
    def _candidates(self) -> tuple[list[str], dict[str, str]]:
        """ "No effect" and the applicable effects, and why the others do not apply
        (the detection and the choice both ask)."""
        effects, skipped = applicable_effects(self.x)
        return [NO_EFFECT, *effects], skipped

    def _detection(self, where: dict) -> dict:
        """Whether there is a gap: the exact max-T test alone, or joined with the model
        choice's learned test by Simes's rule (p = min(2 min(p1, p2), max(p1, p2)); a
        valid level under the positive dependence of two tests of the same data; Simes,
        Biometrika 73, 1986), which keeps the family-wise false alarm at alpha."""
        exact = float(where["overall"]["p_value"])
        alpha = self.settings.alpha
        models, _ = self._candidates
        learned = None
        if (
            self.settings.method == "amortised"
            and self.settings.detection == "combined"
            and len(models) > 1
        ):
            self.choice = design_model_choice(
                self.sims, self.data, models, self.tables, self.run_many, self.progress, self.seed
            )
            learned = learned_detection(self.choice, self.sims, self.data)
        if learned is None:
            return dict(
                rule="exact",
                p_value=exact,
                exact_p_value=exact,
                learned=None,
                significant=bool(where["overall"]["significant"]),
                text=f"the exact max-T test gives p = {exact:.3g}",
            )
        q = learned["p_value"]
        p = min(1.0, 2.0 * min(exact, q), max(exact, q))
        return dict(
            rule="simes",
            p_value=p,
            exact_p_value=exact,
            learned=learned,
            significant=bool(p < alpha),
            text=f"the exact max-T test gives p = {exact:.3g} and the learned test (posterior "
            f"probability of no effect {learned['probability_no_effect']:.3g}, against "
            f"{learned['null_datasets']} effect-free simulated datasets) p = {q:.3g}, "
            "joined by Simes's rule",
        )

    def _amortised(self, where: dict, full: dict[str, Dataset], detection: dict) -> dict:
        """Which effect by the amortised model choice, judged by its predictive check."""
        models, skipped = self._candidates
        section, verdict = choose_effect(
            self.sims,
            self.data,
            full,
            where,
            models,
            self.tables,
            self.run_many,
            self.progress,
            self.rng,
            self.seed,
            choice=self.choice,
        )
        section["not_applicable"] = skipped
        gap = [t["condition"] for t in where["tests"] if t["significant"]]
        verdict["text"] = (
            f"Gap in {', '.join(gap) or 'the conditions taken together'}. " + (verdict["text"])
        )
        report = self._report(where, [], full, None, {}, verdict, detection)
        check = section.get("predictive_check")
        if check:
            keys = check.pop("keys")
            for c in full:
                key = keys[c]
                positions = self.sims.drops[key].positions
                report["scatter"][c]["best_effect"] = np.round(positions, 2).tolist()
        report["model_choice"] = section
        return report

    def _report(self, where, folds, full, which, how_far, verdict, detection) -> dict:
        best = which["best"] if which else None
        return {
            "scatter": self._scatter(folds, full, best),
            **self._description(),
            "detection": detection,
            "where": where,
            "which": which,
            "how_far": how_far,
            "verdict": verdict,
        }

    def _datasets(self, parts: list[tuple[str, np.ndarray | None]]) -> list[Dataset]:
        """Datasets of (condition, drop indices or None for all)."""
        return [
            Dataset.observe(c, self._drops(c, index), self.sims, self.rng) for c, index in parts
        ]

    def _drops(self, condition: str, index: np.ndarray | None) -> DropData:
        return self.data[condition] if index is None else self.data[condition].take(index)

    def _folds(self, full: dict[str, Dataset]) -> list[Fold]:
        """Cross-fitting folds. ``held_out = "halves"`` (the default, and always with one
        condition): every condition's drops split in two halves at random; each half of
        every condition calibrates, the other halves are judged. ``"conditions"``: leave
        one condition out, so each fitted model must carry over to a condition it never
        saw (a harder test, and one that punishes effects whose strength is hard to pin
        down from the other conditions, air drag's most of all)."""
        conditions = list(full)
        if self.settings.held_out == "conditions" and len(conditions) > 1:
            return [
                Fold(
                    f"hold out {h}",
                    calibration=[full[c] for c in conditions if c != h],
                    held_out=[full[h]],
                )
                for h in conditions
            ]
        rng = np.random.default_rng([self.seed, 13])
        halves = {}
        for c in conditions:
            order = rng.permutation(full[c].data.n)
            half = len(order) // 2
            halves[c] = (np.sort(order[:half]), np.sort(order[half:]))
        a = self._datasets([(c, halves[c][0]) for c in conditions])
        b = self._datasets([(c, halves[c][1]) for c in conditions])
        every = "" if len(conditions) == 1 else " of every condition"
        return [
            Fold(f"calibrate on half A{every}, judge half B", calibration=a, held_out=b),
            Fold(f"calibrate on half B{every}, judge half A", calibration=b, held_out=a),
        ]

    def _scatter(self, folds: list[Fold], full: dict[str, Dataset], best: str | None) -> dict:
        """Final positions of each held-out condition: experiment, baseline, best effect
        (none when no candidate effect applies)."""
        scatter = {}
        for c in full:
            base = self.sims.drops[self.sims.baseline(c, None)]
            scatter[c] = {
                "experiment": np.round(full[c].data.positions, 2).tolist(),
                "baseline": np.round(base.positions, 2).tolist(),
            }
        for fold in folds:
            for ds in fold.held_out:
                if best is not None and "best_effect" not in scatter[ds.condition]:
                    key = fold.model(self.sims, ds.condition, best)
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
        gap = significant or ["the conditions taken together"]
        refit = which["baseline_refit"]
        # The refit is a candidate like the effects: chosen when the best effect scores
        # significantly worse on the held-out drops and the drops are consistent with it;
        # tied with the best effect, it is named among the indistinguishable.
        if refit["adequate"] and refit["better_than_effects"] and refit["held_out_reduction"] > 0:
            return dict(
                kind="baseline refit",
                text=f"Gap in {', '.join(gap)}; refitting the baseline's release tilt "
                f"({refit['all_conditions_deg']:g} deg) closes it: the held-out drops are "
                "consistent with the refitted baseline.",
            )
        if refit["tied_with_best_effect"]:
            tilt = f"the baseline refit (release tilt {refit['all_conditions_deg']:g} deg)"
            which = dict(which, indistinguishable=[*which["indistinguishable"], tilt])
        return effect_verdict(gap, which, how_far, self.settings.alpha, where)


def diagnose_drops(
    experiment: Experiment,
    data: dict[str, DropData],
    run_many: RunMany | None = None,
    seed: int = 0,
    progress: Callable[[str], None] | None = None,
    detect_only: bool = False,
    tables: TableStore | None = None,
) -> dict:
    """The whole diagnosis of a drop experiment as a JSON-ready dict; with
    ``detect_only``, only the detection and "where" (verdict "gap detected" when there is
    a gap: nothing is fitted). ``tables`` keeps the amortised model choice's reference
    tables and trained models (default: in memory, for this call only)."""
    diagnosis = _DropDiagnosis(experiment, data, run_many, seed, progress, tables)
    return diagnosis.run(detect_only)
