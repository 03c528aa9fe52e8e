"""Sim-to-real diagnosis of stack and container measurements (named quantities).

Each condition is a scenario; the simulation runs it ``repeats`` times per setting (seeds
differ between repeats, not between settings: common random numbers). A measured
quantity (value, sd, n) is compared with the mean of the repeats by Welch's t,

    t = (measured - simulated mean) / sqrt(sd_measured^2 / n + sd_simulated^2 / repeats),

with Welch-Satterthwaite degrees of freedom. A condition departs when its smallest
p-value, Bonferroni-adjusted over its quantities, is significant after Holm across the
conditions (the quantities correlate, so no test that assumes them independent); "where"
adjusts every quantity of every condition together (Holm). Effect-free data stop there.

Otherwise, as for drops: each effect's strength is fitted on calibration conditions (the
vertex of G = mean t^2 over a grid, refitted on every parametric resample of measurements
and simulations for its interval), simulated at that strength and scored on the held-out
conditions (leave one condition out; one condition is scored in-sample, and the report
says so); the effects are ranked by the held-out gap they close, the ones not
significantly worse than the best (bootstrap, Holm) are its tie set, and the best is
"explained" only if the held-out measurements are consistent with it (``how_far_best``).
No fitted parameter of the baseline exists for these kinds (the paper fitted only the
drop's damping and tilt range), so the baseline is not refitted.
"""

from __future__ import annotations

import logging
import math
import zlib
from collections.abc import Callable

import numpy as np
from scipy.stats import t as student_t

from chipstack.core.arrangement import arrangements_from_stack
from chipstack.core.errors import InputError
from chipstack.core.schema import Scenario
from chipstack.diagnosis.model import Experiment, QuantityData
from chipstack.diagnosis.quantity_kinds import MAX_LAYERS, QUANTITIES, QUANTITY_MEASURES
from chipstack.diagnosis.ranking import adjust_tests
from chipstack.diagnosis.stack_effects import (
    BOOTSTRAP,
    StackEffectRanking,
    how_far_best,
    mean_square,
    stack_folds,
    strength_grid,
)
from chipstack.diagnosis.statistics import holm
from chipstack.diagnosis.verdicts import applicable_effects, effect_verdict
from chipstack.geometry.describe import describe
from chipstack.packing.deposition import deposit
from chipstack.packing.effects import EFFECTS, contact_model
from chipstack.packing.fill import container_fill
from chipstack.packing.presets import PRESETS

__all__ = [
    "QUANTITIES",
    "QUANTITY_MEASURES",
    "diagnose_stacks",
    "simulate_quantities",
    "synthesize_quantities",
]

log = logging.getLogger(__name__)

BASELINE_REPEATS = 8


def _container_quantities(scenario: Scenario, stack) -> dict:
    """A container fill's volume fraction and the chips inside it."""
    volumes = np.array([stack.shapes[k].volume_mm3 for k in stack.shape_index])
    c = scenario.container
    fill = container_fill(stack.positions, volumes, c.radius_mm, c.height_mm)
    return {"volume_fraction": fill["volume_fraction"], "chips_inside": fill["chips_inside"]}


def _stack_quantities(scenario: Scenario, stack) -> dict:
    """A stack's contacts per chip, heights, volume fraction and layer filling."""
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


# How a deposition of each scenario kind is reduced to its quantities, looked up by the
# scenario's kind (a plugin scenario kind would also need its quantities in QUANTITIES
# and an experiment kind of its own).
QUANTITY_MEASURES.register("stack", _stack_quantities)
QUANTITY_MEASURES.register("container", _container_quantities)


