"""Where a drop experiment departs from its baseline simulation: every observable of
every condition with a bootstrap interval and the noise floor, an overall test per
condition, and the rings and sectors of the scatter whose share of drops differs."""

from __future__ import annotations

import numpy as np

from diagnosis.drop_simulations import Dataset, DropSimulations
from diagnosis.observables import anisotropy
from diagnosis.ranking import adjust_tests
from diagnosis.spec import DropData
from diagnosis.statistics import energy_test, interval

__all__ = ["locate_gap"]

PERMUTATIONS = 300
RING_QUANTILES = (0.25, 0.5, 0.75, 0.9)
SECTORS = 8


def locate_gap(
    full: dict[str, Dataset], sims: DropSimulations, rng: np.random.Generator, alpha: float
) -> dict:
    """The "where" section: observables, overall tests and regions of every condition."""
    rows, tests, regions = [], [], []
    for c, ds in full.items():
        protocol = sims.x.condition(c).protocol
        key = sims.baseline(c, protocol.tilt_deg)
        rows += _observable_rows(ds, sims, key, rng)
        tests.append(_overall_test(ds, sims, key, protocol.yaw_deg, rng))
        regions += _regions(ds, sims.drops[key], protocol.yaw_deg)
    adjust_tests(tests, alpha)
    return dict(observables=rows, tests=tests, regions=regions)


def _observable_rows(
    ds: Dataset, sims: DropSimulations, key: tuple, rng: np.random.Generator
) -> list[dict]:
    sim = sims.observables[key]
    # The resamples carry the experiment's noise only; jitter of the simulation's standard
    # error adds its own, so the interval covers both.
    sim_se = ds.scale / np.sqrt(1 + ds.data.n / sims.n) * np.sqrt(ds.data.n / sims.n)
    jitter = rng.normal(size=ds.resampled.shape) * sim_se
    diffs = ds.resampled - sim - jitter
    rows = []
    for k, name in enumerate(sims.names):
        d = float(ds.observed[k] - sim[k])
        lo, hi = interval(diffs[:, k])
        beyond = abs(d) > ds.floor[k] and (lo > 0 or hi < 0)
        rows.append(
            dict(
                condition=ds.condition,
                observable=name,
                experiment=float(ds.observed[k]),
                simulation=float(sim[k]),
                difference=d,
                ci95=[lo, hi],
                noise_floor=float(ds.floor[k]),
                z=float(d / ds.scale[k]),
                beyond_noise=bool(beyond),
            )
        )
    return rows


def _overall_test(
    ds: Dataset, sims: DropSimulations, key: tuple, yaw0: float, rng: np.random.Generator
) -> dict:
    g = sims.gap(ds, key)
    e_stat, e_p = energy_test(ds.data.positions, sims.drops[key].positions, PERMUTATIONS, rng)
    exp_aniso = anisotropy(*_anisotropy_pair(ds.observed, sims.names), yaw0)
    sim_aniso = anisotropy(*_anisotropy_pair(sims.observables[key], sims.names), yaw0)
    return dict(
        condition=ds.condition,
        gap=g,
        null_mean=ds.expected_null,
        null_q95=float(np.percentile(ds.null, 95)),
        p_gap=ds.p_value(g),
        # Two omnibus tests (the gap statistic against its measured null; the energy
        # distance of the scatters), Bonferroni-combined.
        p_value=min(1.0, 2 * min(ds.p_value(g), e_p)),
        energy_statistic=e_stat,
        energy_p_value=e_p,
        anisotropy_experiment=dict(strength=exp_aniso[0], axis_deg=exp_aniso[1]),
        anisotropy_simulation=dict(strength=sim_aniso[0], axis_deg=sim_aniso[1]),
    )


def _anisotropy_pair(values: np.ndarray, names: list[str]) -> tuple[float, float]:
    return float(values[names.index("aniso_c")]), float(values[names.index("aniso_s")])


def _regions(ds: Dataset, sim: DropData, yaw0: float) -> list[dict]:
    """Rings (by the simulation's distance quantiles) and 45-degree sectors: the share
    of drops in each, experiment against simulation."""
    out = _rings(ds.condition, ds.data.positions, sim.positions)
    out += _sectors(ds.condition, ds.data.positions, sim.positions, yaw0)
    threshold = _bonferroni_z(len(out))
    for row in out:
        row["notable"] = abs(row["z"]) > threshold
    return out


def _rings(condition: str, experiment: np.ndarray, simulation: np.ndarray) -> list[dict]:
    r_sim = np.hypot(*simulation.T)
    r_exp = np.hypot(*experiment.T)
    edges = np.concatenate([[0.0], np.quantile(r_sim, RING_QUANTILES), [np.inf]])
    rows = []
    for lo, hi in zip(edges[:-1], edges[1:], strict=False):
        label = f"{lo:.0f}-{hi:.0f} mm" if np.isfinite(hi) else f"> {lo:.0f} mm"
        in_exp, in_sim = (r_exp >= lo) & (r_exp < hi), (r_sim >= lo) & (r_sim < hi)
        rows.append(_share_row(condition, "ring", label, in_exp, in_sim))
    return rows


def _sectors(
    condition: str, experiment: np.ndarray, simulation: np.ndarray, yaw0: float
) -> list[dict]:
    width = 360.0 / SECTORS

    def sector(p):
        # Centred on the chip's sides, so sector 0 straddles its x side.
        angle = (np.degrees(np.arctan2(p[:, 1], p[:, 0])) - yaw0 + width / 2) % 360.0
        return (angle // width).astype(int)

    s_exp, s_sim = sector(experiment), sector(simulation)
    labels = [f"{k * width:.0f} deg from the chip's x side" for k in range(SECTORS)]
    return [
        _share_row(condition, "sector", label, s_exp == k, s_sim == k)
        for k, label in enumerate(labels)
    ]


def _share_row(
    condition: str, kind: str, label: str, in_exp: np.ndarray, in_sim: np.ndarray
) -> dict:
    """The two shares of drops in a region and the two-proportion z of their difference."""
    n, m = len(in_exp), len(in_sim)
    p_e, p_s = in_exp.mean(), in_sim.mean()
    pooled = (in_exp.sum() + in_sim.sum()) / (n + m)
    se = np.sqrt(max(pooled * (1 - pooled), 1e-12) * (1 / n + 1 / m))
    return dict(
        condition=condition,
        region=kind,
        where=label,
        experiment_share=float(p_e),
        simulation_share=float(p_s),
        z=float((p_e - p_s) / se),
    )


def _bonferroni_z(m: int, alpha: float = 0.05) -> float:
    from scipy.stats import norm

    return float(norm.ppf(1 - alpha / (2 * m)))
