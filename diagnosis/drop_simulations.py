"""The two kinds of drop sample a drop diagnosis compares: the simulated settings it runs
(kept, with their observables and standardised features) and the observed drops of a
condition (with their bootstrap weights); and the energy distances and scores between
them."""

from __future__ import annotations

import hashlib
import io
import math
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from chipstack.diagnosis.model import DropData, Experiment
from chipstack.diagnosis.observables import (
    FeatureMetric,
    drop_features,
    drop_observables,
    symmetry_order,
)
from chipstack.diagnosis.reference_table import TableStore, simulation_key
from chipstack.diagnosis.statistics import (
    energy_distance,
    mean_cross,
    mean_within,
    resample_weights,
)
from chipstack.packing.effects import EFFECTS, contact_model
from chipstack.packing.presets import PRESETS

__all__ = ["CALIBRATION_POOL", "Dataset", "DropSimulations", "NOISE_POOL"]

# The pool every setting is drawn from; pool "B" is the same setting simulated again,
# independently, to test a fitted model on data it was not chosen with.
BASELINE_POOL = "A"
NOISE_POOL = "B"
# Grid settings (the curves strengths and tilts are fitted on) are simulated with half
# the drops: the curve's smooth surrogate pools the grid points, and their drops are the
# first of pool A's (each drop has its own random stream), so the grid stays paired with
# the fitted models.
GRID_POOL = "G"
# The fitted model simulated a third time: the pseudo-experiments its adequacy test is
# calibrated on (independent of the drops it was chosen with and tested against).
CALIBRATION_POOL = "C"
GRID_MIN_DROPS = 60  # below that a grid point's curve is too rough to fit on


TILT_GRID_DEG = (0.0, 2.5, 10.0, 15.0, 20.0)


