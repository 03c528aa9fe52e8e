"""Where a drop experiment departs from its baseline simulation, with every test exact:
the labels (experiment, simulation) of a condition's drops are permuted, the same
permutations serving every statistic of the condition, so

- each condition gets a test of its whole distribution of drops: the energy statistics
  of the position, yaw and tilt blocks and of their sum, combined by max-T; and the
  experiment one overall test, stratified by condition (each statistic summed over the
  conditions under the same permutations, then max-T): the detection;
- every observable and every ring and sector of the scatter gets a permutation p-value,
  Holm-adjusted across all of them in every condition (one family), with a bootstrap
  interval of its difference and the noise floor (what 95 % of differences look like
  when there is no gap)."""

from __future__ import annotations

import numpy as np

from diagnosis.drop_simulations import Dataset, DropSimulations
from diagnosis.observables import anisotropy
from diagnosis.ranking import adjust_tests
from diagnosis.spec import DropData
from diagnosis.statistics import (
    PERMUTATIONS,
    energy_statistics,
    exceedance_p,
    holm,
    interval,
    max_t,
    permutation_masks,
    standardise,
)

__all__ = ["locate_gap", "energy_test"]

RING_QUANTILES = (0.25, 0.5, 0.75, 0.9)
SECTORS = 8


def locate_gap(
    full: dict[str, Dataset], sims: DropSimulations, rng: np.random.Generator, alpha: float
) -> dict:
    """The "where" section: the overall test, and per condition its test, observables
    and regions."""
    rows, tests, regions = [], [], []
    total = 0.0
    for c, ds in full.items():
        perm = _ConditionPermutations(ds, sims, sims.baseline(c, None), rng)
        total = total + perm.standardised
        tests.append(perm.test())
        rows += perm.observable_rows(rng)
        regions += perm.region_rows()
        sims.observable_sd[c] = perm.observable_sd
    adjust_tests(tests, alpha)
    adjusted = holm([r["p_value"] for r in rows + regions])
    for r, p in zip(rows + regions, adjusted, strict=True):
        r["p_holm"] = float(p)
        r["beyond_noise" if "observable" in r else "notable"] = bool(p < alpha)
    # Each statistic (block or total) summed over conditions under the same
    # permutations, then the largest: the detection, stratified by condition.
    overall_t = max_t(total)
    overall = dict(
        statistic=float(overall_t[0]),
        null_mean=float(overall_t[1:].mean()),
        p_value=exceedance_p(overall_t[1:], overall_t[0]),
        by_block={
            name: exceedance_p(total[k, 1:], total[k, 0])
            for k, name in enumerate(perm.statistic_names)
        },
        permutations=PERMUTATIONS,
    )
    overall["significant"] = overall["p_value"] < alpha
    return dict(overall=overall, tests=tests, observables=rows, regions=regions)


def block_statistics(distances: np.ndarray, masks: np.ndarray) -> np.ndarray:
    """Energy statistics (blocks + 1, R) of pooled drops under each labelling: one per
    block of features (``distances`` (blocks, N, N)), then their sum."""
    blocks = np.array([energy_statistics(d, masks) for d in distances])
    return np.vstack([blocks, blocks.sum(axis=0)])


def energy_test(ds: Dataset, sims: DropSimulations, key: tuple, rng: np.random.Generator):
    """The exact permutation test of the dataset against the simulation ``key``: the
    max-T of its blocks' and total energy statistics, and its p-value."""
    features = sims.features(key)
    pooled = np.vstack([ds.features, features])
    masks = permutation_masks(ds.data.n, len(features), PERMUTATIONS, rng)
    t = max_t(block_statistics(sims.metric[ds.condition].distances(pooled), masks))
    return t, exceedance_p(t[1:], t[0])


