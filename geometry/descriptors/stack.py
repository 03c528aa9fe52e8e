"""The whole stack: height, bulk volume fraction, bare and uneven target area."""

from __future__ import annotations

from typing import Any

import numpy as np

from chipstack.geometry.descriptors.base import (
    Context,
    Descriptor,
    scalar,
)
from chipstack.geometry.solids import target_prism


def _stack_headline(section: dict[str, Any]) -> str:
    s = section["scalars"]
    return (
        f"mean height {s['height_mean_mm']['value']:.1f} mm, "
        f"volume fraction {s['volume_fraction']['value']:.3f}"
    )


def _stack(ctx: Context):
    a = ctx.final
    maps = ctx.rays
    on = maps.grid.on_target
    top = maps.top_mm[on]
    neh = maps.neh[on]
    height_max = float(a.bounds[:, 1, 2].max()) if a.n_chips else 0.0
    height_mean = float(top.mean()) if len(top) else 0.0
    area = a.target_size_mm**2
    solid = (ctx.union ^ target_prism(a.target_size_mm, 0.0, height_max + 1.0)).volume()
    # Solid and envelope sampled by the same rays, so the ratio cannot pass 1 by sampling.
    sampled_solid = float(np.minimum(maps.solid_mm[on], top).sum())
    envelope = float(top.sum())
    scalars = {
        "height_max_mm": scalar(height_max, "mm", "highest point of any chip"),
        "height_mean_mm": scalar(
            height_mean, "mm", "mean over the target's pixels of the top surface (0 if bare)"
        ),
        "solid_volume_over_target_mm3": scalar(
            solid, "mm3", "solid inside the target prism above the conveyor (exact)"
        ),
        "volume_fraction": scalar(
            sampled_solid / envelope if envelope > 0 else 0.0,
            "",
            "bulk volume fraction: solid / volume under the top surface, over the target "
            "(both sampled by the NEH rays)",
        ),
        "volume_fraction_max_height": scalar(
            solid / (area * height_max) if height_max > 0 else 0.0,
            "",
            "exact solid over the target / (target area x maximum height)",
        ),
        "bare_fraction": scalar(
            np.mean(neh == 0) if len(neh) else 1.0, "", "share of target pixels with no chip"
        ),
        "neh_cv": scalar(
            neh.std() / neh.mean() if len(neh) and neh.mean() > 0 else 0.0,
            "",
            "coefficient of variation (sd / mean) of NEH over the target",
        ),
        "chips_outside_target": scalar(
            np.sum(~a.inside_target()), "chips", "chips whose centre is off the target"
        ),
    }
    return None, {"scalars": scalars, "profiles": {}}


DESCRIPTOR = Descriptor(
    "stack",
    "height, bulk volume fraction, bare and uneven target area",
    headline=_stack_headline,
    ensemble_scalars=("height_max_mm", "volume_fraction"),
    order=30,
    compute=_stack,
)
