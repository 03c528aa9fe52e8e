"""Where a drop experiment departs from its baseline simulation, with every test exact.

The labels (experiment, simulation) of each condition's pooled drops are permuted
(``PERMUTATIONS`` times); row r of every condition's permutations together is one
labelling of the whole experiment, stratified by condition, and every statistic below is
computed under the observed labelling and under each of those rows, so all of them share
one exact joint null.

- Per condition: the energy statistics of the position, yaw and tilt blocks and of their
  sum, standardised by their nulls and combined by max-T; Holm across conditions.
- Targeted statistics: for each condition c and observable k the difference experiment
  minus simulation standardised by its permutation null's mean and sd, Z[c, k], taken
  two-sided (|Z|); for each observable the stratified sum over the C conditions,
  sum_c Z[c, k] / sqrt(C) (standardised again, two-sided), which gathers a shift in the
  same direction in every condition; for each ring and sector of every condition the
  standardised difference of its share of drops (two-sided).
- The detection: one max-T over the whole family (each block's energy statistic summed
  over the conditions and standardised, one-sided; the stratified sums; every |Z[c, k]|;
  every region's |Z|), the largest per permutation row, its p-value against the null
  rows' largest. The family-wise error is alpha under the exact stratified null, and a
  shift in one feature is found without being diluted into the omnibus statistic.
- "Where": every row of that family gets its Westfall-Young step-down max-T adjusted
  p-value from the same rows (``statistics.max_t_adjusted``); an observable is beyond the
  noise, a region notable, when it is below alpha, so the flags keep the family-wise
  error at alpha, and the detection is significant exactly when some row of the family
  is. Each row keeps its difference, direction, z, bootstrap interval and noise floor
  (what 95 % of differences look like when there is no gap). The report reads them
  hierarchically: each condition's test, then the observables flagged in it.
"""

from __future__ import annotations

import numpy as np

from chipstack.diagnosis.drop_simulations import Dataset, DropSimulations
from chipstack.diagnosis.model import DropData
from chipstack.diagnosis.observables import anisotropy
from chipstack.diagnosis.ranking import adjust_tests
from chipstack.diagnosis.statistics import (
    PERMUTATIONS,
    energy_statistics,
    exceedance_p,
    interval,
    max_t,
    max_t_adjusted,
    permutation_masks,
    standardise,
)

__all__ = ["locate_gap", "energy_test", "gap_family"]

RING_QUANTILES = (0.25, 0.5, 0.75, 0.9)
SECTORS = 8

# The parts of the family, in the order ``gap_family`` stacks them.
FAMILY_PARTS = ("energy", "across conditions", "per condition", "regions")


def locate_gap(
    full: dict[str, Dataset],
    sims: DropSimulations,
    rng: np.random.Generator,
    alpha: float,
    keys: dict[str, tuple] | None = None,
    permutations: int = PERMUTATIONS,
    intervals: bool = True,
) -> dict:
    """The "where" section: the overall test (the detection), per condition its test and
    the observables beyond the noise in it; every observable and region of every
    condition, and every observable across the conditions, with its adjusted p-value.
    Against the baseline simulation, or with ``keys`` (condition -> simulation key)
    against those simulations (a posterior-predictive check of a fitted model).
    ``permutations`` and ``intervals`` (the observables' bootstrap intervals) trade
    detail for time where only the overall p-value is wanted."""
    perms, tests, rows, regions = [], [], [], []
    for c, ds in full.items():
        key = keys[c] if keys else sims.baseline(c, None)
        perm = _ConditionPermutations(ds, sims, key, rng, permutations)
        perms.append(perm)
        tests.append(perm.test())
        rows.append(perm.observable_rows(rng, intervals))
        regions.append(perm.region_rows())
        if not keys:
            sims.observable_sd[c] = perm.observable_sd
    adjust_tests(tests, alpha)
    # Each block's energy statistic summed over conditions under the same permutations.
    total = sum(perm.standardised for perm in perms)
    labels, family = gap_family(total, [p.z for p in perms], [p.region_z for p in perms])
    adjusted = dict(zip(labels, max_t_adjusted(family), strict=True))
    for c, (t, own, shares) in enumerate(zip(tests, rows, regions, strict=True)):
        for k, r in enumerate(own):
            r["p_adjusted"] = float(adjusted[FAMILY_PARTS[2], c, k])
        for g, r in enumerate(shares):
            r["p_adjusted"] = float(adjusted[FAMILY_PARTS[3], c, g])
        for r in own + shares:
            r["beyond_noise" if "observable" in r else "notable"] = r["p_adjusted"] < alpha
        # The hierarchical reading: within the condition, what is off, surest first.
        t["observables_beyond_noise"] = [
            {k: r[k] for k in ("observable", "difference", "direction", "z", "p_adjusted")}
            for r in sorted(own, key=lambda r: (r["p_adjusted"], -abs(r["z"])))
            if r["beyond_noise"]
        ]
    across = [
        dict(row, p_adjusted=float(adjusted[FAMILY_PARTS[1], k]))
        for k, row in enumerate(_across_rows(perms, sims.names))
    ]
    for row in across:
        row["beyond_noise"] = row["p_adjusted"] < alpha
    described = _descriptions(labels, perms, rows, regions, across)
    overall = _overall(labels, family, described, total, perms[-1].statistic_names, alpha)
    return dict(
        overall=overall,
        tests=tests,
        across_conditions=across,
        observables=[r for own in rows for r in own],
        regions=[r for shares in regions for r in shares],
    )


