"""What both diagnoses (drops, stacks) share once the effects are ranked: which effects
can act on the chips at all, and the verdict on the best one."""

from __future__ import annotations

import math

import numpy as np

from chipstack.core.errors import InputError
from chipstack.diagnosis.model import Experiment
from chipstack.diagnosis.observables import DROP_OBSERVABLES
from chipstack.diagnosis.statistics import combined_p, holm
from chipstack.packing.effects import EFFECTS, shaped
from chipstack.packing.release import draw_shapes

__all__ = ["applicable_effects", "effect_verdict", "how_far", "off_text", "percent"]


def percent(value: float) -> str:
    """A fraction as a rounded percentage, ``n/a`` when undefined."""
    return "n/a" if value is None or not math.isfinite(value) else f"{100 * value:.0f} %"


def applicable_effects(experiment: Experiment) -> tuple[list[str], dict[str, str]]:
    """Candidate effects that can act on every condition's chips, and why the others
    cannot (a warp needs a flat convex chip, for instance)."""
    scenarios = [c.scenario for c in experiment.conditions if c.scenario is not None]
    scenarios = scenarios or [experiment.scenario]
    shapes = [draw_shapes(s, 1, np.random.default_rng(s.seed))[0] for s in scenarios]
    usable, skipped = [], {}
    for name in experiment.candidate_effects:
        try:
            for shape in shapes:
                shaped(shape, {name: EFFECTS.get(name).prior[1]})
        except InputError as exc:
            skipped[name] = str(exc)
            continue
        usable.append(name)
    return usable, skipped


def effect_verdict(
    significant: list[str], which: dict, how_far: dict, alpha: float, where: dict | None = None
) -> dict:
    """``unexplained`` when the best effect does not close a significant part of the gap
    on held-out data; ``partly explained`` when it closes a significant part but the
    held-out data are still not consistent with it (its adequacy tests, combined over
    the held-out datasets by Fisher's method, are significant: ``_still_off``);
    else ``explained``, with the effects tied with it. An unexplained gap names the
    observables and regions of ``where`` still off (significant after adjustment)."""
    gap = ", ".join(significant)
    off = off_text(where)
    if not which["ranking"]:
        return dict(kind="unexplained", text=f"Gap in {gap}; no candidate effect applies.{off}")
    top = which["ranking"][0]
    lo, hi = top["held_out_reduction_ci95"]
    shown = f"{percent(top['held_out_reduction'])} [{percent(lo)}, {percent(hi)}]"
    if not _closes_significantly(top, alpha):
        # The top of the ranking may be the best on the whole data (drops with the tilt
        # known) while another effect closes a significant part of the held-out gap.
        closing = [e["effect"] for e in which["ranking"] if _closes_significantly(e, alpha)]
        if max(e["gap_closed"] for e in which["ranking"]) <= 0:
            # Every effect then closes nothing: usually each fitted to its neutral
            # strength, the baseline itself, which is no candidate to name.
            text = (
                f"Gap in {gap}; no candidate effect closes any of it on held-out data "
                "(each, at its fitted strength, leaves the held-out gap as large or larger)."
            )
        elif closing:
            text = (
                f"Gap in {gap}; {top['effect']} fits the data best but does not close a "
                f"significant part of it on held-out data ({shown}), where "
                f"{', '.join(closing)} does: the evidence does not single out one effect."
            )
        else:
            text = (
                f"Gap in {gap}; no candidate effect closes a significant part of it on "
                f"held-out data (best: {top['effect']}, {shown})."
            )
        return dict(kind="unexplained", text=text + off)
    others = [e for e in which["indistinguishable"] if e != top["effect"]]
    text = (
        f"Gap in {gap}; {top['effect']} closes {shown} of it on held-out data at "
        f"strength {top['strength']:.3g}{' ' + top['unit'] if top['unit'] else ''}."
    )
    remaining = _still_off(
        how_far.get("conditions", []), alpha, how_far.get("adequacy", {}).get("p_calibrated")
    )
    if others:
        text += f" Indistinguishable from it: {', '.join(others)}."
    if remaining:
        text += (
            f" A significant gap remains after it in {', '.join(remaining)} (the held-out "
            "data against simulations of it at every strength it plausibly has, combined "
            "by Fisher's method and calibrated on pseudo-experiments drawn from it): an "
            "effect outside the library, or more than one, is at work."
        )
        kind = "partly explained"
    else:
        kind = "explained"
    return dict(
        kind=kind,
        effect=top["effect"],
        indistinguishable=others,
        still_off=remaining,
        text=text,
    )


