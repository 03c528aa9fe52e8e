"""The diagnosis report: ``diagnosis.json`` (everything), ``diagnosis.md`` (for people)
and figures: the scatter of every condition (experiment, baseline, best effect), the
discrepancy of every observable against the noise floor, and the ranking of effects."""

from __future__ import annotations

import math

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from chipstack.diagnosis.drop_separation import MOST_DROPS
from chipstack.diagnosis.spec import EXPERIMENT_KINDS
from chipstack.diagnosis.verdicts import percent

__all__ = ["write_diagnosis", "report_markdown"]


def _fmt(value, digits: int = 3) -> str:
    if value is None:
        return "-"
    if isinstance(value, float) and math.isnan(value):
        return "n/a"
    if isinstance(value, float):
        return f"{value:.{digits}g}"  # an unbounded interval's end prints as inf
    return str(value)


def report_markdown(result: dict) -> str:
    """The report as Markdown."""
    lines = _summary(result)
    drop = EXPERIMENT_KINDS.get(result["kind"]).replicated_drops
    lines += _where_section(result["where"], drop, result.get("detection"))
    if result.get("model_choice"):
        lines += _model_choice_section(result["model_choice"])
    else:
        lines += _which_section(
            result["which"], no_gap=result["verdict"]["kind"] == "no significant gap"
        )
    lines += _how_far_section(result.get("how_far") or {}, drop)
    return "\n".join(lines) + "\n"


def _summary(result: dict) -> list[str]:
    return [
        f"# Sim-to-real diagnosis: {result['experiment']}",
        "",
        f"**Verdict ({result['verdict']['kind']}).** {result['verdict']['text']}",
        "",
        f"Kind `{result['kind']}`, seed {result['seed']}, "
        f"{_fmt(result.get('wall_time_s', float('nan')))} s.",
        "",
    ]


def _interval(pair, show=_fmt) -> str:
    return f"[{show(pair[0])}, {show(pair[1])}]"


# -- 1. where --------------------------------------------------------------------------
def _where_section(where: dict, drop: bool, detection: dict | None = None) -> list[str]:
    lines = ["## 1. Where the gap lies", ""]
    if detection and detection.get("rule") == "simes":
        learned = detection["learned"]
        lines += [
            f"Detection: p = {_fmt(detection['p_value'])}, {detection['text']}. The learned "
            'test asks the model choice (section 2) how probable "no effect" is for these '
            "drops; a probability as low as theirs in "
            f"{_fmt(100 * learned['p_value'])} % of effect-free simulated datasets of the "
            "design. It finds effects the observables below miss; where the gap lies is "
            "told by the exact test's family.",
            "",
        ]
    if "overall" in where:
        o = where["overall"]
        if "family_size" in o:
            lines += [
                "Overall test (the detection): one max-T over a family of "
                f"{o['family_size']} standardised statistics, against their exact "
                f"permutation null ({o['permutations']} label permutations within each "
                "condition, the same for every statistic): the energy statistics of the "
                "experiment's drops (position, yaw over the chip's symmetry, tilt, all) "
                "against the baseline simulation's, summed over conditions; every "
                "observable's difference summed over the conditions; every observable's, "
                "ring's and sector's difference in every condition. Largest statistic "
                f"{_fmt(o['statistic'])} ({o['carried_by']}), null mean "
                f"{_fmt(o['null_mean'])}, p = {_fmt(o['p_value'])}.",
                "",
            ]
        else:
            lines += [
                "Overall test (the detection): the energy distance of the experiment's "
                "drops to the baseline simulation's, summed over conditions, against its "
                f"exact permutation null ({o['permutations']} label permutations within "
                f"each condition): statistic {_fmt(o['statistic'])}, null mean "
                f"{_fmt(o['null_mean'])}, p = {_fmt(o['p_value'])}.",
                "",
            ]
    return lines + [
        *_tests_table(where["tests"], drop),
        *_across_table(where.get("across_conditions")),
        *_observables_table(where["observables"], drop),
        *_regions(where.get("regions")),
    ]


