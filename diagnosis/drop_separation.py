"""Which release condition would tell two tied models apart, and with how many drops.

Each model (an effect at the strength fitted on every condition) is simulated at every
candidate release (heights and yaws around the spec's, at its release tilt); at each,
the energy distance between the two models' drops (the same features and metric as the
detection) and the spread of its permutation null give the number of drops per
condition at which the detection test would tell them apart: the expected statistic
grows as n times the distance, its null keeps the same spread, so one-sided 5 % with
80 % power needs n = (1.645 + 0.842) sd0 / distance.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from diagnosis.drop_simulations import DropSimulations
from diagnosis.observables import FeatureMetric
from diagnosis.statistics import (
    energy_distance,
    energy_statistics,
    mean_cross,
    mean_within,
    permutation_masks,
)

__all__ = ["CANDIDATE_HEIGHTS_MM", "CANDIDATE_YAWS_DEG", "separating_releases"]

CANDIDATE_HEIGHTS_MM = (150.0, 300.0, 600.0, 1000.0)
CANDIDATE_YAWS_DEG = (0.0, 45.0)
SEPARATION_DROPS = 60  # simulated drops per model and candidate release
NULL_PERMUTATIONS = 199
Z_ALPHA_PLUS_POWER = 1.645 + 0.842  # one-sided 5 %, power 80 %


def separating_releases(
    sims: DropSimulations,
    strengths: dict[str, float],
    best: str,
    offsets: dict[str, float] | None = None,
) -> dict[str, dict]:
    """For every model of ``strengths`` (effect -> fitted strength) other than ``best``:
    the candidate release that separates it from ``best`` with the fewest drops. Each
    model is released at the spec's tilt plus its fitted offset (``offsets``, deg)."""
    spec = sims.x.conditions[0].protocol
    candidates = [
        replace(spec, height_mm=h, yaw_deg=y)
        for h in CANDIDATE_HEIGHTS_MM
        for y in CANDIDATE_YAWS_DEG
    ]
    index, calls = [], []
    for j, protocol in enumerate(candidates):
        for effect, strength in strengths.items():
            index.append((j, effect))
            calls.append(
                dict(
                    scenario=sims.x.scenario,
                    protocol=replace(
                        protocol, tilt_deg=protocol.tilt_deg + (offsets or {}).get(effect, 0.0)
                    ),
                    n=SEPARATION_DROPS,
                    strengths={effect: strength},
                    # Common random numbers across the models of one release.
                    seed=int(sims.seed) * 1000 + 500 + 10 * j + 3,
                    position_sd_mm=sims.x.position_sd_mm,
                    angle_sd_deg=sims.x.angle_sd_deg,
                )
            )
    sims.progress(f"simulating {len(calls)} x {SEPARATION_DROPS} drops at candidate releases")
    drops = dict(zip(index, sims.run_many(sims.simulate, calls), strict=True))
    rng = np.random.default_rng([sims.seed, 23])
    out = {}
    for other in strengths:
        if other == best:
            continue
        rows = []
        for j, protocol in enumerate(candidates):
            a = sims.release_features(drops[(j, best)], protocol.yaw_deg)
            b = sims.release_features(drops[(j, other)], protocol.yaw_deg)
            distance, needed = _drops_needed(sims, a, b, rng)
            rows.append((needed, j, distance))
        needed, j, distance = min(rows)
        out[other] = dict(
            height_mm=candidates[j].height_mm,
            yaw_deg=candidates[j].yaw_deg,
            tilt_deg=candidates[j].tilt_deg,
            energy_distance=distance,
            drops_needed_per_condition=None if math.isinf(needed) else int(needed),
        )
    return out


def _drops_needed(sims: DropSimulations, a: np.ndarray, b: np.ndarray, rng) -> tuple[float, float]:
    """The energy distance (U-statistic) of two models' raw features at one release, and
    the drops per condition that would separate them (inf when they do not differ)."""
    metric = FeatureMetric.of(
        np.vstack([a, b]), "yaw_spread" in sims.names, "tilt_q50" in sims.names
    )
    pooled = metric.apply(np.vstack([a, b]))
    distances = metric.distances(pooled).sum(axis=0)
    n = len(a)
    one_a, one_b = np.ones((1, n)), np.ones((1, len(b)))
    distance = float(
        energy_distance(
            mean_cross(distances[:n, n:], one_a, one_b),
            mean_within(distances[:n, :n], one_a),
            mean_within(distances[n:, n:], one_b),
        )[0]
    )
    null = energy_statistics(distances, permutation_masks(n, len(b), NULL_PERMUTATIONS, rng))[1:]
    if distance <= 0:
        return distance, math.inf
    return distance, float(np.ceil(Z_ALPHA_PLUS_POWER * null.std() / distance))