def _closes_significantly(top: dict, alpha: float) -> bool:
    """Whether the best effect closes a significant part of the gap on held-out data: its
    test against the baseline (drops: paired per-drop scores; stacks and containers: the
    bootstrap of the held-out gap closed), Holm-adjusted across the effects."""
    return top["p_better_than_baseline_holm"] < alpha


def off_text(where: dict | None, most: int = 8) -> str:
    """ " Still off: ..." naming the observables (across the conditions, then per
    condition) and regions of ``where`` beyond the noise after adjustment, with their
    direction and size where the rows carry one (at most ``most`` of them), or nothing."""
    if not where:
        return ""
    names = [
        f"{r['observable']} across the conditions{_size(r, r['mean_difference'])}"
        for r in where.get("across_conditions", [])
        if r.get("beyond_noise")
    ]
    names += [
        f"{r['observable']} in {r['condition']}{_size(r, r.get('difference'))}"
        for r in where.get("observables", [])
        if r.get("beyond_noise")
    ]
    names += [
        f"{r['region']} {r['where']} in {r['condition']}"
        + (f" ({100 * r['difference']:+.0f} % of the drops)" if "direction" in r else "")
        for r in where.get("regions", [])
        if r.get("notable")
    ]
    if not names:
        return ""
    more = f" and {len(names) - most} more" if len(names) > most else ""
    return f" Still off: {', '.join(names[:most])}{more}."


def _size(row: dict, difference: float | None) -> str:
    """The signed difference, " (+1.9 mm)", (experiment minus simulation) of a drop
    observable's row, or nothing for rows without a direction."""
    if "direction" not in row or difference is None:
        return ""
    unit = DROP_OBSERVABLES.get(row["observable"], ("",))[0]
    return f" ({difference:+.3g}{' ' + unit if unit else ''})"


def _still_off(conditions: list[dict], alpha: float, overall_p: float | None = None) -> list[str]:
    """The held-out conditions whose gap after the best effect is still beyond the noise
    floor. The adequacy tests of the held-out datasets (``p_after``: a condition may be
    held out in several folds, on disjoint drops) are combined by Fisher's method,
    overall and per condition: the model is inadequate when the overall combination is
    significant, and the conditions named are those whose own combination is, Holm-
    adjusted across conditions (or "the held-out conditions taken together" when the
    evidence is spread over them). Splitting the held-out drops into small tests and
    adjusting for their number would hide a gap that every one of them sees a little of.
    ``overall_p``: the overall combination calibrated by simulation (drops:
    ``drop_adequacy.calibrated_adequacy``), which decides in place of Fisher's."""
    if overall_p is None:
        overall_p = combined_p([row["p_after"] for row in conditions]) if conditions else 1.0
    if not conditions or overall_p >= alpha:
        return []
    names = list(dict.fromkeys(row["condition"] for row in conditions))
    per_condition = [
        combined_p([row["p_after"] for row in conditions if row["condition"] == name])
        for name in names
    ]
    adjusted = holm(per_condition)
    named = sorted(n for n, p in zip(names, adjusted, strict=True) if p < alpha)
    return named or ["the held-out conditions taken together"]


def how_far(best: str, top: dict, rows: list, conditions: list) -> dict:
    """The "how far" section: the best effect's fitted strength and held-out gap closed
    (from its ranking entry ``top``), with the per-observable and per-condition rows."""
    return dict(
        effect=best,
        strength=top["strength"],
        strength_ci95=top["strength_ci95"],
        reduction=top["held_out_reduction"],
        reduction_ci95=top["held_out_reduction_ci95"],
        observables=rows,
        conditions=conditions,
    )
