"""The two kinds of drop sample a drop diagnosis compares: the simulated settings it runs
(kept, with their observables) and the observed drops of a condition (with the bootstrap
resamples, scales and noise floor that make gaps comparable)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from diagnosis.observables import drop_observables, symmetry_order
from diagnosis.spec import DropData, Experiment
from diagnosis.statistics import bootstrap_indices, exceedance_p, gap_statistic
from packing.effects import EFFECTS, contact_model
from packing.presets import PRESETS

__all__ = ["Dataset", "DropSimulations", "NULL_REPLICAS", "NOISE_POOL"]

NULL_REPLICAS = 400

# The setting without any effect, and the pool every fitted setting is drawn from; pool
# "B" is an independent second baseline that measures the simulation's own noise.
BASELINE_POOL = "A"
NOISE_POOL = "B"


TILT_GRID_DEG = (0.0, 2.5, 5.0, 7.5, 10.0, 15.0, 20.0)


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
    ):
        self.x = experiment
        self.names = names
        chip = experiment.scenario.chips[0]
        self.order = symmetry_order(chip.length_mm, chip.width_mm, chip.shape)
        self.simulate = simulate
        self.run_many = run_many
        self.seed = seed
        self.progress = progress
        self.index = {c.name: k for k, c in enumerate(experiment.conditions)}
        self.drops: dict[tuple, DropData] = {}
        self.observables: dict[tuple, np.ndarray] = {}
        self._resampled: dict[tuple, np.ndarray] = {}
        self._resample_indices: np.ndarray | None = None
        self.n = experiment.settings.sim_drops
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
        calls = [self._call(*key) for key in keys]
        self.progress(f"simulating {len(keys)} x {self.n} drops")
        for key, result in zip(keys, self.run_many(self.simulate, calls), strict=True):
            self.drops[key] = result
            self.observables[key] = self.observe(result, key[0])

    def _call(self, condition: str, tilt: float, effect: str | None, strength: float, pool: str):
        return dict(
            scenario=self.x.scenario,
            protocol=replace(self.x.condition(condition).protocol, tilt_deg=tilt),
            n=self.n,
            strengths={effect: strength} if effect else {},
            seed=self._seed(condition, pool),
            position_sd_mm=self.x.position_sd_mm,
            angle_sd_deg=self.x.angle_sd_deg,
        )

    def _seed(self, condition: str, pool: str) -> int:
        # Common random numbers: every setting of a condition uses the same draws.
        pool_offset = 1 if pool == BASELINE_POOL else 2
        return int(self.seed) * 1000 + 10 * self.index[condition] + pool_offset

    def observe(self, d: DropData, condition: str) -> np.ndarray:
        yaw0 = self.x.condition(condition).protocol.yaw_deg
        return drop_observables(d.positions, d.yaw_deg, d.tilt_deg, yaw0, self.order, self.names)

    # -- gaps ----------------------------------------------------------------------------
    def resampled(self, key: tuple) -> np.ndarray:
        """Observables (B, K) of the simulation ``key`` resampled: the same drop indices for
        every setting, so settings stay paired (their drops share the release draws)."""
        if key not in self._resampled:
            if self._resample_indices is None:
                rng = np.random.default_rng([self.seed, 19])
                self._resample_indices = bootstrap_indices(self.n, self.x.settings.bootstrap, rng)
            d = self.drops[key]
            self._resampled[key] = np.array(
                [self.observe(d.take(i), key[0]) for i in self._resample_indices]
            )
        return self._resampled[key]

    def gap(self, ds: Dataset, key: tuple) -> float:
        """G of the observed dataset against the simulation ``key``."""
        return float(gap_statistic(ds.observed, self.observables[key], ds.scale))

    def gaps(self, ds: Dataset, key: tuple) -> np.ndarray:
        """G of the dataset and of each resample, (1 + B,). A resample draws both the
        observed drops and the simulated ones, so intervals carry the simulation's noise."""
        sim = self.observables[key]
        return np.concatenate(
            [
                [gap_statistic(ds.observed, sim, ds.scale)],
                gap_statistic(ds.resampled, self.resampled(key), ds.scale),
            ]
        )


@dataclass
class Dataset:
    """The observed drops of one condition (or a part of them) and their statistics."""

    condition: str
    data: DropData
    observed: np.ndarray  # (K,)
    resampled: np.ndarray  # (B, K)
    scale: np.ndarray | None = None  # (K,) standard error of exp - sim
    null: np.ndarray | None = None  # (R,) G of independent replicas
    floor: np.ndarray | None = None  # (K,) 95 % of |replica - sim|

    @classmethod
    def observe(
        cls,
        condition: str,
        data: DropData,
        sims: DropSimulations,
        rng: np.random.Generator,
    ) -> Dataset:
        """The observables of ``data`` and of its bootstrap resamples (not calibrated)."""
        boot = bootstrap_indices(data.n, sims.x.settings.bootstrap, rng)
        resampled = np.array([sims.observe(data.take(b), condition) for b in boot])
        return cls(condition, data, sims.observe(data, condition), resampled)

    def calibrate(self, sims: DropSimulations, rng: np.random.Generator) -> None:
        """Scales and noise floor from the baseline's two independent pools: replicas of
        the experiment's size drawn from pool B, compared with pool A, are what a gap
        looks like when there is none."""
        a = sims.baseline(self.condition, None)
        b = sims.baseline(self.condition, None, NOISE_POOL)
        self.scale, self.null, self.floor = self.noise_floor(sims, a, b, rng)

    def noise_floor(
        self, sims: DropSimulations, key_a: tuple, key_b: tuple, rng: np.random.Generator
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(scales (K,), null G (R,), 95 % floor (K,)) of this dataset against the model
        simulated twice, independently, as ``key_a`` and ``key_b``: replicas of the
        experiment's size drawn from pool B, compared with pool A, are what a gap looks
        like when the model is right."""
        sim_a = sims.observables[key_a]
        b = sims.drops[key_b]
        n = self.data.n
        # Replicas of the experiment's own size, drawn with replacement from pool B (also
        # when the experiment has more drops than the pool: cutting them to the pool's
        # size would make the null's replicas smaller than the experiment).
        draws = rng.integers(0, len(b.positions), size=(NULL_REPLICAS, n))
        replicas = np.array([sims.observe(b.take(i), self.condition) for i in draws])
        spread = np.maximum(self.resampled.std(axis=0), replicas.std(axis=0))
        spread = np.maximum(spread, 1e-6 * (1 + np.abs(sim_a)))
        scale = spread * np.sqrt(1 + n / sims.n)
        null = gap_statistic(replicas, sim_a, scale)
        floor = np.percentile(np.abs(replicas - sim_a), 95, axis=0)
        return scale, null, floor

    @property
    def expected_null(self) -> float:
        return float(self.null.mean())

    def p_value(self, g: float) -> float:
        return exceedance_p(self.null, g)