class _ConditionPermutations:
    """One condition's experiment pooled with its baseline simulation, and every
    statistic of it under the observed labelling and the same label permutations."""

    def __init__(self, ds: Dataset, sims: DropSimulations, key: tuple, rng: np.random.Generator):
        self.ds, self.sims, self.key = ds, sims, key
        self.sim = sims.drops[key]
        self.yaw0 = sims.x.condition(ds.condition).protocol.yaw_deg
        n, m = ds.data.n, self.sim.n
        self.pooled = DropData(
            np.vstack([ds.data.positions, self.sim.positions]),
            _joined(ds.data.yaw_deg, self.sim.yaw_deg),
            _joined(ds.data.tilt_deg, self.sim.tilt_deg),
        )
        pooled_features = np.vstack([ds.features, sims.features(key)])
        self.masks = permutation_masks(n, m, PERMUTATIONS, rng)
        metric = sims.metric[ds.condition]
        self.statistic_names = [*metric.blocks, "all"]
        stats = block_statistics(metric.distances(pooled_features), self.masks)
        self.energy = stats[-1]
        self.standardised = standardise(stats)
        self.t = self.standardised.max(axis=0)
        # Observable differences (experiment - simulation) under every labelling.
        self.differences = np.array(
            [
                sims.observe(self.pooled.take(mask), ds.condition)
                - sims.observe(self.pooled.take(~mask), ds.condition)
                for mask in self.masks
            ]
        )
        self.observable_sd = np.maximum(self.differences[1:].std(axis=0), 1e-12)

    def test(self) -> dict:
        ds, names = self.ds, self.sims.names
        exp_aniso = anisotropy(*_anisotropy_pair(ds.observed, names), self.yaw0)
        sim_aniso = anisotropy(*_anisotropy_pair(self.sims.observables[self.key], names), self.yaw0)
        return dict(
            condition=ds.condition,
            gap=float(self.energy[0]),
            null_mean=float(self.energy[1:].mean()),
            null_q95=float(np.percentile(self.energy[1:], 95)),
            max_t=float(self.t[0]),
            p_value=exceedance_p(self.t[1:], self.t[0]),
            p_by_block={
                name: exceedance_p(self.standardised[k, 1:], self.standardised[k, 0])
                for k, name in enumerate(self.statistic_names)
            },
            anisotropy_experiment=dict(strength=exp_aniso[0], axis_deg=exp_aniso[1]),
            anisotropy_simulation=dict(strength=sim_aniso[0], axis_deg=sim_aniso[1]),
        )

    def observable_rows(self, rng: np.random.Generator) -> list[dict]:
        ds, sims = self.ds, self.sims
        sim = sims.observables[self.key]
        boot = _bootstrap_differences(ds, self.sim, sims, rng)
        rows = []
        for k, name in enumerate(sims.names):
            d = float(self.differences[0, k])
            null = np.abs(self.differences[1:, k])
            rows.append(
                dict(
                    condition=ds.condition,
                    observable=name,
                    experiment=float(ds.observed[k]),
                    simulation=float(sim[k]),
                    difference=d,
                    ci95=list(interval(boot[:, k])),
                    noise_floor=float(np.percentile(null, 95)),
                    z=float(d / self.observable_sd[k]),
                    p_value=exceedance_p(null, abs(d)),
                )
            )
        return rows

    def region_rows(self) -> list[dict]:
        """Rings (by the pooled drops' distance quantiles) and 45-degree sectors: the
        share of drops in each, experiment against simulation."""
        positions = self.pooled.positions
        r = np.hypot(*positions.T)
        edges = np.concatenate([[0.0], np.quantile(r, RING_QUANTILES), [np.inf]])
        regions = []
        for lo, hi in zip(edges[:-1], edges[1:], strict=False):
            label = f"{lo:.0f}-{hi:.0f} mm" if np.isfinite(hi) else f"> {lo:.0f} mm"
            regions.append(("ring", label, (r >= lo) & (r < hi)))
        width = 360.0 / SECTORS
        # Centred on the chip's sides, so sector 0 straddles its x side.
        angle = (np.degrees(np.arctan2(positions[:, 1], positions[:, 0])) - self.yaw0) % 360.0
        sector = ((angle + width / 2) % 360.0 // width).astype(int)
        for k in range(SECTORS):
            regions.append(("sector", f"{k * width:.0f} deg from the chip's x side", sector == k))
        masks = self.masks.astype(float)
        n, m = self.ds.data.n, self.sim.n
        rows = []
        for kind, label, inside in regions:
            share_exp = masks @ inside / n
            share_sim = (1.0 - masks) @ inside / m
            diff = share_exp - share_sim
            sd = max(float(diff[1:].std()), 1e-12)
            rows.append(
                dict(
                    condition=self.ds.condition,
                    region=kind,
                    where=label,
                    experiment_share=float(share_exp[0]),
                    simulation_share=float(share_sim[0]),
                    z=float(diff[0] / sd),
                    p_value=exceedance_p(np.abs(diff[1:]), abs(diff[0])),
                )
            )
        return rows


def _joined(a: np.ndarray | None, b: np.ndarray | None) -> np.ndarray | None:
    return None if a is None or b is None else np.concatenate([a, b])


def _bootstrap_differences(
    ds: Dataset, sim: DropData, sims: DropSimulations, rng: np.random.Generator
) -> np.ndarray:
    """Observable differences (B, K) with the experiment's and the simulation's drops
    both resampled: their interval carries both noises."""
    resamples = sims.x.settings.bootstrap
    exp_draws = rng.integers(0, ds.data.n, size=(resamples, ds.data.n))
    sim_draws = rng.integers(0, sim.n, size=(resamples, sim.n))
    return np.array(
        [
            sims.observe(ds.data.take(i), ds.condition) - sims.observe(sim.take(j), ds.condition)
            for i, j in zip(exp_draws, sim_draws, strict=True)
        ]
    )


def _anisotropy_pair(values: np.ndarray, names: list[str]) -> tuple[float, float]:
    return float(values[names.index("aniso_c")]), float(values[names.index("aniso_s")])
