"""Which effect, and how far it goes, for a drop experiment with a detected gap: the
amortised model choice (``diagnosis.model_choice``) names the effects with their
posterior probabilities and strengths; a posterior-predictive check of the best one (its
fitted strength simulated afresh, the observed drops tested against it with the same
exact max-T family as the detection) decides between "explained", "partly explained"
and "unexplained"; an out-of-distribution score keeps a cause outside the library from
being "explained".
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable

import numpy as np

from chipstack.diagnosis.drop_simulations import Dataset, DropSimulations
from chipstack.diagnosis.drop_where import locate_gap
from chipstack.diagnosis.model import DropData
from chipstack.diagnosis.model_choice import (
    ModelChoice,
    _quiet_parallel,
    build_model_choice,
)
from chipstack.diagnosis.next_experiment import next_experiment
from chipstack.diagnosis.reference_table import (
    NO_EFFECT,
    ReferenceTable,
    TableStore,
    pool_drops_for,
)
from chipstack.diagnosis.statistics import interval
from chipstack.diagnosis.summaries import design_summaries
from chipstack.diagnosis.verdicts import off_text, percent
from chipstack.packing.effects import EFFECTS

__all__ = ["choose_effect", "describe_design", "design_model_choice"]

# A posterior probability of the best effect at least this high lets it be "explained"
# though the exact (uncalibrated) predictive test rejects it.
CONFIDENT = 0.9
# Below this out-of-distribution p-value the data look like none of the simulated datasets.
OOD_ALPHA = 0.01
# The largest 95 % set whose best effect can be said to explain the gap: with more models
# in it the drops do not single the cause out (the study counts an effect identified when
# it is alone or in a set of two).
EXPLAINED_SET = 2


def describe_design(checks: dict, conditions: list[str]) -> str:
    """The design's ceiling in words a process engineer reads."""
    where = ", ".join(conditions)
    lo, hi = checks["accuracy_ci95_pools"]
    text = (
        f"With these conditions ({where}) and this many drops, simulated datasets of a "
        f"known cause are given the right one (out of {len(checks['confusion']['models'])}, "
        f"'no effect' included) {percent(checks['accuracy'])} of the time [{percent(lo)}, "
        f"{percent(hi)}], {percent(checks['accuracy_upper_half'])} when the effect is in "
        "the upper half of its range."
    )
    hard = [p for p in checks["hardest_pairs"] if p["told_apart"] < 0.99]
    if hard:
        pairs = "; ".join(
            f"{a} and {b} are told apart {percent(p['told_apart'])} of the time"
            for p in hard[:3]
            for a, b in [p["pair"]]
        )
        text += f" Hardest: {pairs}."
    else:
        text += " Every pair of candidates is told apart at least 99 % of the time."
    text += (
        " The probabilities are calibrated to within "
        f"{100 * checks['expected_calibration_error']:.1f} points (expected calibration "
        "error on held-out simulated datasets)."
    )
    return text


@_quiet_parallel
def design_model_choice(
    sims: DropSimulations,
    data: dict,
    models: list[str],
    store: TableStore,
    run_many: Callable,
    progress: Callable[[str], None],
    seed: int,
) -> ModelChoice:
    """The experiment's design's trained model choice (from ``store`` when trained
    before; else its reference table simulated and the classifier trained)."""
    first = next(iter(data.values()))
    return build_model_choice(
        sims.x,
        {c: d.n for c, d in data.items()},
        models,
        sims.order,
        first.yaw_deg is not None,
        first.tilt_deg is not None,
        store,
        run_many,
        progress,
        max_pools=sims.x.settings.table_pools,
        seed=seed,
    )


@_quiet_parallel
def learned_detection(choice: ModelChoice, sims: DropSimulations, data: dict) -> dict:
    """The learned test of a gap: the data's posterior probability of "no effect" against
    the same probability of effect-free simulated datasets of the design."""
    first = next(iter(data.values()))
    observed = design_summaries(
        data, sims.x, sims.order, first.yaw_deg is not None, first.tilt_deg is not None
    )
    probability = float(choice.probabilities(observed, data)[choice.models.index(NO_EFFECT)])
    return dict(
        probability_no_effect=probability,
        p_value=choice.detection_p_value(probability),
        null_datasets=len(choice.no_effect_null),
    )