def _across_table(rows: list[dict] | None) -> list[str]:
    """The observables off in the same direction across the conditions (drops)."""
    if rows is None:
        return []
    off = sorted((r for r in rows if r["beyond_noise"]), key=lambda r: r["p_adjusted"])
    return _flagged(
        "Every observable across the conditions (its z-scores summed over the conditions: "
        "a shift in the same direction everywhere) with its max-T adjusted p-value (the "
        "same family as the detection); beyond the noise:",
        "| observable | mean difference | z | p (max-T) |",
        [
            f"| {r['observable']} | {_fmt(r['mean_difference'])} | {_fmt(r['z'], 2)} "
            f"| {_fmt(r['p_adjusted'])} |"
            for r in off
        ],
    )


def _flagged(about: str, header: str, rows: list[str]) -> list[str]:
    """A paragraph, then the table of the rows it flags, or "none."."""
    lines = ["", about, ""]
    if not rows:
        return lines + ["none."]
    return lines + [header, "|" + "---|" * header.count(" | ") + "---|", *rows]


def _tests_table(tests: list[dict], drop: bool) -> list[str]:
    if drop:
        about = (
            "Test per condition: the energy statistic of its drops against the same "
            "permutations (exact), Holm-adjusted across conditions."
        )
    else:
        about = (
            "Test per condition: Welch's t of every measured quantity against the "
            "baseline's repeats, the smallest p-value Bonferroni-adjusted over the "
            "condition's quantities (valid however they correlate); Holm-adjusted across "
            "conditions. G, the mean squared t (about 1 when there is no gap), shows the "
            "size of the gap."
        )
    lines = [
        about,
        "",
        f"| condition | {'energy' if drop else 'G'} | null mean | p | p (Holm) | significant "
        "| share of the gap |",
        "|---|---|---|---|---|---|---|",
    ]
    for t in tests:
        lines.append(
            f"| {t['condition']} | {_fmt(t['gap'])} "
            f"| {_fmt(t['null_mean'])} | {_fmt(t['p_value'])} "
            f"| {_fmt(t['p_holm'])} | {'yes' if t['significant'] else 'no'} "
            f"| {percent(t['share_of_gap'])} |"
        )
    return lines


