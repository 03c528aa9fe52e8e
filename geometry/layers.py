"""Layer filling (paper section 3.1.3) and the porosity profile through the thickness.

The paper's descriptor: the stack is cut into layers of ``layer_mm`` (2 mm) from the
conveyor up, and each chip is counted once, in the layer holding its centre of mass,
whatever its orientation. A full layer holds ``target area / chip area`` chips (56 for
20 mm squares on a 150 mm target).

Beyond the paper, from exact slabs of the union of the chips clipped to the target prism:
the solid volume fraction of each layer (1 - porosity) and its covered area fraction (the
share of the target that the layer's solid covers seen from above).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import manifold3d as m3
import numpy as np

from chipstack.core.arrangement import Arrangement
from chipstack.core.errors import InputError
from chipstack.geometry.solids import target_prism

__all__ = ["LayerFilling", "layer_counts", "full_layer_count", "slab_fractions"]


def _check_layer(layer_mm: float) -> None:
    if not (math.isfinite(layer_mm) and layer_mm > 0):
        raise InputError(f"layer_mm: must be positive, got {layer_mm!r}")


def layer_counts(
    heights_mm: np.ndarray, layer_mm: float = 2.0, n_layers: int | None = None
) -> np.ndarray:
    """(L,) int: chips per layer, a chip in layer ``floor(z / layer_mm)`` of its centre z (mm).

    Centres below the conveyor (z < 0, only from numerical interpenetration) count in
    layer 0. ``n_layers`` pads or fixes the length (counts above it are an error).
    """
    _check_layer(layer_mm)
    z = np.asarray(heights_mm, dtype=float)
    index = np.maximum(np.floor(z / layer_mm), 0).astype(np.int64)
    size = int(index.max()) + 1 if len(index) else 0
    if n_layers is not None:
        if size > n_layers:
            raise InputError(f"n_layers: {n_layers} layers cannot hold a centre at {z.max():g} mm")
        size = n_layers
    return np.bincount(index, minlength=size)


def full_layer_count(target_size_mm: float, chip_area_mm2: float) -> float:
    """Chips that tile the target once: target area / chip area (56.25 for 20 mm on 150 mm)."""
    return target_size_mm**2 / chip_area_mm2


def slab_fractions(
    union: m3.Manifold, target_size_mm: float, edges_mm: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Solid volume fraction and covered area fraction of slabs over the target.

    ``union`` is the solid of the stack (mm); ``edges_mm`` (L + 1,) the slab boundaries.
    Returns two (L,) arrays: volume of solid in the slab over the target divided by the
    slab's volume over the target; area of the slab's solid projected on the plane divided
    by the target's area. Dimensionless, between 0 and 1.
    """
    edges = np.asarray(edges_mm, dtype=float)
    area = float(target_size_mm) ** 2
    clipped = union ^ target_prism(target_size_mm, edges[0], edges[-1])
    solid = np.zeros(len(edges) - 1)
    covered = np.zeros(len(edges) - 1)
    rest = clipped
    for k in range(len(edges) - 1):
        # split_by_plane keeps cutting what is above, so each slab is cut out once.
        above, below = rest.split_by_plane((0.0, 0.0, 1.0), float(edges[k + 1]))
        rest = above
        volume = below.volume()
        # A face lying on a cut leaves a flat sliver of no volume: not solid in this slab.
        if below.is_empty() or volume <= 1e-9 * area * (edges[k + 1] - edges[k]):
            continue
        solid[k] = volume / (area * (edges[k + 1] - edges[k]))
        covered[k] = below.project().area() / area
    return solid, covered


@dataclass(frozen=True)
class LayerFilling:
    """Per-layer figures; layer k spans [k h, (k + 1) h] mm above the conveyor.

    chips: chips per layer by centre of mass, all chips (the paper's count).
    chips_over_target: the same for chips whose centre lies over the target.
    full_layer: chips per full layer (target area / chip area).
    solid_fraction, covered_fraction: from exact slabs over the target (see
    :func:`slab_fractions`); porosity is 1 - solid_fraction.
    """

    layer_mm: float
    chips: np.ndarray
    chips_over_target: np.ndarray
    full_layer: float
    solid_fraction: np.ndarray
    covered_fraction: np.ndarray


def layer_filling(
    arrangement: Arrangement, union: m3.Manifold, layer_mm: float = 2.0
) -> LayerFilling:
    """Every layer figure of one stack (see :class:`LayerFilling`)."""
    _check_layer(layer_mm)
    z = arrangement.positions[:, 2]
    top = float(arrangement.bounds[:, 1, 2].max()) if arrangement.n_chips else 0.0
    n_layers = max(
        int(np.floor(max(z.max(initial=0.0), 0.0) / layer_mm)) + 1,
        math.ceil(top / layer_mm - 1e-9),
        1,
    )
    counts = layer_counts(z, layer_mm, n_layers)
    over = layer_counts(z[arrangement.inside_target()], layer_mm, n_layers)
    edges = layer_mm * np.arange(n_layers + 1)
    solid, covered = slab_fractions(union, arrangement.target_size_mm, edges)
    areas = [_plan_area(s) for s in arrangement.shapes]
    mean_area = float(np.mean([areas[i] for i in arrangement.shape_index])) if areas else 1.0
    result = LayerFilling(
        float(layer_mm),
        counts,
        over,
        full_layer_count(arrangement.target_size_mm, mean_area),
        solid,
        covered,
    )
    for array in (counts, over, solid, covered):
        array.setflags(write=False)
    return result


def _plan_area(shape) -> float:
    """Area of a chip's face (mm2): its volume over its thickness."""
    thickness = 2 * float(shape.half_extents[2])
    return shape.volume_mm3 / thickness