def gap_family(
    energy: np.ndarray, z: list[np.ndarray], region_z: list[np.ndarray]
) -> tuple[list[tuple], np.ndarray]:
    """The statistics (S, R) of the detection and of "where", on a common scale, with
    their labels (part first, then indices). ``energy`` (B, R): each block's energy
    statistic summed over the conditions (one-sided, standardised here); ``z`` and
    ``region_z``: per condition the standardised signed differences (K, R) of the
    observables and (G, R) of the regions' shares, two-sided; the observables' stratified
    sums over conditions (two-sided) come between. Column r of every input must be the
    same labelling of the whole experiment (row 0 the observed one)."""
    conditions = len(z)
    stratified = standardise(np.sum(z, axis=0) / np.sqrt(conditions))
    parts = [
        ([(FAMILY_PARTS[0], b) for b in range(len(energy))], standardise(energy)),
        ([(FAMILY_PARTS[1], k) for k in range(len(stratified))], np.abs(stratified)),
        (
            [(FAMILY_PARTS[2], c, k) for c in range(conditions) for k in range(len(z[c]))],
            np.abs(np.vstack(z)),
        ),
        (
            [(FAMILY_PARTS[3], c, g) for c in range(conditions) for g in range(len(region_z[c]))],
            np.abs(np.vstack(region_z)),
        ),
    ]
    labels = [label for part, _ in parts for label in part]
    return labels, np.vstack([statistics for _, statistics in parts])


def _across_rows(perms: list[_ConditionPermutations], names: list[str]) -> list[dict]:
    """Every observable across the conditions: the stratified sum of its z-scores (its
    sign the direction), the mean of its differences, its raw p-value."""
    stratified = standardise(np.sum([p.z for p in perms], axis=0) / np.sqrt(len(perms)))
    rows = []
    for k, name in enumerate(names):
        z = stratified[k]
        rows.append(
            dict(
                observable=name,
                mean_difference=float(np.mean([p.differences[0, k] for p in perms])),
                direction=int(np.sign(z[0])),
                z=float(z[0]),
                p_value=exceedance_p(np.abs(z[1:]), abs(z[0])),
            )
        )
    return rows


def _descriptions(labels, perms, rows, regions, across) -> list[str]:
    """Each family label in words, the direction of a two-sided statistic with it."""

    def signed(row: dict) -> str:
        return f" ({'+-'[row['direction'] < 0]})" if row["direction"] else ""

    words = []
    for label in labels:
        part, *index = label
        if part == FAMILY_PARTS[0]:
            block = perms[0].statistic_names[index[0]]
            words.append(f"energy statistic ({block}) summed over the conditions")
        elif part == FAMILY_PARTS[1]:
            row = across[index[0]]
            words.append(f"{row['observable']} across the conditions{signed(row)}")
        elif part == FAMILY_PARTS[2]:
            row = rows[index[0]][index[1]]
            words.append(f"{row['observable']} in {row['condition']}{signed(row)}")
        else:
            row = regions[index[0]][index[1]]
            words.append(f"{row['region']} {row['where']} in {row['condition']}{signed(row)}")
    return words


def _overall(labels, family, described, total, block_names, alpha) -> dict:
    """The detection: the largest statistic of the family against the null rows'
    largest; each part's own max-T p-value; which statistic carried it."""
    largest = family.max(axis=0)
    by_statistic = {}
    for part in FAMILY_PARTS:
        rows = [i for i, label in enumerate(labels) if label[0] == part]
        if rows:
            t = family[rows].max(axis=0)
            by_statistic[part] = exceedance_p(t[1:], t[0])
    overall = dict(
        statistic=float(largest[0]),
        null_mean=float(largest[1:].mean()),
        p_value=exceedance_p(largest[1:], largest[0]),
        by_block={
            name: exceedance_p(total[k, 1:], total[k, 0]) for k, name in enumerate(block_names)
        },
        by_statistic=by_statistic,
        carried_by=described[int(np.argmax(family[:, 0]))],
        family_size=len(labels),
        permutations=len(largest) - 1,
    )
    overall["significant"] = overall["p_value"] < alpha
    return overall


def block_statistics(distances: np.ndarray, masks: np.ndarray) -> np.ndarray:
    """Energy statistics (blocks + 1, R) of pooled drops under each labelling: one per
    block of features (``distances`` (blocks, N, N)), then their sum."""
    blocks = np.array([energy_statistics(d, masks) for d in distances])
    return np.vstack([blocks, blocks.sum(axis=0)])