@_quiet_parallel
def choose_effect(
    sims: DropSimulations,
    data: dict,
    full: dict[str, Dataset],
    where: dict,
    models: list[str],
    store: TableStore,
    run_many: Callable,
    progress: Callable[[str], None],
    rng: np.random.Generator,
    seed: int,
    choice: ModelChoice | None = None,
) -> tuple[dict, dict]:
    """The "model_choice" section of the report and the verdict. ``choice``: the design's
    trained model choice when the caller has it (the detection's), else built here."""
    x = sims.x
    first = next(iter(data.values()))
    has_yaw, has_tilt = first.yaw_deg is not None, first.tilt_deg is not None
    drops = {c: d.n for c, d in data.items()}
    if choice is None:
        choice = design_model_choice(sims, data, models, store, run_many, progress, seed)
    observed = design_summaries(data, x, sims.order, has_yaw, has_tilt)
    chosen = choice.choose(observed, data)
    section = dict(chosen, design=choice.checks, design_text="")
    section["design_text"] = describe_design(choice.checks, [c.name for c in x.conditions])
    best = chosen["best_effect"]
    if best is None:  # only "no effect" was a candidate
        verdict = dict(
            kind="unexplained",
            text=f"Gap detected; no candidate effect applies.{off_text(where)}",
        )
        return section, verdict
    table = ReferenceTable(x, [best], store, pool_drops_for(drops))
    table.load()
    check = _predictive_check(sims, full, where, best, chosen, rng, table)
    check.update(
        _calibrated_lack_of_fit(
            sims,
            full,
            best,
            chosen,
            choice,
            table,
            has_yaw,
            has_tilt,
            check["p_value"],
            store,
            rng,
        )
    )
    section["predictive_check"] = check
    verdict = _verdict(section, check, where, x.settings.alpha)
    tied = chosen["credible_set"]
    if len(tied) >= 2 and verdict["kind"] != "unexplained":
        section["next_experiment"] = next_experiment(
            x,
            drops,
            tied,
            choice.checks["pools"],
            sims.order,
            has_yaw,
            has_tilt,
            store,
            run_many,
            progress,
            seed=seed,
        )
    return section, verdict


# The table's pools of the best effect the predictive check tries: those nearest its
# posterior median within the 95 % interval.
CHECK_POOLS = 12  # pools of the best effect within its interval the check fits among
FIT_POOLS = 3  # of which the best-fitting make the predictive sample
CHECK_VERSION = 3  # raised when the check changes (its cached reference is then redone)
MIXTURE_DROPS = 240  # drops per condition of the posterior predictive sample
CALIBRATION_SLICES = 2  # datasets cut from each table pool for the calibrated check
# The reference datasets' tests: their p-values only (to 1 / 200), no intervals.
REFERENCE_PERMUTATIONS = 199


def _table_settings(
    sims, table: ReferenceTable, best: str, entry: dict, rng, skip: int | None = None
) -> dict:
    """The best effect's table pools nearest its posterior median, as simulations of the
    diagnosis (key per condition), with the experiment's measurement noise. They were
    simulated before the data were seen and independently of them."""
    settings = table.settings(best, table.count(best))
    low, high = entry["strength_ci95"]
    nearest = _nearest_pools(settings, entry["strength"], low, high, skip)
    out = {}
    for setting in nearest:
        keys = {}
        for c in sims.x.conditions:
            drops = table.noisy(table.pools[c.name, best][setting.index], rng)
            tilt = c.protocol.tilt_deg if np.isnan(setting.tilt_deg) else setting.tilt_deg
            key = sims.key(c.name, tilt, best, setting.strength, f"T{setting.index}")
            _register(sims, key, DropData(drops[:, :2], drops[:, 2], drops[:, 3]), c.name)
            keys[c.name] = key
        out[setting.strength] = keys
    return out


def _register(sims, key: tuple, data: DropData, condition: str) -> None:
    """Hand the diagnosis's simulations drops made elsewhere (the table's), dropping what
    it had cached for that key."""
    sims.forget(key)
    sims.drops[key] = data
    sims.observables[key] = sims.observe(data, condition)


