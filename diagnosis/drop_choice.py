"""Which effect, and how far it goes, for a drop experiment with a detected gap: the
amortised model choice (``diagnosis.model_choice``) names the effects with their
posterior probabilities and strengths; a posterior-predictive check of the best one (its
fitted strength simulated afresh, the observed drops tested against it with the same
exact max-T family as the detection) decides between "explained", "partly explained"
and "unexplained"; an out-of-distribution score keeps a cause outside the library from
being "explained".
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from diagnosis.drop_simulations import Dataset, DropSimulations
from diagnosis.drop_where import locate_gap
from diagnosis.model_choice import (
    ModelChoice,
    build_model_choice,
    design_summaries,
    next_experiment,
)
from diagnosis.reference_table import NO_EFFECT, TableStore
from diagnosis.statistics import interval
from diagnosis.verdicts import off_text, percent
from packing.effects import EFFECTS

__all__ = ["choose_effect", "describe_design"]

# Below this out-of-distribution p-value the data look like none of the simulated datasets.
OOD_ALPHA = 0.01


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
) -> tuple[dict, dict]:
    """The "model_choice" section of the report and the verdict."""
    x = sims.x
    first = next(iter(data.values()))
    has_yaw, has_tilt = first.yaw_deg is not None, first.tilt_deg is not None
    drops = {c: d.n for c, d in data.items()}
    choice: ModelChoice = build_model_choice(
        x,
        drops,
        models,
        sims.order,
        has_yaw,
        has_tilt,
        store,
        run_many,
        progress,
        max_pools=x.settings.table_pools,
        seed=seed,
    )
    observed = design_summaries(data, x, sims.order, has_yaw, has_tilt)
    chosen = choice.choose(observed)
    section = dict(chosen, design=choice.checks, design_text="")
    section["design_text"] = describe_design(choice.checks, [c.name for c in x.conditions])
    best = chosen["best_effect"]
    if best is None:  # only "no effect" was a candidate
        verdict = dict(
            kind="unexplained",
            text=f"Gap detected; no candidate effect applies.{off_text(where)}",
        )
        return section, verdict
    check = _predictive_check(sims, full, where, best, chosen, rng)
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


def _fitted_tilt(sims: DropSimulations, chosen: dict, best: str, condition: str) -> float | None:
    tilt = chosen["release_tilts"].get(best)
    return None if tilt is None else float(tilt["tilt_deg"])


def _candidate_strengths(chosen: dict, best: str) -> list[float]:
    entry = chosen["strengths"][best]
    return sorted({round(v, 12) for v in entry["posterior_quantiles"].values()})


def _predictive_check(sims, full, where, best, chosen, rng) -> dict:
    """The observed drops against the best effect at the strength that fits them best:
    the posterior's 10 to 90 % quantiles simulated (the diagnosis's drops per setting,
    the baseline's draws) and the one with the least energy gap summed over the
    conditions kept (the amortised median of a steep effect can sit off its narrow
    valley). Then the detection's exact max-T test against it, and how much of the
    baseline's energy gap the effect closes (bootstrap interval)."""
    tilt = {c: _fitted_tilt(sims, chosen, best, c) for c in full}
    settings = {
        v: {c: sims.setting(c, tilt[c], best, v) for c in full}
        for v in _candidate_strengths(chosen, best)
    }
    sims.ensure([k for keys in settings.values() for k in keys.values()])
    gaps = {
        v: sum(float(sims.energy(full[c], k)[0]) for c, k in keys.items())
        for v, keys in settings.items()
    }
    strength = min(gaps, key=gaps.get)
    keys = settings[strength]
    test = locate_gap(full, sims, rng, sims.x.settings.alpha, keys=keys)
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
        consistent=not test["overall"]["significant"],
        carried_by=test["overall"].get("carried_by"),
        gap_closed=float(closed[0]) if math.isfinite(closed[0]) else None,
        gap_closed_ci95=list(interval(resamples)) if len(resamples) else [None, None],
        where=test,
    )


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
    if check["consistent"]:
        text = (
            f"{best} at {strength} explains the gap: the observed drops are consistent "
            f"with it (posterior-predictive max-T test p = {check['p_value']:.3g}). "
            f"Posterior probabilities: {probable}"
        )
        if len(named) > 1:
            text += (
                f" (the 95 % set: {', '.join(named)}; the next experiment below tells them apart)"
            )
        return dict(kind="explained", text=text + ".")
    still = off_text(check["where"])
    if closes:
        return dict(
            kind="partly explained",
            text=f"{best} ({strength}) is the most probable effect ({probable}) and closes "
            f"{percent(closed)} of the gap [{percent(closed_lo)}, "
            f"{percent(check['gap_closed_ci95'][1])}], but the drops are still not "
            f"consistent with it (p = {check['p_value']:.3g}).{still}",
        )
    return dict(
        kind="unexplained",
        text=f"No candidate effect explains the gap: the most probable, {best} "
        f"({strength}; {probable}), leaves the drops inconsistent with it (p = "
        f"{check['p_value']:.3g}) and closes no significant part of the gap.{still}",
    )


def no_effect_first(section: dict) -> bool:
    return section["most_probable"] == NO_EFFECT