def _observables_table(rows: list[dict], drop: bool) -> list[str]:
    if drop:
        about = (
            "Every observable: experiment minus simulation, its bootstrap 95 % interval "
            "(both samples resampled), the noise floor (95 % of |difference| under the "
            "permutations) and its max-T adjusted p-value (Westfall-Young, step-down, in "
            "the family of the detection: every observable, ring and sector of every "
            "condition and the sums across conditions). Starred rows are significant "
            "after that adjustment."
        )
    else:
        about = (
            "Every quantity: experiment minus simulation, its 95 % interval (1.96 times "
            "the standard error of the difference: the measurement's and the simulated "
            "mean's), that margin as the noise floor, Welch's t and its p-value, "
            "Holm-adjusted across every quantity of every condition. Starred rows are "
            "significant after that adjustment."
        )
    lines = [
        "",
        about,
        "",
        "| condition | observable | experiment | simulation | difference | 95 % interval | "
        f"noise floor | z | p ({'max-T' if drop else 'Holm'}) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    adjusted = "p_adjusted" if drop else "p_holm"
    for r in rows:
        star = " *" if r["beyond_noise"] else ""
        lines.append(
            f"| {r['condition']} | {r['observable']}{star} | {_fmt(r['experiment'])} | "
            f"{_fmt(r['simulation'])} | {_fmt(r['difference'])} | {_interval(r['ci95'])} | "
            f"{_fmt(r['noise_floor'])} | {_fmt(r['z'], 2)} | {_fmt(r[adjusted])} |"
        )
    return lines


def _regions(regions: list[dict] | None) -> list[str]:
    if not regions:
        return []
    return _flagged(
        "Regions of the scatter (rings by the pooled drops' distance quantiles, 45-degree "
        "sectors) whose share of drops differs significantly (permutation p-values, "
        "adjusted in one family with the observables):",
        "| condition | region | experiment share | simulation share | z |",
        [
            f"| {r['condition']} | {r['region']} {r['where']} "
            f"| {percent(r['experiment_share'])} | "
            f"{percent(r['simulation_share'])} | {_fmt(r['z'], 2)} |"
            for r in regions
            if r["notable"]
        ],
    )


# -- 2. which --------------------------------------------------------------------------
def _model_choice_section(choice: dict) -> list[str]:
    """The amortised model choice: probabilities, strengths, the design's ceiling, the
    predictive check and the next experiment."""
    lines = ["", "## 2. Which effect", ""]
    lines += [
        "A classifier trained on simulated datasets of this experiment's design (every "
        "candidate effect with strengths drawn over its prior, and no effect) gives each "
        "its posterior probability; the 95 % set is the fewest that hold 95 % of it.",
        "",
        choice["design_text"],
        "",
        "| model | probability | strength | 95 % interval |",
        "|---|---|---|---|",
    ]
    strengths = choice["strengths"]
    for name, p in sorted(choice["probabilities"].items(), key=lambda item: -item[1]):
        s = strengths.get(name)
        shown = (_fmt(s["strength"]), _interval(s["strength_ci95"])) if s else ("-", "-")
        lines.append(f"| {name} | {percent(p)} | {shown[0]} | {shown[1]} |")
    lines += ["", f"95 % set: {', '.join(choice['credible_set'])}."]
    ood = choice["out_of_distribution"]
    lines.append(
        f"Out-of-distribution p = {_fmt(ood['p_value'])} (the share of simulated datasets "
        "lying at least as far from the rest of the table as the observed one)."
    )
    check = choice.get("predictive_check")
    if check:
        closed = check["gap_closed_ci95"]
        lines += [
            "",
            f"Posterior-predictive check of {check['effect']} (best-fitting strength "
            f"{_fmt(check['strength'])}): the drops' lack of fit to its posterior "
            f"predictive sample, against that of {check['reference_datasets']} datasets it "
            f"made itself, calibrated p = {_fmt(check['calibrated_p_value'])}; the "
            f"detection's exact max-T test against the same sample p = "
            f"{_fmt(check['p_value'])} (not calibrated for the strength's uncertainty); the "
            f"sample closes {percent(check['gap_closed'])} {_interval(closed, percent)} of "
            "the baseline's energy gap.",
        ]
    nxt = choice.get("next_experiment")
    if nxt:
        lines += ["", nxt["text"]]
    for name, why in choice.get("not_applicable", {}).items():
        lines.append(f"\n{name}: not applicable ({why}).")
    return lines


def _which_section(which: dict, no_gap: bool) -> list[str]:
    lines = ["", "## 2. Which effect", ""]
    if which is None:
        return lines + ["Nothing was fitted (see the verdict)."]
    if no_gap:
        lines += ["There is no significant gap to explain: what follows is for reference only.", ""]
    lines += _baseline_refit(which["baseline_refit"])
    lines += _ranking_table(which)
    for name, why in which.get("not_applicable", {}).items():
        lines.append(f"\n{name}: not applicable ({why}).")
    return lines + _telling_apart(which)


def _baseline_refit(refit: dict) -> list[str]:
    lines = [f"Baseline refit first: {refit['parameter']}."]
    if "all_conditions_deg" in refit:  # only drops have a fitted baseline parameter
        lines.append(f"Refitted on all conditions: {refit['all_conditions_deg']:g} deg; per fold:")
        lines += [
            f"- {h['fold']}, {h['condition']}: {h['refit_tilt_deg']:g} deg, held-out energy "
            f"distance {_fmt(h['gap'])}, consistency test p {_fmt(h['p_value'])} "
            f"(most consistent tilt {_fmt(h['most_consistent_tilt_deg'])} deg; at the "
            f"refitted tilt alone p {_fmt(h['p_at_refit_tilt'])})"
            for h in refit["held_out"]
        ]
        return lines + [
            "",
            f"Held-out energy distance of the refitted baseline: "
            f"{_fmt(refit['held_out_excess'])} {_interval(refit['held_out_excess_ci95'])}; "
            f"reduction {percent(refit['held_out_reduction'])}; the held-out drops are "
            f"{'' if refit['adequate'] else 'not '}consistent with it (Fisher's "
            f"combination of the consistency tests: p {_fmt(refit['adequacy_p'])}).",
        ]
    return lines + [
        "",
        f"Held-out excess gap of the refitted baseline: {_fmt(refit['held_out_excess'])} "
        f"{_interval(refit['held_out_excess_ci95'])}.",
    ]


def _ranking_table(which: dict) -> list[str]:
    if not which["ranking"]:
        return ["", "No candidate effect can act on these chips: nothing is fitted or ranked."]
    folds = ", ".join(which.get("folds", [])) or "leave one condition out"
    in_sample = "discrepancy" in which["ranking"][0]
    if in_sample:
        about = (
            "Effects fitted on all the drops and ranked by the discrepancy left at the "
            "fitted strength (energy distance summed over the conditions, about 0 for the "
            "right model); tied: not significantly worse than the best (bootstrap of the "
            "drops, observed and simulated, each resample refitted). The held-out "
            f"reduction is each effect fitted on calibration conditions and scored on "
            f"held-out ones ({folds}): 1 - excess gap with the effect / without."
        )
    else:
        about = (
            f"Effects fitted on calibration conditions, scored on held-out ones ({folds}); "
            "ranked by the held-out gap reduction (1 - excess gap with the effect / without)."
        )
    lines = [
        "",
        about,
        "",
        "| rank | effect | fitted strength | 95 % interval | "
        + ("discrepancy left | 95 % interval | " if in_sample else "")
        + "held-out reduction | 95 % interval | indistinguishable from the best |",
        "|---|---|---|---|" + ("---|---|" if in_sample else "") + "---|---|---|",
    ]
    for k, e in enumerate(which["ranking"], 1):
        left = (
            f"{_fmt(e['discrepancy'])} | {_interval(e['discrepancy_ci95'])} | " if in_sample else ""
        )
        lines.append(
            f"| {k} | {e['effect']} | {_fmt(e['strength'])} {e['unit']} "
            f"| {_interval(e['strength_ci95'])} | {left}{percent(e['held_out_reduction'])} | "
            f"{_interval(e['held_out_reduction_ci95'], percent)} | "
            f"{'yes' if e['indistinguishable_from_best'] else 'no'} |"
        )
    return lines


def _telling_apart(which: dict) -> list[str]:
    if not which["telling_apart"]:
        return []
    lines = ["", "What would tell the indistinguishable effects apart from the best:", ""]
    for name, t in which["telling_apart"].items():
        if t.get("z", 0) <= 0:
            lines.append(f"- {name}: no measured observable separates them.")
            continue
        extra = (
            f"; about {t['drops_needed_per_condition']} drops per condition would separate them"
            if "drops_needed_per_condition" in t
            else ""
        )
        lines.append(
            f"- {name}: {t['observable']} in {t['condition']} ({which['best']} predicts "
            f"{_fmt(t['best_predicts'])}, {name} {_fmt(t['other_predicts'])}, "
            f"{_fmt(t['z'], 2)} standard errors apart{extra})."
        )
        release = t.get("release")
        if release:
            needed = release["drops_needed_per_condition"]
            lines.append(
                f"  A new condition would separate them best at {_fmt(release['height_mm'])} mm, "
                f"yaw {_fmt(release['yaw_deg'])} deg, tilt {_fmt(release['tilt_deg'])} deg: "
                + (f"about {needed} drops." if needed else "no candidate release separates them.")
            )
    joint = which.get("next_experiment")
    if joint:
        needed = joint["drops_needed_per_condition"]
        where = (
            f"{_fmt(joint['height_mm'])} mm, yaw {_fmt(joint['yaw_deg'])} deg, "
            f"tilt {_fmt(joint['tilt_deg'])} deg"
        )
        lines += [
            "",
            (
                f"Next experiment: one new condition at {where}, {needed} drops; with them "
                f"the paired test on the held-out drops' scores (Bonferroni over the tied "
                f"effects) would "
                f"tell {which['best']} from {', '.join(joint['separates'])} with probability "
                f"about {percent(joint['power'])} if the effects keep their fitted strengths "
                "(a lower bound on the drops: the strengths are refitted, and the tie test "
                "also carries the simulations' noise)."
            )
            if needed
            else (
                f"Next experiment: no candidate release tells {which['best']} from "
                f"{', '.join(joint['separates'])} within {MOST_DROPS} drops by the tie test; "
                "closest at " + where + "."
            ),
        ]
    return lines


# -- 3. how far ------------------------------------------------------------------------
def _calibration_text(adequacy: dict | None) -> str:
    """The adequacy combination and its calibration by simulation (drops), or "."."""
    if not adequacy or adequacy.get("p_calibrated") is None:
        return "."
    return (
        f" (calibrated by simulation: Fisher's p = {_fmt(adequacy['p_combined'])} is as "
        f"small or smaller in a share {_fmt(adequacy['p_calibrated'])} of "
        f"{adequacy['replicates']} pseudo-experiments drawn from the fitted model itself, "
        "the p-value that decides)."
    )


def _how_far_section(how: dict, drop: bool) -> list[str]:
    if not how:
        return []
    gap = "energy distance" if drop else "G"
    return [
        "",
        "## 3. How far the best effect closes the gap",
        "",
        f"{how['effect']} at {_fmt(how['strength'])} {_interval(how['strength_ci95'])}: "
        f"held-out reduction {percent(how['reduction'])} "
        f"{_interval(how['reduction_ci95'], percent)}.",
        "",
        f"| fold | held-out condition | strength | {gap} before | {gap} after | p before "
        "| p after | most consistent strength |",
        "|---|---|---|---|---|---|---|---|",
        *(
            f"| {c.get('fold', '')} | {c['condition']} | {_fmt(c['strength'])} "
            f"| {_fmt(c['gap_before'])} | {_fmt(c['gap_after'])} | "
            f"{_fmt(c['p_before'])} | {_fmt(c['p_after'])} "
            f"| {_fmt(c.get('most_consistent_strength', c['strength']))} |"
            for c in how["conditions"]
        ),
        "",
        (
            "p after: the held-out drops against independent simulations of the effect at "
            "every strength within the fold's 95 % interval"
            if drop
            else "p after: the held-out measurements against the simulations of the effect "
            "at the fitted strength and at every grid strength within the fold's 95 % "
            "interval (the test of section 1, on the grid's repeats)"
        )
        + ", the largest p-value (the strength it was largest at is the most consistent "
        "one); the model is adequate when Fisher's combination of them is not significant"
        + _calibration_text(how.get("adequacy")),
        "",
        "| fold | held-out condition | observable | experiment | before | after | z before "
        "| z after |",
        "|---|---|---|---|---|---|---|---|",
        *(
            f"| {r.get('fold', '')} | {r['condition']} | {r['observable']} "
            f"| {_fmt(r['experiment'])} | {_fmt(r['before'])} | "
            f"{_fmt(r['after'])} | {_fmt(r['z_before'], 2)} | {_fmt(r['z_after'], 2)} |"
            for r in how["observables"]
        ),
    ]


def _canvas(width: float, height: float) -> Figure:
    figure = Figure(figsize=(width, height))
    FigureCanvasAgg(figure)
    return figure


def plot_scatter(path, scatter: dict, tests: list[dict] | None = None) -> None:
    """Final positions per condition: experiment, baseline and best effect, the shift of
    the mean position from the baseline's to the experiment's drawn as an arrow, and the
    observables the where-test flags in the condition (``tests``: ``where["tests"]``)."""
    n = len(scatter)
    flagged = {t["condition"]: t.get("observables_beyond_noise", []) for t in tests or []}
    figure = _canvas(4.2 * n, 4.6)
    for k, (condition, sets) in enumerate(scatter.items()):
        ax = figure.add_subplot(1, n, k + 1)
        for name, colour, marker in (
            ("baseline", "0.6", "."),
            ("best_effect", "tab:blue", "."),
            ("experiment", "tab:red", "x"),
        ):
            if name not in sets:  # no best effect when none applies
                continue
            p = np.asarray(sets[name]).reshape(-1, 2)
            ax.scatter(
                p[:, 0], p[:, 1], s=10, c=colour, marker=marker, label=name.replace("_", " ")
            )
        start = np.asarray(sets["baseline"]).reshape(-1, 2).mean(axis=0)
        end = np.asarray(sets["experiment"]).reshape(-1, 2).mean(axis=0)
        ax.annotate(
            "",
            xy=tuple(end),
            xytext=tuple(start),
            arrowprops=dict(arrowstyle="->", color="black", lw=1.5),
        )
        shift = end - start
        ax.text(
            0.02,
            0.02,
            f"mean shift {shift[0]:+.1f}, {shift[1]:+.1f} mm",
            transform=ax.transAxes,
            fontsize=7,
        )
        off = ", ".join(
            f"{r['observable']} {r['difference']:+.3g}" for r in flagged.get(condition, [])[:3]
        )
        ax.set_aspect("equal")
        ax.set_title(f"{condition}\noff: {off}" if off else condition, fontsize=9)
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("y (mm)")
        if k == 0:
            ax.legend(fontsize=7)
    figure.tight_layout()
    figure.savefig(path, dpi=120)


def plot_discrepancies(path, rows: list[dict]) -> None:
    """z of every observable and condition, with the +-1.96 band."""
    figure = _canvas(max(6.0, 0.35 * len(rows)), 4.0)
    ax = figure.add_subplot(1, 1, 1)
    z = [r["z"] for r in rows]
    colours = ["tab:red" if r["beyond_noise"] else "0.5" for r in rows]
    ax.bar(range(len(rows)), z, color=colours)
    ax.axhspan(-1.96, 1.96, color="0.9", zorder=0)
    ax.set_xticks(range(len(rows)))
    ax.set_xticklabels(
        [f"{r['condition']}: {r['observable']}" for r in rows], rotation=90, fontsize=6
    )
    ax.set_ylabel("experiment - simulation (standard errors)")
    figure.tight_layout()
    figure.savefig(path, dpi=120)


def plot_ranking(path, ranking: list[dict]) -> None:
    """Every effect in rank order: the discrepancy left at its fitted strength (when the
    ranking is on the whole data) and its held-out gap reduction, with 95 % intervals."""
    panels = [("held_out_reduction", "held-out gap reduction")]
    if "discrepancy" in ranking[0]:
        panels.insert(0, ("discrepancy", "discrepancy left (energy distance)"))
    figure = _canvas(4.5 * len(panels) + 1.5, 0.5 * len(ranking) + 1.5)
    names = [e["effect"] for e in ranking][::-1]
    y = np.arange(len(names))
    for k, (field, label) in enumerate(panels, 1):
        ax = figure.add_subplot(1, len(panels), k)
        values = [e[field] for e in ranking][::-1]
        lo = [e[field + "_ci95"][0] for e in ranking][::-1]
        hi = [e[field + "_ci95"][1] for e in ranking][::-1]
        v = np.nan_to_num(np.array(values, dtype=float))
        ax.barh(y, v, color="tab:blue")
        # An unbounded end (too many resamples with no gap to close) is drawn to the edge.
        lo = np.nan_to_num(np.array(lo, dtype=float), nan=0.0, neginf=-1.0, posinf=1.0)
        hi = np.nan_to_num(np.array(hi, dtype=float), nan=0.0, neginf=-1.0, posinf=1.0)
        err = np.array([v - np.minimum(lo, v), np.maximum(hi, v) - v])
        ax.errorbar(v, y, xerr=np.clip(err, 0, None), fmt="none", ecolor="k")
        ax.set_yticks(y)
        ax.set_yticklabels(names if k == 1 else [])
        ax.axvline(0, color="k", lw=0.8)
        ax.set_xlabel(label)
    figure.tight_layout()
    figure.savefig(path, dpi=120)


def write_diagnosis(run, result: dict) -> list[str]:
    """Write the report into a run directory (``run.path(name)`` gives where)."""
    run.write_json("diagnosis.json", _jsonable(result))
    run.write_text("diagnosis.md", report_markdown(result))
    files = ["diagnosis.json", "diagnosis.md"]
    if result.get("scatter"):
        plot_scatter(run.path("fig_scatter.png"), result["scatter"], result["where"]["tests"])
        files.append("fig_scatter.png")
    plot_discrepancies(run.path("fig_discrepancies.png"), result["where"]["observables"])
    files.append("fig_discrepancies.png")
    if result["which"] and result["which"]["ranking"]:
        plot_ranking(run.path("fig_effects.png"), result["which"]["ranking"])
        files.append("fig_effects.png")
    return files


def _jsonable(value):
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


__all__ += ["plot_scatter", "plot_discrepancies", "plot_ranking"]