def _mixture(sims, settings: dict, best: str, median: float, tag: str = "TM") -> dict:
    """Per condition, the drops of the given pools pooled in equal parts (``MIXTURE_DROPS``
    in all): a sample of the posterior predictive distribution."""
    keys = {}
    for c in sims.x.conditions:
        parts = [sims.drops[k[c.name]] for k in settings.values()]
        per = max(1, min(MIXTURE_DROPS // len(parts), *(d.n for d in parts)))
        index = np.arange(per)
        data = DropData(
            np.vstack([d.positions[index] for d in parts]),
            np.concatenate([d.yaw_deg[index] for d in parts]),
            np.concatenate([d.tilt_deg[index] for d in parts]),
        )
        first = next(iter(settings.values()))[c.name]
        key = sims.key(c.name, first[1], best, median, tag)
        _register(sims, key, data, c.name)
        keys[c.name] = key
    return keys


def _predictive_check(sims, full, where, best, chosen, rng, table) -> dict:
    """A posterior-predictive check of the best effect: the observed drops against its
    posterior predictive distribution, sampled by the table's pools of it nearest its
    posterior median within the 95 % interval, pooled in equal parts (a strength's
    uncertainty matters: air drag's landings change abruptly with it). The detection's
    exact max-T test against that sample, and how much of the baseline's energy gap it
    closes (bootstrap interval). The pool with the least energy gap gives the strength
    reported as the best fit. Nothing is simulated: the pools were, once, for the table,
    before the data were seen."""
    settings = _table_settings(sims, table, best, chosen["strengths"][best], rng)
    gaps = _energy_gaps(sims, {c: ds.features for c, ds in full.items()}, settings)
    strength = min(gaps, key=gaps.get)
    fitting = {v: settings[v] for v in sorted(gaps, key=gaps.get)[:FIT_POOLS]}
    keys = _mixture(sims, fitting, best, strength)
    test = locate_gap(full, sims, rng, sims.x.settings.alpha, keys=keys, intervals=False)
    before = sum(sims.energy(ds, sims.baseline(c, None)) for c, ds in full.items())
    after = sum(sims.energy(ds, keys[c]) for c, ds in full.items())
    with np.errstate(divide="ignore", invalid="ignore"):
        closed = np.where(before > 0, 1.0 - after / before, np.nan)
    resamples = closed[1:][np.isfinite(closed[1:])]
    return dict(
        effect=best,
        strength=strength,
        strengths_tried=[dict(strength=v, energy_gap=g) for v, g in gaps.items()],
        p_value=test["overall"]["p_value"],
        exact_test_significant=bool(test["overall"]["significant"]),
        carried_by=test["overall"].get("carried_by"),
        gap_closed=float(closed[0]) if math.isfinite(closed[0]) else None,
        gap_closed_ci95=list(interval(resamples)) if len(resamples) else [None, None],
        where=test,
        keys=keys,  # the simulations it was tested against (taken out of the report)
    )


def _energy_gaps(sims, features: dict[str, np.ndarray], settings: dict) -> dict:
    """Each pool's energy distance to the dataset (standardised features per condition),
    summed over the conditions."""
    gaps = {}
    for v, keys in settings.items():
        total = 0.0
        for c, key in keys.items():
            metric = sims.metric[c]
            pool = metric.apply(sims.raw_features(sims.drops[key], c))
            total += _energy(metric, features[c], pool)
        gaps[v] = total
    return gaps


def _nearest_pools(settings: list, median: float, low: float, high: float, skip=None) -> list:
    inside = [s for s in settings if low <= s.strength <= high and s.index != skip]
    inside = inside or [s for s in settings if s.index != skip]
    return sorted(inside, key=lambda s: abs(s.strength - median))[:CHECK_POOLS]


def _energy(metric, a: np.ndarray, b: np.ndarray) -> float:
    """Energy distance (U-statistic) between standardised feature samples a and b."""
    cross = metric.distances(a, b).sum(axis=0).mean()
    within = []
    for f in (a, b):
        d = metric.distances(f).sum(axis=0)
        n = len(f)
        within.append(d.sum() / (n * (n - 1)))
    return float(2.0 * cross - within[0] - within[1])


def _calibrated_lack_of_fit(
    sims, full, best, chosen, choice, table, has_yaw, has_tilt, p_observed, store, rng
) -> dict:
    """The exact max-T test's p-value of the data against the best effect's posterior
    predictive sample, against the same p-value of datasets truly made by that effect,
    each tested against its own predictive sample: a calibrated posterior-predictive
    p-value (a plain one is not uniform: for an effect whose landings change abruptly
    with its strength, air drag, it rejects the right model; for a smooth one it is
    about uniform). The reference: two datasets cut from every table pool of the effect
    (the design's drops and measurement noise), each judged like the data (its own
    posterior median from its summaries, its predictive sample from the nearest other
    pools). It depends on the design and the effect, not on the data: kept in the table
    store. No simulation."""
    name = f"check{CHECK_VERSION}-{choice.key}-{best.replace(' ', '_')}-{table.count(best)}.json"
    blob = store.load(name)
    if blob is not None:
        reference = np.asarray(json.loads(blob))
    else:
        reference = _reference_p_values(sims, full, best, choice, table, has_yaw, has_tilt, rng)
        store.save(name, json.dumps(reference.tolist()).encode())
    k = len(reference)
    if k == 0:  # pools too short for a dataset of the design: the check has no reference
        raise ValueError(
            f"the reference table's pools hold {table.pool_drops} drops, fewer than a "
            f"dataset of the design ({max(d.data.n for d in full.values())})"
        )
    # Compared at the references' resolution (their tests have fewer permutations).
    floor = 1.0 / (REFERENCE_PERMUTATIONS + 1)
    p = float((1 + np.sum(reference <= max(p_observed, floor) + 1e-12)) / (1 + k))
    return dict(
        calibrated_p_value=p,
        reference_datasets=k,
        reference_p_values_below_alpha=float(np.mean(reference < sims.x.settings.alpha)),
    )


def _reference_p_values(sims, full, best, choice, table, has_yaw, has_tilt, rng) -> np.ndarray:
    x = sims.x
    model = choice.strengths[best]
    settings = table.settings(best, table.count(best))
    noise = np.random.default_rng([sims.seed, 71])
    drops = {c: ds.data.n for c, ds in full.items()}
    out = []
    for setting in settings:
        for part in range(CALIBRATION_SLICES):
            cut = {}
            for c in x.conditions:
                pool = table.pools[c.name, best][setting.index]
                n = drops[c.name]
                # Disjoint slices of the pool, after the drops a predictive sample takes
                # from a pool where the pool is long enough, else from its start (its own
                # test's predictive sample is drawn from the other pools, ``skip``).
                start = MIXTURE_DROPS // FIT_POOLS + part * n
                if MIXTURE_DROPS // FIT_POOLS + CALIBRATION_SLICES * n > len(pool):
                    start = part * n
                if start + n > len(pool):
                    break
                d = table.noisy(pool[start : start + n], noise)
                cut[c.name] = DropData(d[:, :2], d[:, 2], d[:, 3])
            if len(cut) < len(x.conditions):
                continue
            summary = design_summaries(cut, x, sims.order, has_yaw, has_tilt)
            median, low, high = model.predict(summary)
            entry = dict(strength=median, strength_ci95=[low, high])
            settings_near = _table_settings(sims, table, best, entry, noise, skip=setting.index)
            keys = _mixture(sims, settings_near, best, median, tag=f"R{setting.index}")
            reference = {c: Dataset.observe(c, d, sims, rng) for c, d in cut.items()}
            test = locate_gap(
                reference,
                sims,
                rng,
                x.settings.alpha,
                keys=keys,
                permutations=REFERENCE_PERMUTATIONS,
                intervals=False,
            )
            out.append(test["overall"]["p_value"])
    return np.asarray(out)


def _verdict(section: dict, check: dict, where: dict, alpha: float) -> dict:
    best = check["effect"]
    p = section["probabilities"]
    named = [m for m in section["credible_set"]]
    unit = EFFECTS.get(best).unit
    s = section["strengths"][best]
    lo, hi = s["strength_ci95"]
    strength = f"{check['strength']:.3g}{' ' + unit if unit else ''} [{lo:.3g}, {hi:.3g}]"
    probable = ", ".join(f"{m} {percent(p[m])}" for m in named)
    ood = section["out_of_distribution"]["p_value"]
    closed = check["gap_closed"]
    closed_lo = check["gap_closed_ci95"][0]
    closes = closed is not None and closed_lo is not None and closed_lo > 0
    if ood < OOD_ALPHA:
        return dict(
            kind="unexplained",
            text=f"The data look like none of the simulated datasets (out-of-distribution "
            f"p = {ood:.3g}): no candidate effect, at any strength, makes drops like "
            f"these. Closest: {best} ({strength}).{off_text(where)}",
        )
    calibrated = check["calibrated_p_value"]
    still = off_text(check["where"])
    if section["most_probable"] == NO_EFFECT:
        # The detection finds a gap, yet the classifier finds effect-free datasets the
        # likeliest source of drops like these: no candidate is the likelier cause, so
        # none is said to explain it, however well its predictive check fits.
        text = (
            f"The most probable model is no effect ({probable}): the gap is not one a "
            f"candidate effect makes more likely than the simulation without one"
        )
        if closes:
            return dict(
                kind="partly explained",
                text=f"{text}; {best} ({strength}) closes {percent(closed)} of it "
                f"[{percent(closed_lo)}, {percent(check['gap_closed_ci95'][1])}].{still}",
            )
        return dict(kind="unexplained", text=f"{text}.{still}")
    # The exact test against the predictive sample is not calibrated for the strength's
    # uncertainty, and the calibrated one is lenient while the table's strengths are
    # coarse (the effect's own datasets, fitted among 16 pools, often fit badly). So an
    # exact rejection stands unless the classifier is confident: a confident posterior
    # says datasets like these came from that effect (calibrated probabilities); a cause
    # outside the library leaves the probability split over several imitators.
    exact_ok = check["p_value"] >= alpha or p[best] >= CONFIDENT
    singled_out = len(named) <= EXPLAINED_SET
    if calibrated >= alpha and exact_ok and singled_out:
        text = (
            f"{best} at {strength} explains the gap: the drops fit its posterior "
            f"predictive distribution as well as drops it makes do (calibrated "
            f"posterior-predictive p = {calibrated:.3g}). Posterior probabilities: {probable}"
        )
        if len(named) > 1:
            text += (
                f" (the 95 % set: {', '.join(named)}; the next experiment below tells them apart)"
            )
        return dict(kind="explained", text=text + ".")
    if calibrated >= alpha and exact_ok:  # it fits, but so may others: no single cause
        closing = (
            f" and closes {percent(closed)} of the gap [{percent(closed_lo)}, "
            f"{percent(check['gap_closed_ci95'][1])}]"
            if closes
            else ""
        )
        return dict(
            kind="partly explained",
            text=f"{best} ({strength}) is the most probable effect{closing} and its "
            f"predictive check passes (calibrated p = {calibrated:.3g}), but the drops do "
            f"not single it out: the 95 % set holds {len(named)} models ({probable}); the "
            f"next experiment below tells them apart.{still}",
        )
    if closes:
        return dict(
            kind="partly explained",
            text=f"{best} ({strength}) is the most probable effect ({probable}) and closes "
            f"{percent(closed)} of the gap [{percent(closed_lo)}, "
            f"{percent(check['gap_closed_ci95'][1])}], but the drops do not fit it "
            f"(calibrated posterior-predictive p = {calibrated:.3g}; exact test against "
            f"its predictive sample p = {check['p_value']:.3g}).{still}",
        )
    return dict(
        kind="unexplained",
        text=f"No candidate effect explains the gap: the most probable, {best} "
        f"({strength}; {probable}), does not fit the drops (calibrated posterior-predictive "
        f"p = {calibrated:.3g}; exact test p = {check['p_value']:.3g}) and closes no "
        f"significant part of the gap.{still}",
    )
