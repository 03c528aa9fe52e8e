"""Sim-to-real diagnosis of stack and container measurements (named quantities).

Each condition is a scenario; the simulation runs it ``repeats`` times per setting (seeds
differ between repeats, not between settings: common random numbers). A measured
quantity is compared with the mean of the repeats,

    z = (measured - simulated mean) / sqrt(se_measured^2 + sd_simulated^2 / repeats),

and the gap of a condition is G = mean z^2 (about 1 when there is none; a chi-square
test with as many degrees of freedom as quantities). No fitted parameter of the baseline
exists for these kinds (the paper fitted only the drop's damping and tilt range), so
there is nothing to refit first. Effects are fitted on calibration conditions and scored
on held-out ones (leave one condition out); with a single condition they are scored
in-sample, and the report says so.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable

import numpy as np
from scipy.stats import chi2

from core.errors import InputError
from core.schema import Scenario
from diagnosis.ranking import adjust_tests
from diagnosis.spec import Experiment, QuantityData
from diagnosis.stack_effects import (
    BOOTSTRAP,
    StackEffectRanking,
    how_far_best,
    mean_square,
    stack_folds,
    strength_grid,
)
from diagnosis.verdicts import applicable_effects, effect_verdict
from packing.deposition import deposit
from packing.effects import EFFECTS, contact_model
from packing.presets import PRESETS

__all__ = ["QUANTITIES", "diagnose_stacks", "simulate_quantities", "synthesize_quantities"]

log = logging.getLogger(__name__)

# name -> (unit, meaning, kinds)
QUANTITIES: dict[str, tuple[str, str, tuple[str, ...]]] = {
    "volume_fraction": (
        "",
        "chip volume over the container's (containers: centres inside) or over "
        "the target area times the mean height (stacks)",
        ("stack", "container"),
    ),
    "chips_inside": ("", "chips whose centre of mass is inside the container", ("container",)),
    "height_mean_mm": ("mm", "mean height of the stack's top surface", ("stack",)),
    "height_max_mm": ("mm", "highest point of the stack", ("stack",)),
    "contacts_per_chip": ("", "contacts (point + line + surface) per chip", ("stack",)),
    "contacts_point_per_chip": ("", "point contacts per chip", ("stack",)),
    "contacts_line_per_chip": ("", "line contacts per chip", ("stack",)),
    "contacts_surface_per_chip": ("", "surface contacts per chip", ("stack",)),
}
MAX_LAYERS = 30
for _k in range(MAX_LAYERS):
    QUANTITIES[f"layer_filling_{_k}"] = (
        "",
        f"chips whose centre lies in layer {_k} (2 mm layers by default) over a full layer "
        "(target area over chip area)",
        ("stack",),
    )


def simulate_quantities(scenario: Scenario, strengths: dict[str, float], seed: int) -> dict:
    """One deposition of ``scenario`` with effects, reduced to every quantity of its kind."""
    stack = deposit(scenario.with_seed(seed), effects=strengths)
    if scenario.kind == "container":
        from packing.fill import container_fill

        volumes = np.array([stack.shapes[k].volume_mm3 for k in stack.shape_index])
        c = scenario.container
        fill = container_fill(stack.positions, volumes, c.radius_mm, c.height_mm)
        return {"volume_fraction": fill["volume_fraction"], "chips_inside": fill["chips_inside"]}
    from geometry import arrangements_from_stack, describe

    description = describe(
        arrangements_from_stack(stack), scenario.geometry, ["contacts", "stack", "layers"]
    )
    contacts = description.sections["contacts"]["scalars"]
    heights = description.sections["stack"]["scalars"]
    out = {
        f"contacts_{t}_per_chip": contacts[f"{t}_per_chip"]["value"]
        for t in ("point", "line", "surface")
    }
    out["contacts_per_chip"] = sum(out.values())
    out["volume_fraction"] = heights["volume_fraction"]["value"]
    out["height_mean_mm"] = heights["height_mean_mm"]["value"]
    out["height_max_mm"] = heights["height_max_mm"]["value"]
    layers = description.sections["layers"]
    full = layers["scalars"]["full_layer"]["value"]
    chips = list(layers["profiles"]["chips"]["values"])
    for k in range(MAX_LAYERS):
        out[f"layer_filling_{k}"] = (chips[k] if k < len(chips) else 0.0) / full
    return out


class StackRuns:
    """Depositions of every setting (condition, effect, strength), each run as many times
    as its condition repeats, in batches through ``run_many``; and their means and sds."""

    def __init__(self, experiment: Experiment, run_many, seed: int, progress):
        self.x = experiment
        self.run_many = run_many
        self.seed = seed
        self.progress = progress
        self.results: dict[tuple, list[dict]] = {}
        first = experiment.conditions[0].scenario
        preset = PRESETS.get(first.physics.preset, key="physics.preset")
        self.contact = contact_model(preset, first.physics)

    def key(self, condition: str, effect: str | None, strength: float) -> tuple:
        # An effect at its neutral strength is the baseline: one setting, run once.
        if effect is not None and abs(strength - EFFECTS.get(effect).neutral(self.contact)) < 1e-12:
            effect, strength = None, 0.0
        return (condition, effect, round(strength, 12))

    def ensure(self, keys: list[tuple]) -> None:
        """Run, in one batch, the settings of ``keys`` not run yet."""
        keys = [k for k in dict.fromkeys(keys) if k not in self.results]
        calls, owners = [], []
        for key in keys:
            condition = self.x.condition(key[0])
            for r in range(condition.repeats):
                calls.append(
                    dict(
                        scenario=condition.scenario,
                        strengths={key[1]: key[2]} if key[1] else {},
                        # Common random numbers: repeat r of every setting shares a seed.
                        seed=int(self.seed) * 1000 + r,
                    )
                )
                owners.append(key)
        if not calls:
            return
        self.progress(f"simulating {len(calls)} depositions")
        for key, result in zip(owners, self.run_many(simulate_quantities, calls), strict=True):
            self.results.setdefault(key, []).append(result)

    def moments(self, key: tuple, quantity: str) -> tuple[float, float, int]:
        """Mean, sd and number of the repeats of a setting."""
        values = np.array([r[quantity] for r in self.results[key]], dtype=float)
        sd = float(values.std(ddof=1)) if len(values) > 1 else 0.0
        return float(values.mean()), sd, len(values)


class StackScores:
    """Measured quantities against the runs, standardised: for the measurements
    themselves (draw None) or for one of ``BOOTSTRAP`` parametric resamples, which draw
    both the measurement and the simulated mean from their standard errors."""

    def __init__(self, data: dict, runs: StackRuns, conditions: list[str], rng):
        self.data = data
        self.runs = runs
        self._noise = {c: {q: rng.normal(size=BOOTSTRAP) for q in data[c]} for c in conditions}
        self._sim_noise = {
            (k, q): rng.normal(size=BOOTSTRAP) for k in runs.results for q in data[k[0]]
        }

    def z(self, condition: str, key: tuple, draw: int | None = None) -> dict[str, float]:
        out = {}
        for quantity, q in self.data[condition].items():
            mean, sd, r = self.runs.moments(key, quantity)
            se_obs = q.sd / math.sqrt(q.n) if math.isfinite(q.sd) else 0.0
            scale = math.sqrt(se_obs**2 + sd**2 / r)
            # A floor for quantities every repeat reproduces exactly (an empty layer).
            scale = max(scale, 1e-3 * (1 + abs(mean)))
            value = q.value
            if draw is not None:
                value = q.value + self._noise[condition][quantity][draw] * se_obs
                mean = mean + self._sim_noise[(key, quantity)][draw] * sd / math.sqrt(r)
            out[quantity] = (value - mean) / scale
        return out

    def gap(self, condition: str, key: tuple, draw: int | None = None) -> float:
        return mean_square(self.z(condition, key, draw))


class _StackDiagnosis:
    """One stack or container diagnosis: the settings run, the three questions in order
    (the resample draws come from one random stream), and the report."""

    def __init__(self, experiment, data, run_many, seed, progress):
        self.x = experiment
        self.data = data
        self.seed = seed
        self.rng = np.random.default_rng([seed, 17])
        self.runs = StackRuns(
            experiment,
            run_many or (lambda f, calls: [f(**c) for c in calls]),
            seed,
            progress or (lambda message: None),
        )
        for _name, values in data.items():
            for quantity in values:
                if experiment.kind not in QUANTITIES[quantity][2]:
                    raise InputError(
                        f"{experiment.observations.name}: quantity {quantity!r} is not defined "
                        f"for {experiment.kind} scenarios"
                    )

    def run(self) -> dict:
        names = [c.name for c in self.x.conditions]
        effects, skipped = applicable_effects(self.x)
        points = self.x.settings.grid_points
        keys = [self.runs.key(c, None, 0.0) for c in names]
        keys += [
            self.runs.key(c, e, s)
            for e in effects
            for s in strength_grid(e, points, self.runs.contact)
            for c in names
        ]
        self.runs.ensure(keys)
        scores = StackScores(self.data, self.runs, names, self.rng)
        where = self._where(names, scores)
        folds = stack_folds(names)
        which = StackEffectRanking(self.runs, scores, folds, names, points).run(
            effects, self.x.kind
        )
        which["not_applicable"] = skipped
        how_far = how_far_best(which, folds, self.runs, scores)
        return dict(
            **self._description(names),
            where=where,
            which=which,
            how_far=how_far,
            verdict=self._verdict(where, which, how_far),
        )

    def _description(self, names: list[str]) -> dict:
        return dict(
            experiment=self.x.name,
            kind=self.x.kind,
            conditions=[
                dict(name=c.name, scenario=c.scenario.name, repeats=c.repeats)
                for c in self.x.conditions
            ],
            quantities={
                q: dict(unit=QUANTITIES[q][0], meaning=QUANTITIES[q][1])
                for q in sorted({q for c in names for q in self.data[c]})
            },
            seed=self.seed,
        )

    def _where(self, names: list[str], scores: StackScores) -> dict:
        """The "where" section: every quantity against the baseline's mean, and a
        chi-square test per condition."""
        rows, tests = [], []
        for c in names:
            key = self.runs.key(c, None, 0.0)
            z = scores.z(c, key)
            rows += [self._quantity_row(c, quantity, key, z[quantity]) for quantity in self.data[c]]
            g, k = mean_square(z), len(z)
            tests.append(
                dict(
                    condition=c,
                    gap=g,
                    null_mean=1.0,
                    p_value=float(chi2.sf(g * k, k)),
                    test=f"chi-square, {k} degrees of freedom",
                )
            )
        adjust_tests(tests, self.x.settings.alpha)
        return dict(observables=rows, tests=tests, regions=[])

    def _quantity_row(self, condition: str, quantity: str, key: tuple, z: float) -> dict:
        q = self.data[condition][quantity]
        mean, sd, r = self.runs.moments(key, quantity)
        difference = q.value - mean
        # The scale z was standardised with; a z of 0 does not tell it.
        scale = difference / z if z else math.nan
        margin = 1.96 * abs(scale)
        known = math.isfinite(scale)
        return dict(
            condition=condition,
            observable=quantity,
            experiment=q.value,
            simulation=mean,
            simulation_sd=sd,
            repeats=r,
            difference=difference,
            ci95=[difference - margin, difference + margin] if known else [math.nan, math.nan],
            noise_floor=margin if known else 0.0,
            z=z,
            beyond_noise=abs(z) > 1.96,
        )

    def _verdict(self, where, which, how_far) -> dict:
        significant = [t["condition"] for t in where["tests"] if t["significant"]]
        if not significant:
            return dict(
                kind="no significant gap",
                text="The measurements lie within the simulation's "
                "noise in every condition (chi-square tests, Holm-adjusted).",
            )
        return effect_verdict(significant, which, how_far, self.x.settings.alpha, where)


def diagnose_stacks(
    experiment: Experiment,
    data: dict[str, dict[str, QuantityData]],
    run_many=None,
    seed: int = 0,
    progress: Callable[[str], None] | None = None,
) -> dict:
    """The whole diagnosis of stack or container measurements as a JSON-ready dict."""
    return _StackDiagnosis(experiment, data, run_many, seed, progress).run()


def synthesize_quantities(
    experiment: Experiment, strengths: dict, seed: int, run_many=None
) -> list[dict]:
    """Rows ``condition, quantity, value, sd, n``: the mean and sd over each condition's
    repeats with the effects on (seeds apart from the diagnosis's own)."""
    calls, owners = [], []
    for condition in experiment.conditions:
        for r in range(max(condition.repeats, 2)):
            calls.append(
                dict(
                    scenario=condition.scenario,
                    strengths=strengths,
                    seed=10_000_000 + 1000 * int(seed) + r,
                )
            )
            owners.append(condition.name)
    results = (
        run_many(simulate_quantities, calls)
        if run_many
        else [simulate_quantities(**c) for c in calls]
    )
    rows = []
    for condition in experiment.conditions:
        runs = [r for o, r in zip(owners, results, strict=True) if o == condition.name]
        for quantity in runs[0]:
            values = np.array([r[quantity] for r in runs], dtype=float)
            if quantity.startswith("layer_filling_") and not values.any():
                continue  # layers above every stack
            rows.append(
                dict(
                    condition=condition.name,
                    quantity=quantity,
                    value=float(values.mean()),
                    sd=float(values.std(ddof=1)),
                    n=len(values),
                )
            )
    return rows
