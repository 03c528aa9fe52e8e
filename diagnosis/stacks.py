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
from diagnosis.spec import Experiment, QuantityData
from diagnosis.statistics import holm, interval
from diagnosis.verdicts import applicable_effects, effect_verdict, how_far
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
BOOTSTRAP = 400


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


class _StackDiagnosis:
    def __init__(self, experiment, data, run_many, seed, progress):
        self.x = experiment
        self.data = data
        self.run_many = run_many or (lambda f, calls: [f(**c) for c in calls])
        self.seed = seed
        self.progress = progress or (lambda message: None)
        self.runs: dict[tuple, list[dict]] = {}
        self.rng = np.random.default_rng([seed, 17])
        first = experiment.conditions[0].scenario
        preset = PRESETS.get(first.physics.preset, key="physics.preset")
        self.contact = contact_model(preset, first.physics)
        for _name, values in data.items():
            for quantity in values:
                if experiment.kind not in QUANTITIES[quantity][2]:
                    raise InputError(
                        f"{experiment.observations.name}: quantity {quantity!r} is not defined "
                        f"for {experiment.kind} scenarios"
                    )

    def _grid(self, effect: str) -> list[float]:
        lo, hi = EFFECTS.get(effect).prior
        points = max(3, min(self.x.settings.grid_points, 5))
        values = set(np.round(np.linspace(lo, hi, points), 12).tolist())
        values.add(round(EFFECTS.get(effect).neutral(self.contact), 12))
        return sorted(values)

    def _key(self, condition: str, effect: str | None, strength: float):
        if effect is not None and abs(strength - EFFECTS.get(effect).neutral(self.contact)) < 1e-12:
            effect, strength = None, 0.0
        return (condition, effect, round(strength, 12))

    def _ensure(self, keys: list[tuple]) -> None:
        keys = [k for k in dict.fromkeys(keys) if k not in self.runs]
        calls, owners = [], []
        for key in keys:
            condition = self.x.condition(key[0])
            for r in range(condition.repeats):
                calls.append(
                    dict(
                        scenario=condition.scenario,
                        strengths={key[1]: key[2]} if key[1] else {},
                        seed=int(self.seed) * 1000 + r,
                    )
                )
                owners.append(key)
        if not calls:
            return
        self.progress(f"simulating {len(calls)} depositions")
        for key, result in zip(owners, self.run_many(simulate_quantities, calls), strict=True):
            self.runs.setdefault(key, []).append(result)

    def _moments(self, key: tuple, quantity: str) -> tuple[float, float, int]:
        values = np.array([r[quantity] for r in self.runs[key]], dtype=float)
        sd = float(values.std(ddof=1)) if len(values) > 1 else 0.0
        return float(values.mean()), sd, len(values)

    def _z(self, condition: str, key: tuple, draw: int | None = None) -> dict[str, float]:
        out = {}
        for quantity, q in self.data[condition].items():
            mean, sd, r = self._moments(key, quantity)
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

    def _gap(self, condition: str, key: tuple, draw: int | None = None) -> float:
        z = np.array(list(self._z(condition, key, draw).values()))
        return float(np.mean(z**2))

    def run(self) -> dict:
        names = [c.name for c in self.x.conditions]
        effects, skipped = applicable_effects(self.x)
        keys = [self._key(c, None, 0.0) for c in names]
        keys += [self._key(c, e, s) for e in effects for s in self._grid(e) for c in names]
        self._ensure(keys)
        self._noise = {c: {q: self.rng.normal(size=BOOTSTRAP) for q in self.data[c]} for c in names}
        self._sim_noise = {
            (k, q): self.rng.normal(size=BOOTSTRAP) for k in self.runs for q in self.data[k[0]]
        }
        where = self._where(names)
        which = self._which(names, effects)
        which["not_applicable"] = skipped
        how_far = self._how_far(names, which)
        verdict = self._verdict(where, which)
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
            where=where,
            which=which,
            how_far=how_far,
            verdict=verdict,
        )

    def _where(self, names: list[str]) -> dict:
        rows, tests = [], []
        for c in names:
            key = self._key(c, None, 0.0)
            z = self._z(c, key)
            for quantity, q in self.data[c].items():
                mean, sd, r = self._moments(key, quantity)
                scale = (q.value - mean) / z[quantity] if z[quantity] else math.nan
                rows.append(
                    dict(
                        condition=c,
                        observable=quantity,
                        experiment=q.value,
                        simulation=mean,
                        simulation_sd=sd,
                        repeats=r,
                        difference=q.value - mean,
                        ci95=[
                            q.value - mean - 1.96 * abs(scale),
                            q.value - mean + 1.96 * abs(scale),
                        ]
                        if math.isfinite(scale)
                        else [math.nan, math.nan],
                        noise_floor=1.96 * abs(scale) if math.isfinite(scale) else 0.0,
                        z=z[quantity],
                        beyond_noise=abs(z[quantity]) > 1.96,
                    )
                )
            k = len(z)
            g = float(np.mean(np.array(list(z.values())) ** 2))
            tests.append(
                dict(
                    condition=c,
                    gap=g,
                    null_mean=1.0,
                    p_value=float(chi2.sf(g * k, k)),
                    test=f"chi-square, {k} degrees of freedom",
                )
            )
        for t, p in zip(tests, holm([t["p_value"] for t in tests]), strict=True):
            t["p_holm"] = p
            t["significant"] = p < self.x.settings.alpha
        total = sum(max(t["gap"] - 1.0, 0.0) for t in tests)
        for t in tests:
            t["share_of_gap"] = max(t["gap"] - 1.0, 0.0) / total if total > 0 else 0.0
        return dict(observables=rows, tests=tests, regions=[])

    def _folds(self, names):
        if len(names) > 1:
            return [
                dict(name=f"hold out {h}", calibration=[c for c in names if c != h], held_out=[h])
                for h in names
            ]
        return [
            dict(
                name="in-sample (one condition: nothing to hold out)",
                calibration=names,
                held_out=names,
            )
        ]

    def _which(self, names, effects) -> dict:
        folds = self._folds(names)
        draws = [None, *range(BOOTSTRAP)]

        def excess(conditions, key_of, draw):
            return sum(self._gap(c, key_of(c), draw) - 1.0 for c in conditions)

        base = np.array(
            [
                sum(excess(f["held_out"], lambda c: self._key(c, None, 0.0), d) for f in folds)
                for d in draws
            ]
        )
        results, reductions, closed = {}, {}, {}
        for effect in effects:
            grid = self._grid(effect)
            held = np.zeros(len(draws))
            per_fold = []
            for fold in folds:
                # Fitted once on the calibration data and held; the held-out data resampled.
                cal = [
                    excess(fold["calibration"], lambda c, s=s, e=effect: self._key(c, e, s), None)
                    for s in grid
                ]
                fitted_here = grid[int(np.argmin(cal))]
                for j, d in enumerate(draws):
                    s = fitted_here
                    held[j] += excess(
                        fold["held_out"], lambda c, s=s, e=effect: self._key(c, e, s), d
                    )
                    if d is None:
                        per_fold.append(dict(fold=fold["name"], strength=s))
                        fold.setdefault("chosen", {})[effect] = s
            with np.errstate(divide="ignore", invalid="ignore"):
                reduction = np.where(base > 0, 1 - held / base, np.nan)
            reductions[effect] = reduction
            closed[effect] = base - held
            fitted = []
            for d in draws:
                cal = [excess(names, lambda c, s=s, e=effect: self._key(c, e, s), d) for s in grid]
                fitted.append(grid[int(np.argmin(cal))])
            e = EFFECTS.get(effect)
            results[effect] = dict(
                effect=effect,
                parameter=e.parameter,
                unit=e.unit,
                prior=list(e.prior),
                strength=fitted[0],
                strength_ci95=list(interval(fitted[1:])),
                held_out_reduction=float(reduction[0]),
                held_out_reduction_ci95=list(interval(reduction[1:])),
                gap_closed=float(closed[effect][0]),
                gap_closed_ci95=list(interval(closed[effect][1:])),
                folds=per_fold,
            )
        ranking = sorted(effects, key=lambda e: -closed[e][0])
        best = ranking[0] if ranking else None
        for effect in ranking:
            lo, hi = interval(closed[best][1:] - closed[effect][1:])
            results[effect]["difference_to_best_ci95"] = [lo, hi]
            results[effect]["indistinguishable_from_best"] = bool(effect == best or not lo > 0)
        tied = [e for e in ranking if results[e]["indistinguishable_from_best"]]
        telling = {}
        for e in tied:
            if e == best:
                continue
            top = dict(z=0.0)
            for fold in folds:
                for c in fold["held_out"]:
                    for q in self.data[c]:
                        a, sa, ra = self._moments(self._key(c, best, fold["chosen"][best]), q)
                        b, sb, rb = self._moments(self._key(c, e, fold["chosen"][e]), q)
                        z = abs(a - b) / max(math.sqrt(sa**2 / ra + sb**2 / rb), 1e-12)
                        if z > top["z"]:
                            top = dict(
                                z=z, observable=q, condition=c, best_predicts=a, other_predicts=b
                            )
            telling[e] = top
        return dict(
            baseline_refit=dict(
                parameter=f"none: the baseline has no fitted parameter for {self.x.kind} scenarios",
                held_out=[],
                held_out_excess=float(base[0]),
                held_out_excess_ci95=list(interval(base[1:])),
            ),
            ranking=[results[e] for e in ranking],
            best=best,
            indistinguishable=tied,
            telling_apart=telling,
            folds=[f["name"] for f in folds],
        )

    def _how_far(self, names, which) -> dict:
        best = which["best"]
        if best is None:
            return {}
        rows, totals = [], []
        for fold in self._folds(names):
            s = next(
                f["strength"] for f in which["ranking"][0]["folds"] if f["fold"] == fold["name"]
            )
            for c in fold["held_out"]:
                before = self._z(c, self._key(c, None, 0.0))
                after = self._z(c, self._key(c, best, s))
                for q in self.data[c]:
                    rows.append(
                        dict(
                            fold=fold["name"],
                            condition=c,
                            observable=q,
                            experiment=self.data[c][q].value,
                            before=self._moments(self._key(c, None, 0.0), q)[0],
                            after=self._moments(self._key(c, best, s), q)[0],
                            z_before=before[q],
                            z_after=after[q],
                        )
                    )
                g0 = float(np.mean(np.array(list(before.values())) ** 2))
                g1 = float(np.mean(np.array(list(after.values())) ** 2))
                k = len(before)
                totals.append(
                    dict(
                        fold=fold["name"],
                        condition=c,
                        strength=s,
                        gap_before=g0,
                        gap_after=g1,
                        null_mean=1.0,
                        p_before=float(chi2.sf(g0 * k, k)),
                        p_after=float(chi2.sf(g1 * k, k)),
                    )
                )
        return how_far(best, which["ranking"][0], rows, totals)

    def _verdict(self, where, which) -> dict:
        significant = [t["condition"] for t in where["tests"] if t["significant"]]
        if not significant:
            return dict(
                kind="no significant gap",
                text="The measurements lie within the simulation's "
                "noise in every condition (chi-square tests, Holm-adjusted).",
            )
        return effect_verdict(significant, which)


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