def simulate_quantities(scenario: Scenario, strengths: dict[str, float], seed: int) -> dict:
    """One deposition of ``scenario`` with effects, reduced to every quantity of its kind."""
    measure = QUANTITY_MEASURES.get(scenario.kind, key="scenario kind")
    return measure(scenario, deposit(scenario.with_seed(seed), effects=strengths))


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
            for r in range(self.repeats(key)):
                calls.append(
                    dict(
                        scenario=self.x.condition(key[0]).scenario,
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

    def repeats(self, key: tuple) -> int:
        """Runs of a setting: the condition's repeats, and at least ``BASELINE_REPEATS``
        for the baseline, whose spread decides the detection and scales every score:
        Welch's test with the 1 or 2 degrees of freedom of 2 or 3 repeats raised 7.7 %
        false alarms for 5 % (300 analytic cases as in tests/test_stack_diagnosis.py),
        and the conservative alternative (Hsu's degrees of freedom) finds almost
        nothing."""
        repeats = self.x.condition(key[0]).repeats
        return max(repeats, BASELINE_REPEATS) if key[1] is None else repeats

    def moments(
        self, key: tuple, quantity: str, first: int | None = None
    ) -> tuple[float, float, int]:
        """Mean, sd and number of the repeats of a setting (its ``first`` ones only)."""
        values = np.array([r[quantity] for r in self.results[key][:first]], dtype=float)
        sd = float(values.std(ddof=1)) if len(values) > 1 else 0.0
        return float(values.mean()), sd, len(values)


class StackScores:
    """Measured quantities against the runs, standardised, and tested.

    The detection compares each quantity with the mean of all the baseline's runs.
    Once the grid is run (``freeze``), every setting of a condition is compared on one
    scale: its mean over the grid's repeats (the same seeds for every setting: common
    random numbers, so the curves over a strength are smooth) and the standard error
    those repeats would have with the baseline's spread (from its 8 or more runs of
    distinct seeds; the settings' own repeats share seeds, so pooling them would count
    the same noise several times). A squared error on a scale no model chooses is a
    proper score of the mean, so a model that scatters more is not rewarded for it.

    Draws: the measurements themselves (None) or one of ``BOOTSTRAP`` parametric
    resamples, which draw each measurement from its standard error and the simulated
    means from theirs. The settings share their seeds, so part of their errors moves
    together and part does not (a deposition is chaotic: a different effect soon takes
    the chips elsewhere); the shared share ``rho`` is measured from the grid
    (``shared_share``), and each setting's draw is sqrt(rho) times one draw common to
    the condition's settings plus sqrt(1 - rho) times its own."""

    def __init__(self, data: dict, runs: StackRuns, seed: int):
        self.data = data
        self.runs = runs
        self.seed = int(seed)
        self.frozen = False
        rng = np.random.default_rng([self.seed, 19])
        self._noise = {c: {q: rng.normal(size=BOOTSTRAP) for q in data[c]} for c in data}
        self._shared_noise = {c: {q: rng.normal(size=BOOTSTRAP) for q in data[c]} for c in data}
        self._own_noise: dict[tuple, np.ndarray] = {}
        self.shared: dict[tuple[str, str], float] = {}
        self._gaps: dict[tuple, np.ndarray] = {}

    def freeze(self) -> None:
        """Score every setting on the grid's repeats from now on, with the share of their
        errors the settings have in common measured from the grid."""
        self.frozen = True
        for c, values in self.data.items():
            for q in values:
                self.shared[(c, q)] = self.shared_share(c, q)
        self._gaps.clear()

    def shared_share(self, condition: str, quantity: str) -> float:
        """The share of a setting's repeat-to-repeat variance that every setting of the
        condition has in common (the seeds' part), 0 to 1: one minus the two-way
        residual variance (settings x seeds, both means removed) over the baseline's
        variance. Model: x[k, r] = mean[k] + seed[r] + own[k, r]."""
        repeats = self.runs.x.condition(condition).repeats
        rows = [
            [run[quantity] for run in runs[:repeats]]
            for key, runs in self.runs.results.items()
            if key[0] == condition and len(runs) >= repeats
        ]
        x = np.array(rows, dtype=float)
        _, sd, _ = self.runs.moments(self.runs.key(condition, None, 0.0), quantity)
        if len(x) < 2 or sd == 0:
            return 1.0
        residual = x - x.mean(axis=1, keepdims=True) - x.mean(axis=0, keepdims=True) + x.mean()
        own = float((residual**2).sum()) / ((x.shape[0] - 1) * (x.shape[1] - 1))
        return float(np.clip(1 - own / sd**2, 0.0, 1.0))

    def _sim_draws(self, condition: str, key: tuple, quantity: str) -> np.ndarray:
        """Standard normal draws of a setting's simulated-mean error (``BOOTSTRAP``,)."""
        if (key, quantity) not in self._own_noise:
            stream = zlib.crc32(repr((key, quantity)).encode())
            rng = np.random.default_rng([self.seed, 29, stream])
            self._own_noise[(key, quantity)] = rng.normal(size=BOOTSTRAP)
        rho = self.shared.get((condition, quantity), 1.0)
        shared = self._shared_noise[condition][quantity]
        return math.sqrt(rho) * shared + math.sqrt(1 - rho) * self._own_noise[(key, quantity)]

    def _first(self, condition: str) -> int | None:
        """The repeats a setting's mean is taken over: all of them for the detection;
        once frozen, the grid's (the baseline's first ones)."""
        return self.runs.x.condition(condition).repeats if self.frozen else None

    def mean(self, condition: str, key: tuple, quantity: str) -> float:
        """The simulated mean a measured quantity is compared with."""
        return self.runs.moments(key, quantity, self._first(condition))[0]

    def _variance(self, condition: str, key: tuple, quantity: str) -> tuple[float, float]:
        """The variance of the simulated mean and its degrees of freedom (inf: none
        known): the setting's own runs' for the detection; once frozen, the baseline's
        spread over the grid's repeats."""
        if self.frozen:
            baseline = self.runs.key(condition, None, 0.0)
            _, sd, runs = self.runs.moments(baseline, quantity)
            repeats = self.runs.x.condition(condition).repeats
            return sd**2 / repeats, (runs - 1 if runs > 1 else math.inf)
        _, sd, runs = self.runs.moments(key, quantity)
        return sd**2 / runs, (runs - 1 if runs > 1 else math.inf)

    def t(self, condition: str, key: tuple, quantity: str, resampled: bool = False):
        """Welch's t of a measured quantity against a setting's simulated mean, and its
        Welch-Satterthwaite degrees of freedom. ``resampled``: t for the measurements,
        then for every resample (1 + B,)."""
        q = self.data[condition][quantity]
        mean = self.mean(condition, key, quantity)
        sim_var, sim_dof = self._variance(condition, key, quantity)
        known = math.isfinite(q.sd) and q.n > 1
        obs_var = q.sd**2 / q.n if known else 0.0
        obs_dof = q.n - 1 if known else math.inf
        scale = math.sqrt(obs_var + sim_var)
        value, means = q.value, mean
        if resampled:
            value = np.concatenate(
                [[q.value], q.value + self._noise[condition][quantity] * math.sqrt(obs_var)]
            )
            means = np.concatenate(
                [[mean], mean + self._sim_draws(condition, key, quantity) * math.sqrt(sim_var)]
            )
        floor = 1e-3 * (1 + abs(mean))
        if scale < floor:
            # Every repeat and measurement alike (an empty layer): a floor, no spread.
            return (value - means) / floor, math.inf
        parts = obs_var**2 / obs_dof + sim_var**2 / sim_dof
        dof = (obs_var + sim_var) ** 2 / parts if parts > 0 else math.inf
        return (value - means) / scale, dof

    def z(self, condition: str, key: tuple) -> dict[str, float]:
        return {q: float(self.t(condition, key, q)[0]) for q in self.data[condition]}

    def gap(self, condition: str, key: tuple) -> np.ndarray:
        """G: the mean squared standardised difference over the condition's quantities
        (about 1 without a gap), the discrepancy fits minimise and held-out data score:
        for the measurements, then for every resample (1 + B,). Cached once the scale is
        frozen."""
        cached = (condition, key) in self._gaps
        if not cached:
            squares = [self.t(condition, key, q, True)[0] ** 2 for q in self.data[condition]]
            g = np.mean(squares, axis=0)
            if not self.frozen:
                return g
            self._gaps[(condition, key)] = g
        return self._gaps[(condition, key)]

    def p_values(self, condition: str, key: tuple) -> dict[str, float]:
        """Two-sided Welch test of each quantity of ``condition`` against ``key``."""
        out = {}
        for quantity in self.data[condition]:
            t, dof = self.t(condition, key, quantity)
            out[quantity] = float(2 * student_t.sf(abs(t), dof))
        return out

    def test(self, condition: str, key: tuple) -> float:
        """Is ``condition`` consistent with ``key``? The smallest of its quantities'
        p-values, Bonferroni-adjusted: valid however the quantities correlate (mean
        height and volume fraction nearly duplicate each other), where a chi-square of
        their sum assumes them independent."""
        p = self.p_values(condition, key)
        return float(min(1.0, len(p) * min(p.values())))


class _StackDiagnosis:
    """One stack or container diagnosis: the settings run, the three questions in order
    (the resample draws come from the seed), and the report."""

    def __init__(self, experiment, data, run_many, seed, progress):
        self.x = experiment
        self.data = data
        self.seed = seed
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
        self.runs.ensure([self.runs.key(c, None, 0.0) for c in names])
        scores = StackScores(self.data, self.runs, self.seed)
        where = self._where(names, scores)
        result = dict(**self._description(names), where=where)
        significant = [t["condition"] for t in where["tests"] if t["significant"]]
        if not significant:
            # Effect-free data stop here: no effect is fitted to a gap that is not there.
            return dict(
                **result,
                which=None,
                how_far=None,
                verdict=dict(
                    kind="no significant gap",
                    text="The measurements lie within the simulation's noise in every "
                    "condition (Welch tests of every quantity, Bonferroni within a "
                    "condition, Holm across conditions).",
                ),
            )
        effects, skipped = applicable_effects(self.x)
        points = self.x.settings.grid_points
        self.runs.ensure(
            [
                self.runs.key(c, e, s)
                for e in effects
                for s in strength_grid(e, points, self.runs.contact)
                for c in names
            ]
        )
        scores.freeze()
        folds = stack_folds(names)
        which = StackEffectRanking(self.runs, scores, folds, names, points, self.x.settings.alpha)
        which = which.run(effects, self.x.kind)
        which["not_applicable"] = skipped
        how_far = how_far_best(which, folds, self.runs, scores)
        verdict = effect_verdict(significant, which, how_far, self.x.settings.alpha, where)
        return dict(**result, which=which, how_far=how_far, verdict=verdict)

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
        """The "where" section: every quantity against the baseline's mean (Welch tests,
        Holm-adjusted across every quantity of every condition), and a test per
        condition (Bonferroni within it, Holm across conditions)."""
        rows, tests = [], []
        for c in names:
            key = self.runs.key(c, None, 0.0)
            z = scores.z(c, key)
            p = scores.p_values(c, key)
            rows += [self._quantity_row(c, q, key, z[q], p[q]) for q in self.data[c]]
            tests.append(
                dict(
                    condition=c,
                    gap=mean_square(z),
                    null_mean=1.0,
                    p_value=scores.test(c, key),
                    test=f"Welch t of {len(z)} quantities, smallest p Bonferroni-adjusted",
                )
            )
        adjust_tests(tests, self.x.settings.alpha)
        for row, p_holm in zip(rows, holm([r["p_value"] for r in rows]), strict=True):
            row["p_holm"] = float(p_holm)
            row["beyond_noise"] = bool(p_holm < self.x.settings.alpha)
        return dict(observables=rows, tests=tests, regions=[])

    def _quantity_row(self, condition: str, quantity: str, key: tuple, z: float, p) -> dict:
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
            p_value=p,
        )


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
    experiment: Experiment,
    strengths: dict,
    seed: int,
    run_many=None,
    measurements: int | None = None,
) -> list[dict]:
    """Rows ``condition, quantity, value, sd, n``: the mean and sd over ``measurements``
    depositions of each condition (default: its repeats, at least 2) with the effects on
    (seeds apart from the diagnosis's own)."""
    calls, owners = [], []
    for condition in experiment.conditions:
        for r in range(measurements or max(condition.repeats, 2)):
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