def energy_test(
    ds: Dataset,
    sims: DropSimulations,
    key: tuple,
    rng: np.random.Generator,
    permutations: int = PERMUTATIONS,
):
    """The exact permutation test of the dataset against the simulation ``key``: the
    max-T of its blocks' and total energy statistics, and its p-value."""
    features = sims.features(key)
    pooled = np.vstack([ds.features, features])
    masks = permutation_masks(ds.data.n, len(features), permutations, rng)
    t = max_t(block_statistics(sims.metric[ds.condition].distances(pooled), masks))
    return t, exceedance_p(t[1:], t[0])


class _ConditionPermutations:
    """One condition's experiment pooled with its baseline simulation, and every
    statistic of it under the observed labelling and the same label permutations."""

    def __init__(
        self,
        ds: Dataset,
        sims: DropSimulations,
        key: tuple,
        rng: np.random.Generator,
        permutations: int = PERMUTATIONS,
    ):
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
        self.masks = permutation_masks(n, m, permutations, rng)
        metric = sims.metric[ds.condition]
        self.statistic_names = [*metric.blocks, "all"]
        stats = block_statistics(metric.distances(pooled_features), self.masks)
        self.energy = stats[-1]
        self.standardised = standardise(stats)
        self.t = self.standardised.max(axis=0)
        # Observable differences (experiment - simulation) under every labelling.
        rows = len(self.masks)
        experiment_side = np.nonzero(self.masks)[1].reshape(rows, n)
        simulation_side = np.nonzero(~self.masks)[1].reshape(rows, m)
        self.differences = sims.observe_many(
            self.pooled, experiment_side, ds.condition
        ) - sims.observe_many(self.pooled, simulation_side, ds.condition)
        self.observable_sd = np.maximum(self.differences[1:].std(axis=0), 1e-12)
        # Each difference standardised by its null's mean and sd (K, R); a quantile of
        # the smaller sample is biased even without a gap, and the mean takes that out.
        self.z = standardise(self.differences.T)
        self.regions = self._regions()
        share_exp, share_sim = self._shares()
        self.region_shares = share_exp[0], share_sim[0]
        self.region_z = standardise((share_exp - share_sim).T)  # (G, R)

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

    def observable_rows(self, rng: np.random.Generator, intervals: bool = True) -> list[dict]:
        ds, sims = self.ds, self.sims
        sim = sims.observables[self.key]
        boot = (
            _bootstrap_differences(ds, self.sim, sims, rng)
            if intervals
            else np.full((2, len(sims.names)), np.nan)
        )
        rows = []
        for k, name in enumerate(sims.names):
            d = float(self.differences[0, k])
            z = self.z[k]
            rows.append(
                dict(
                    condition=ds.condition,
                    observable=name,
                    experiment=float(ds.observed[k]),
                    simulation=float(sim[k]),
                    difference=d,
                    direction=int(np.sign(d)),
                    ci95=list(interval(boot[:, k])) if intervals else [None, None],
                    noise_floor=float(np.percentile(np.abs(self.differences[1:, k]), 95)),
                    z=float(z[0]),
                    p_value=exceedance_p(np.abs(z[1:]), abs(z[0])),
                )
            )
        return rows

    def _regions(self) -> list[tuple[str, str, np.ndarray]]:
        """Rings (by the pooled drops' distance quantiles) and 45-degree sectors: (kind,
        label, which pooled drops lie in it)."""
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
        return regions

    def _shares(self) -> tuple[np.ndarray, np.ndarray]:
        """Each region's share of the experiment's and of the simulation's drops under
        every labelling: (R, G) each."""
        inside = np.column_stack([r[2] for r in self.regions]).astype(float)
        masks = self.masks.astype(float)
        n, m = self.ds.data.n, self.sim.n
        return masks @ inside / n, (1.0 - masks) @ inside / m

    def region_rows(self) -> list[dict]:
        """Every region: the share of drops in it, experiment against simulation."""
        share_exp, share_sim = self.region_shares
        rows = []
        for g, (kind, label, _) in enumerate(self.regions):
            z = self.region_z[g]
            difference = float(share_exp[g] - share_sim[g])
            rows.append(
                dict(
                    condition=self.ds.condition,
                    region=kind,
                    where=label,
                    experiment_share=float(share_exp[g]),
                    simulation_share=float(share_sim[g]),
                    difference=difference,
                    direction=int(np.sign(difference)),
                    z=float(z[0]),
                    p_value=exceedance_p(np.abs(z[1:]), abs(z[0])),
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
    return sims.observe_many(ds.data, exp_draws, ds.condition) - sims.observe_many(
        sim, sim_draws, ds.condition
    )


def _anisotropy_pair(values: np.ndarray, names: list[str]) -> tuple[float, float]:
    return float(values[names.index("aniso_c")]), float(values[names.index("aniso_s")])