class DropSimulations:
    """Every simulated setting (condition, release tilt, effect, strength, pool), run in
    batches through ``run_many`` once and kept with its observables."""

    def __init__(
        self,
        experiment: Experiment,
        names: list[str],
        simulate: Callable,
        run_many: Callable[[Callable, list[dict]], list],
        seed: int,
        progress: Callable[[str], None],
        store: TableStore | None = None,
    ):
        self.x = experiment
        # Where finished simulations are kept across diagnoses (the reference tables'
        # store): a second diagnosis of the same design re-simulates nothing.
        self.store = store
        self._store_key = simulation_key(experiment.scenario) if store is not None else ""
        self.names = names
        self.order = symmetry_order(experiment.scenario)
        self.simulate = simulate
        self.run_many = _longest_first(run_many)
        self.seed = seed
        self.progress = progress
        self.index = {c.name: k for k, c in enumerate(experiment.conditions)}
        self.drops: dict[tuple, DropData] = {}
        self.observables: dict[tuple, np.ndarray] = {}
        self.metric: dict[str, FeatureMetric] = {}  # condition -> how drops compare
        self._sim_weights: dict[tuple, np.ndarray] = {}  # (condition, m) -> (1 + B, m)
        self._features: dict[tuple, np.ndarray] = {}
        self._within: dict[tuple, np.ndarray] = {}
        self._cross: dict[tuple, np.ndarray] = {}
        # condition -> (K,) sd of each observable's difference when there is no gap
        self.observable_sd: dict[str, np.ndarray] = {}
        self.n = experiment.settings.sim_drops
        self.pool_sizes: dict[tuple, int] = {}  # settings simulated with other than n drops
        self.grid_n = min(self.n, max(GRID_MIN_DROPS, self.n // 2))
        preset = PRESETS.get(experiment.scenario.physics.preset, key="physics.preset")
        self.contact = contact_model(preset, experiment.scenario.physics)
        # The release tilts the baseline refit may choose: a fixed grid and every
        # condition's own tilt (the spec's value must be one of the candidates).
        self.tilt_grid = tuple(
            sorted(set(TILT_GRID_DEG) | {float(c.protocol.tilt_deg) for c in experiment.conditions})
        )

    # -- keys ----------------------------------------------------------------------------
    @staticmethod
    def key(condition: str, tilt: float, effect: str | None, strength: float, pool: str):
        # Rounded so that a strength reached by two routes (grid, midpoint) is one setting.
        return (condition, round(tilt, 9), effect, round(strength, 12), pool)

    def own_tilt(self, condition: str, tilt: float | None) -> float:
        """``tilt``, or with None the condition's own release tilt (the spec's)."""
        return self.x.condition(condition).protocol.tilt_deg if tilt is None else tilt

    def baseline(self, condition: str, tilt: float | None, pool: str = BASELINE_POOL) -> tuple:
        return self.key(condition, self.own_tilt(condition, tilt), None, 0.0, pool)

    def setting(self, condition: str, tilt: float | None, effect: str | None, strength: float):
        """The key of ``effect`` at ``strength`` (release tilt ``tilt``, None: the
        condition's own); an effect at its neutral strength is the baseline itself, so it
        shares the baseline's simulation."""
        tilt = self.own_tilt(condition, tilt)
        neutral = EFFECTS.get(effect).neutral(self.contact) if effect else 0.0
        if effect is None or abs(strength - neutral) <= 1e-12:
            return self.baseline(condition, tilt)
        return self.key(condition, tilt, effect, strength, BASELINE_POOL)

    def grid_setting(self, condition: str, tilt: float | None, effect: str | None, strength):
        """The key of a grid point: ``setting``'s, simulated with ``grid_n`` drops,
        except the condition's own baseline (the detection's, simulated in full)."""
        key = self.setting(condition, tilt, effect, strength)
        return key if key == self.baseline(condition, None) else key[:4] + (GRID_POOL,)

    def grid_at_offset(self, condition: str, offset: float, effect: str | None, strength):
        """``grid_setting`` at the condition's own release tilt plus ``offset`` (deg)."""
        return self.grid_setting(
            condition, self.own_tilt(condition, None) + offset, effect, strength
        )

    @staticmethod
    def second_pool(key: tuple) -> tuple:
        """The same setting simulated again, independently (its noise-floor twin)."""
        return key[:4] + (NOISE_POOL,)

    # -- running -------------------------------------------------------------------------
    def ensure(self, keys: list[tuple]) -> None:
        """Simulate, in one batch, those of ``keys`` not simulated yet."""
        keys = [k for k in dict.fromkeys(keys) if k not in self.drops]
        if not keys:
            return
        calls = {key: self._call(*key) for key in keys}
        for key in keys:
            stored = self._load(calls[key])
            if stored is not None:
                self._keep(key, stored)
        keys = [k for k in keys if k not in self.drops]
        if not keys:
            return
        drops = sum(calls[k]["n"] for k in keys)
        self.progress(f"simulating {len(keys)} settings, {drops} drops")
        results = self.run_many(self.simulate, [calls[k] for k in keys])
        for key, result in zip(keys, results, strict=True):
            self._keep(key, result)
            self._save(calls[key], result)

    def _keep(self, key: tuple, result: DropData) -> None:
        self.drops[key] = result
        self.observables[key] = self.observe(result, key[0])

    def _stored_name(self, call: dict) -> str:
        simulate = f"{self.simulate.__module__}.{self.simulate.__qualname__}"
        settings = {k: v for k, v in call.items() if k != "scenario"}
        text = f"{self._store_key}|{simulate}|{sorted(settings.items())!r}"
        return f"sims-{hashlib.sha256(text.encode()).hexdigest()[:24]}.npz"

    def _load(self, call: dict) -> DropData | None:
        blob = self.store.load(self._stored_name(call)) if self.store is not None else None
        if blob is None:
            return None
        with np.load(io.BytesIO(blob)) as arrays:
            return DropData(
                arrays["positions"],
                arrays["yaw_deg"] if "yaw_deg" in arrays else None,
                arrays["tilt_deg"] if "tilt_deg" in arrays else None,
            )

    def _save(self, call: dict, result: DropData) -> None:
        if self.store is None or not isinstance(result, DropData):
            return
        arrays = {"positions": result.positions}
        for name in ("yaw_deg", "tilt_deg"):
            if getattr(result, name) is not None:
                arrays[name] = getattr(result, name)
        buffer = io.BytesIO()
        np.savez(buffer, **arrays)
        self.store.save(self._stored_name(call), buffer.getvalue())

    def _call(self, condition: str, tilt: float, effect: str | None, strength: float, pool: str):
        key = (condition, tilt, effect, strength, pool)
        return dict(
            scenario=self.x.scenario,
            protocol=replace(self.x.condition(condition).protocol, tilt_deg=tilt),
            n=self.pool_sizes.get(key, self.grid_n if pool == GRID_POOL else self.n),
            strengths={effect: strength} if effect else {},
            seed=self._seed(condition, pool),
            position_sd_mm=self.x.position_sd_mm,
            angle_sd_deg=self.x.angle_sd_deg,
        )

    def _seed(self, condition: str, pool: str) -> int:
        # Common random numbers: every setting of a condition uses the same draws.
        pool_offset = {NOISE_POOL: 2, CALIBRATION_POOL: 3}.get(pool, 1)
        return int(self.seed) * 1000 + 10 * self.index[condition] + pool_offset

    def forget(self, key: tuple) -> None:
        """Drop every result cached for the simulation ``key`` (before it is replaced)."""
        for cache in (self.drops, self.observables, self._features, self._within):
            cache.pop(key, None)
        for cached in [k for k in self._cross if k[1] == key]:
            del self._cross[cached]

    def observe(self, d: DropData, condition: str) -> np.ndarray:
        yaw0 = self.x.condition(condition).protocol.yaw_deg
        return drop_observables(d.positions, d.yaw_deg, d.tilt_deg, yaw0, self.order, self.names)

    def observe_many(self, d: DropData, index: np.ndarray, condition: str) -> np.ndarray:
        """The observables (R, K) of the R subsets ``d.take(index[r])`` of ``d``
        (``index`` (R, k) drop indices), in one vectorised call."""
        return self.observe(d.take(np.asarray(index)), condition)

    # -- whole-distribution comparisons -----------------------------------------------------
    def raw_features(self, d: DropData, condition: str) -> np.ndarray:
        """Per-drop features (n, d), with only the columns the experiment records."""
        return self.release_features(d, self.x.condition(condition).protocol.yaw_deg)

    def release_features(self, d: DropData, yaw0: float) -> np.ndarray:
        """Per-drop features of drops released at yaw ``yaw0`` (deg)."""
        yaw = d.yaw_deg if "yaw_spread" in self.names else None
        tilt = d.tilt_deg if "tilt_q50" in self.names else None
        return drop_features(d.positions, yaw, tilt, yaw0, self.order)

    def set_metric(self, condition: str, experiment: DropData) -> None:
        """Fix the condition's feature scale from the experiment pooled with the baseline
        (a scale of the pooled drops leaves the permutation tests exact)."""
        pooled = np.vstack(
            [
                self.raw_features(experiment, condition),
                self.raw_features(self.drops[self.baseline(condition, None)], condition),
            ]
        )
        self.metric[condition] = FeatureMetric.of(
            pooled, "yaw_spread" in self.names, "tilt_q50" in self.names
        )

    def sim_weights(self, key: tuple) -> np.ndarray:
        """Bootstrap weights (1 + B, m) of the simulation ``key``: the same for every
        setting of a condition with as many drops (their drops share the release draws,
        so settings stay paired)."""
        condition, m = key[0], self.drops[key].n
        if (condition, m) not in self._sim_weights:
            rng = np.random.default_rng([self.seed, 19, self.index[condition], m])
            weights = resample_weights(m, self.x.settings.bootstrap, rng)
            self._sim_weights[condition, m] = weights
        return self._sim_weights[condition, m]

    def features(self, key: tuple) -> np.ndarray:
        """Standardised features (m, d) of the simulation ``key``."""
        if key not in self._features:
            raw = self.raw_features(self.drops[key], key[0])
            self._features[key] = self.metric[key[0]].apply(raw)
        return self._features[key]

    def within(self, key: tuple) -> np.ndarray:
        """Mean distance between distinct drops of ``key`` and of each resample (1 + B,)."""
        if key not in self._within:
            f = self.features(key)
            distances = self.metric[key[0]].distances(f).sum(axis=0)
            self._within[key] = mean_within(distances, self.sim_weights(key))
        return self._within[key]

    def cross(self, ds: Dataset, key: tuple) -> np.ndarray:
        """Distances (n, m) of the dataset's drops to the simulated drops of ``key``."""
        cache = (id(ds), key)
        if cache not in self._cross:
            blocks = self.metric[key[0]].distances(ds.features, self.features(key))
            self._cross[cache] = blocks.sum(axis=0)
        return self._cross[cache]

    def energy(self, ds: Dataset, key: tuple) -> np.ndarray:
        """The energy distance (U-statistic, standardised features) of the dataset to the
        simulation ``key``, then of each resample (1 + B,): a resample draws both the
        observed drops and the simulated ones, so intervals carry both noises. About 0
        when ``key`` is right, positive when it is not."""
        between = mean_cross(self.cross(ds, key), ds.weights, self.sim_weights(key))
        return energy_distance(between, ds.within, self.within(key))

    def scores(self, ds: Dataset, key: tuple) -> np.ndarray:
        """Each observed drop's energy score under the simulation ``key`` (n,): lower is a
        better prediction of that drop."""
        return self.cross(ds, key).mean(axis=1) - 0.5 * self.within(key)[0]


@dataclass
class Dataset:
    """The observed drops of one condition (or a part of them): their observables, their
    standardised features and bootstrap weights, and the mean distance between them."""

    condition: str
    data: DropData
    observed: np.ndarray  # (K,) observables
    features: np.ndarray  # (n, d) standardised by the condition's metric
    weights: np.ndarray  # (1 + B, n) bootstrap counts, row 0 the data themselves
    within: np.ndarray  # (1 + B,) mean distance between distinct drops

    @classmethod
    def observe(
        cls,
        condition: str,
        data: DropData,
        sims: DropSimulations,
        rng: np.random.Generator,
    ) -> Dataset:
        metric = sims.metric[condition]
        features = metric.apply(sims.raw_features(data, condition))
        weights = resample_weights(data.n, sims.x.settings.bootstrap, rng)
        within = mean_within(metric.distances(features).sum(axis=0), weights)
        return cls(condition, data, sims.observe(data, condition), features, weights, within)


def _longest_first(run_many: Callable[[Callable, list[dict]], list]):
    """``run_many`` with each batch's calls submitted longest first (and the results put
    back in order): workers take calls in the order given, so a long call left to the end
    of a batch keeps one worker busy while the other waits (longest processing time
    first). Each call carries its own seed, so the order changes no result. The cost
    estimate: drops, times the flight (the square root of the height) plus the bounces,
    times the costliest effect's declared ``simulation_cost``."""

    def cost(call: dict) -> float:
        protocol = call.get("protocol")
        height = getattr(protocol, "height_mm", 0.0)
        strengths = call.get("strengths") or {}
        factor = max(
            [EFFECTS.get(name).simulation_cost for name, v in strengths.items() if v], default=1.0
        )
        return call.get("n", 1) * (1.0 + math.sqrt(max(height, 0.0) / 200.0)) * factor

    def ordered(function: Callable, calls: list[dict]) -> list:
        order = sorted(range(len(calls)), key=lambda k: -cost(calls[k]))
        results = run_many(function, [calls[k] for k in order])
        out: list = [None] * len(calls)
        for k, result in zip(order, results, strict=True):
            out[k] = result
        return out

    return ordered
