"""Chip tilt, in-plane direction and fibre orientation tensors, whole and by layer."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from chipstack.export.tables import fmt
from chipstack.geometry.descriptors.base import (
    Context,
    Descriptor,
    profile,
    scalar,
)
from chipstack.geometry.orientation import (
    fibre_directions_world,
    fibre_tensor,
    in_plane_direction_deg,
    tilt_deg,
)

TILT_BINS_DEG = np.arange(0.0, 91.0, 10.0)
DIRECTION_BINS_DEG = np.arange(0.0, 181.0, 15.0)


@dataclass(frozen=True)
class Orientation:
    tilt_deg: np.ndarray
    direction_deg: np.ndarray
    tensor: np.ndarray
    layer_tensors: dict[int, np.ndarray] = field(default_factory=dict)


def _orientation(ctx: Context):
    a = ctx.final
    tilt = tilt_deg(a.rotations)
    direction = in_plane_direction_deg(a.rotations)
    vectors, owners = fibre_directions_world(a)
    tensor = fibre_tensor(vectors, owners)
    layer = np.maximum(np.floor(a.positions[:, 2] / ctx.spec.layer_mm), 0).astype(int)
    layer_tensors = {}
    for k in np.unique(layer):
        mine = np.isin(owners, np.flatnonzero(layer == k))
        layer_tensors[int(k)] = fibre_tensor(vectors[mine], owners[mine])
    eigen = np.sort(np.linalg.eigvalsh(tensor))[::-1]
    scalars = {
        "tilt_mean_deg": scalar(tilt.mean() if len(tilt) else 0, "deg", "mean chip tilt"),
        "tilt_sd_deg": scalar(tilt.std(ddof=1) if len(tilt) > 1 else 0, "deg", "tilt sd"),
        "flat_fraction": scalar(
            np.mean(tilt < 5.0) if len(tilt) else 0, "", "share of chips tilted under 5 deg"
        ),
    }
    for i, j in ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2)):
        name = "xyz"[i] + "xyz"[j]
        scalars[f"a_{name}"] = scalar(tensor[i, j], "", f"fibre orientation tensor A_{name}")
    for k, value in enumerate(eigen):
        scalars[f"a_eigen_{k + 1}"] = scalar(value, "", f"eigenvalue {k + 1} of A")
    histogram = np.histogram(tilt, TILT_BINS_DEG)[0] / max(len(tilt), 1)
    layers = sorted(layer_tensors)
    profiles = {
        "tilt_histogram": profile(
            [float(v) for v in TILT_BINS_DEG[:-1]],
            histogram,
            "tilt bin start (deg)",
            "",
            "share of chips in 10 deg bins of tilt",
        ),
        "direction_histogram": profile(
            [float(v) for v in DIRECTION_BINS_DEG[:-1]],
            np.histogram(direction[np.isfinite(direction)], DIRECTION_BINS_DEG)[0]
            / max(int(np.isfinite(direction).sum()), 1),
            "direction bin start (deg)",
            "",
            "share of chips in 15 deg bins of in-plane direction (local x seen from above)",
        ),
    }
    for i, j in ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2)):
        name = "xyz"[i] + "xyz"[j]
        profiles[f"a_{name}_by_layer"] = profile(
            layers,
            [layer_tensors[k][i, j] for k in layers],
            "layer",
            "",
            f"component A_{name} of the fibre tensor of the chips whose centre is in the layer",
            pad=None,
        )
    record = Orientation(tilt, direction, tensor, layer_tensors)
    return record, {"scalars": scalars, "profiles": profiles}


DESCRIPTOR = Descriptor(
    "orientation",
    "chip tilt, in-plane direction and fibre orientation tensors",
    chip_columns=lambda o: {
        "tilt_deg": [fmt(v) for v in o.tilt_deg],
        "direction_deg": [fmt(v) for v in o.direction_deg],
    },
    order=10,
    compute=_orientation,
)
