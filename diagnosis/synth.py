"""Pseudo-experimental data: the simulation with chosen effects switched on, written in
the observation formats, so a diagnosis can be checked on data whose cause is known."""

from __future__ import annotations

import numpy as np

from chipstack.diagnosis.drops import simulate_condition
from chipstack.diagnosis.model import Experiment
from chipstack.packing.effects import check_effects

__all__ = ["synthesize_drops", "SYNTH_SEED_OFFSET"]

SYNTH_SEED_OFFSET = 10_000_000  # keeps synthetic draws apart from the diagnosis's own


def synthesize_drops(
    experiment: Experiment,
    strengths: dict[str, float],
    seed: int,
    drops: int,
    run_many=None,
) -> list[dict]:
    """Rows ``condition, drop, x_mm, y_mm, yaw_deg, tilt_deg`` for every condition of the
    spec, ``drops`` each, with the spec's measurement noise."""
    strengths = check_effects(strengths, "drop", key="--effect")
    calls = [
        dict(
            scenario=experiment.scenario,
            protocol=condition.protocol,
            n=drops,
            strengths=strengths,
            seed=SYNTH_SEED_OFFSET + 1000 * int(seed) + k,
            position_sd_mm=experiment.position_sd_mm,
            angle_sd_deg=experiment.angle_sd_deg,
        )
        for k, condition in enumerate(experiment.conditions)
    ]
    results = (
        run_many(simulate_condition, calls)
        if run_many
        else [simulate_condition(**c) for c in calls]
    )
    rows = []
    for condition, data in zip(experiment.conditions, results, strict=True):
        for k in range(drops):
            rows.append(
                dict(
                    condition=condition.name,
                    drop=k + 1,
                    x_mm=float(np.round(data.positions[k, 0], 4)),
                    y_mm=float(np.round(data.positions[k, 1], 4)),
                    yaw_deg=float(np.round(data.yaw_deg[k], 3)),
                    tilt_deg=float(np.round(data.tilt_deg[k], 3)),
                )
            )
    return rows
