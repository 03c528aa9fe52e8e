"""Every descriptor of a stack, by name, as plain JSON-ready sections.

``describe`` runs the registered descriptors on a stack's history (one arrangement per
deposited batch, NBD 1, 2, ...) and returns, per descriptor, its record (arrays for
figures and tables) and its section of ``descriptors.json``: named scalars and profiles,
each with its unit and a one-line definition.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

from chipstack.core.arrangement import Arrangement
from chipstack.core.errors import InputError
from chipstack.export.tables import fmt
from chipstack.export.vtk import write_voxel_image
from chipstack.geometry.contacts import (
    GROUND,
    KINDS,
    PLACES,
    ContactTable,
    contact_counts,
    find_contacts,
)
from chipstack.geometry.descriptor_kinds import DESCRIPTORS
from chipstack.geometry.layers import LayerFilling, layer_filling, slab_fractions
from chipstack.geometry.orientation import (
    fibre_directions_world,
    fibre_tensor,
    in_plane_direction_deg,
    tilt_deg,
)
from chipstack.geometry.overlaps import Overlaps, find_overlaps
from chipstack.geometry.rays import RayMaps, ray_maps
from chipstack.geometry.sections import GeometrySpec
from chipstack.geometry.solids import chip_solids, target_prism, union_solid
from chipstack.geometry.voxels import VoxelImage, voxel_solid_profile, voxelize

__all__ = ["DESCRIPTORS", "Description", "describe", "SCHEMA"]

SCHEMA = "chipstack.descriptors/1"
TILT_BINS_DEG = np.arange(0.0, 91.0, 10.0)
DIRECTION_BINS_DEG = np.arange(0.0, 181.0, 15.0)
RING_EDGES_MM = (0.0, 25.0, 50.0, 75.0, np.inf)  # the last ring: the target's corners


def scalar(value: float, unit: str, doc: str) -> dict[str, Any]:
    value = float(value)
    return {"value": value if np.isfinite(value) else None, "unit": unit, "doc": doc}


def profile(
    index: Sequence[float],
    values: Sequence[float],
    index_name: str,
    unit: str,
    doc: str,
    pad: float | str | None = 0.0,
) -> dict[str, Any]:
    """A profile section; ``pad`` is its value at an index a stack does not reach (layers
    above its top: 0 chips), ``"last"`` to repeat the last value (cumulative profiles), or
    None when such an index has no value."""
    return {
        "pad": pad,
        "index_name": index_name,
        "index": [float(v) if isinstance(v, float) else v for v in index],
        "values": [None if not np.isfinite(v) else float(v) for v in values],
        "unit": unit,
        "doc": doc,
    }


class _Context:
    """Intermediate results shared by descriptors (the union, the ray maps), made once."""

    def __init__(self, history: Sequence[Arrangement], spec: GeometrySpec) -> None:
        self.history = list(history)
        self.final = self.history[-1]
        self.spec = spec

    @cached_property
    def union(self):
        return union_solid(chip_solids(self.final))

    @cached_property
    def rays(self) -> RayMaps:
        return ray_maps(self.final, self.spec.pixel_mm)


Table = tuple[list[str], Iterable[list]]  # CSV header and rows


def _no_tables(record: Any) -> dict[str, Table]:
    return {}


def _no_files(record: Any, folder: Path) -> list[str]:
    return []


def _no_figures(record: Any, section: dict[str, Any], folder: Path) -> list[str]:
    return []


def _no_ensemble_figures(summary: dict[str, Any], folder: Path) -> list[str]:
    return []


def _no_comparison_figures(
    labels: tuple[str, str], summaries: tuple[dict[str, Any], dict[str, Any]], folder: Path
) -> list[str]:
    return []


def _no_columns(record: Any) -> dict[str, list]:
    return {}


def _no_headline(section: dict[str, Any]) -> str | None:
    return None


def bands(profile: dict[str, Any]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """An ensemble profile's mean and its 95 % band (the mean where the band is
    undefined: a single repeat)."""

    def array(key: str) -> np.ndarray:
        return np.array([np.nan if v is None else v for v in profile[key]], dtype=float)

    mean = array("mean")
    low, high = array("ci_low"), array("ci_high")
    return mean, np.where(np.isnan(low), mean, low), np.where(np.isnan(high), mean, high)


@dataclass(frozen=True)
class Descriptor:
    """A registered descriptor: how to compute it and what it writes.

    compute(ctx) -> (record of arrays, JSON section); tables(record) -> {CSV name:
    (header, rows)}; files(record, folder) -> other files written (names);
    figures(record, section, folder) -> figures drawn into ``folder`` (names);
    ensemble_figures(summary, folder) -> the same over an ensemble's repeats, from this
    descriptor's part of ``ensemble.json`` (with 95 % bands); comparison_figures(labels,
    summaries, folder) -> two ensembles side by side (``pipeline compare``);
    chip_columns(record) -> {column: one value per chip} for ``chips.csv``; headline(section)
    -> its part of the stage's one-line report, or None; ensemble_scalars: the scalars an
    ensemble's summary on the command line shows with their intervals. ``order``: where
    its columns and its part of the reports come among the other descriptors' (lower
    first; the built-ins keep the order their files have always had).
    """

    name: str
    doc: str
    compute: Callable[[_Context], tuple[Any, dict[str, Any]]]
    tables: Callable[[Any], dict[str, Table]] = _no_tables
    files: Callable[[Any, Path], list[str]] = _no_files
    figures: Callable[[Any, dict[str, Any], Path], list[str]] = _no_figures
    ensemble_figures: Callable[[dict[str, Any], Path], list[str]] = _no_ensemble_figures
    comparison_figures: Callable[[tuple, tuple, Path], list[str]] = _no_comparison_figures
    chip_columns: Callable[[Any], dict[str, list]] = _no_columns
    ensemble_scalars: tuple[str, ...] = ()
    headline: Callable[[dict[str, Any]], str | None] = _no_headline
    order: int = 100


def in_output_order(names) -> list[str]:
    """The registered ones of descriptor ``names``, in the order their columns and their
    parts of the reports come (``Descriptor.order``)."""
    return sorted((n for n in names if n in DESCRIPTORS), key=lambda n: DESCRIPTORS.get(n).order)


def _register(name: str, doc: str, **outputs: Any):
    def wrap(function):
        DESCRIPTORS.register(name, Descriptor(name, doc, function, **outputs))
        return function

    return wrap


# -- contact types -----------------------------------------------------------------------
@dataclass(frozen=True)
class ContactHistory:
    """Contact tables after each batch (NBD 1, 2, ...)."""

    tables: tuple[ContactTable, ...]
    batches: tuple[int, ...]


def _contact_tables(history: ContactHistory) -> dict[str, Table]:
    rows = []
    for batch, table in zip(history.batches, history.tables, strict=True):
        n = max(table.n_chips, 1)
        rows.append(
            [batch, table.n_chips]
            + [fmt(np.sum(table.kind == k) / n) for k in range(len(KINDS))]
            + [fmt(len(table) / n)]
        )
    by_batch = ["batch", "chips"] + [f"{k}_per_chip" for k in KINDS] + ["total_per_chip"]
    final = history.tables[-1]
    places = (*PLACES, "")
    header = ["chip_a", "chip_b", "kind", "extent_1_mm", "extent_2_mm", "extent_3_mm"]
    header += ["x_mm", "y_mm", "z_mm", "area_mm2", "b_seen_from_a", "a_seen_from_b"]
    pairs = (
        [
            int(final.chip_a[k]),
            int(final.chip_b[k]),
            KINDS[final.kind[k]],
            *(fmt(v) for v in final.extents_mm[k]),
            *(fmt(v) for v in final.centre_mm[k]),
            fmt(final.area_mm2[k]),
            places[final.place_a[k]],
            places[final.place_b[k]] if final.place_b[k] >= 0 else "",
        ]
        for k in range(len(final))
    )
    return {"contacts_by_batch.csv": (by_batch, rows), "contacts.csv": (header, pairs)}


def _figures() -> ModuleType:
    """:mod:`export.figures`, imported when a descriptor's figure is first drawn: it brings
    matplotlib, which a description without figures never needs."""
    from chipstack.export import figures

    return figures


def _contact_figures(history: ContactHistory, section: dict[str, Any], folder: Path) -> list[str]:
    figures = _figures()
    profiles = section["profiles"]
    mean = {kind: np.array(profiles[f"{kind}_per_chip_by_batch"]["values"]) for kind in KINDS}
    batches = np.array(profiles["point_per_chip_by_batch"]["index"])
    figures.plot_contact_types(folder / "contact_types.png", batches, mean)
    return ["contact_types.png"]


def _contact_ensemble_figures(summary: dict[str, Any], folder: Path) -> list[str]:
    """Fig. 7 with 95 % confidence bands over the repeats."""
    figures = _figures()
    profiles = summary["profiles"]
    batches = np.array(profiles["point_per_chip_by_batch"]["index"])
    mean, low, high = {}, {}, {}
    for kind in KINDS:
        mean[kind], low[kind], high[kind] = bands(profiles[f"{kind}_per_chip_by_batch"])
    figures.plot_contact_types(folder / "contact_types.png", batches, mean, low, high)
    return ["contact_types.png"]


def _contact_columns(history: ContactHistory) -> dict[str, list]:
    counts = contact_counts(history.tables[-1])
    columns = {
        f"{kind}_contacts": counts[:, k].sum(axis=1).tolist() for k, kind in enumerate(KINDS)
    }
    for p, place in enumerate(PLACES):
        columns[f"contacts_{place}"] = counts[:, :, p].sum(axis=1).tolist()
    return columns


def _contact_headline(section: dict[str, Any]) -> str:
    s = section["scalars"]
    return "contacts per chip: " + ", ".join(
        f"{k} {s[k + '_per_chip']['value']:.2f}" for k in KINDS
    )


@_register(
    "contacts",
    "contact types per chip (point, line, surface) and partner place, by NBD",
    tables=_contact_tables,
    figures=_contact_figures,
    ensemble_figures=_contact_ensemble_figures,
    chip_columns=_contact_columns,
    headline=_contact_headline,
    ensemble_scalars=tuple(f"{kind}_per_chip" for kind in KINDS),
    order=20,
)
def _contacts(ctx: _Context):
    spec = ctx.spec
    tables = tuple(
        find_contacts(a, spec.contact_gap_mm, spec.contact_extent_mm) for a in ctx.history
    )
    batches = tuple(int(a.batch.max()) if a.n_chips else 0 for a in ctx.history)
    final = tables[-1]
    n = max(final.n_chips, 1)
    counts = contact_counts(final)  # (n, kinds, places), each chip counting its own contacts
    scalars: dict[str, Any] = {}
    for k, kind in enumerate(KINDS):
        scalars[f"{kind}_per_chip"] = scalar(
            np.sum(final.kind == k) / n,
            "1/chip",
            f"{kind} contacts (touching pairs, floor included) divided by the number of chips",
        )
    scalars["total_per_chip"] = scalar(len(final) / n, "1/chip", "all contacts / chips")
    for k, kind in enumerate(KINDS):
        scalars[f"{kind}_per_chip_both_sides"] = scalar(
            counts[:, k].sum() / n,
            "1/chip",
            f"{kind} contacts each chip takes part in, averaged over chips "
            "(a chip-chip contact counts for both chips)",
        )
    for p, place in enumerate(PLACES):
        for k, kind in enumerate(KINDS):
            scalars[f"{kind}_{place}_per_chip"] = scalar(
                counts[:, k, p].sum() / n,
                "1/chip",
                f"{kind} contacts with a partner {place} the chip, per chip (both sides)",
            )
    scalars["ground_contacts"] = scalar(
        np.sum(final.chip_b == GROUND), "", "chips touching the conveyor"
    )
    scalars["mean_patch_area_mm2"] = scalar(
        final.area_mm2.mean() if len(final) else 0.0,
        "mm2",
        "mean area of a contact patch at the gap tolerance",
    )
    profiles = {}
    for k, kind in enumerate(KINDS):
        profiles[f"{kind}_per_chip_by_batch"] = profile(
            list(batches),
            [np.sum(t.kind == k) / max(t.n_chips, 1) for t in tables],
            "batch",
            "1/chip",
            f"{kind} contacts per chip after each batch (NBD), pair convention",
            pad=None,
        )
    return ContactHistory(tables, batches), {"scalars": scalars, "profiles": profiles}


# -- local stack thickness -----------------------------------------------------------------
def _thickness_tables(maps: RayMaps) -> dict[str, Table]:
    grid = maps.grid
    rows = (
        [
            fmt(grid.x[i]),
            fmt(grid.y[j]),
            int(grid.on_target[i, j]),
            int(maps.neh[i, j]),
            fmt(maps.top_mm[i, j]),
            fmt(maps.solid_mm[i, j]),
        ]
        for i in range(grid.nx)
        for j in range(grid.ny)
    )
    return {"neh_map.csv": (["x_mm", "y_mm", "on_target", "neh", "top_mm", "solid_mm"], rows)}


def _thickness_figures(maps: RayMaps, section: dict[str, Any], folder: Path) -> list[str]:
    figures = _figures()
    grid = maps.grid
    figures.plot_neh_map(
        folder / "neh_map.png",
        grid.x0 + grid.pixel_mm * np.arange(grid.nx + 1),
        grid.y0 + grid.pixel_mm * np.arange(grid.ny + 1),
        maps.neh,
        grid.target_size_mm,
    )
    return ["neh_map.png"]


@_register(
    "thickness",
    "local stack thickness: chips crossed by vertical rays (NEH map)",
    tables=_thickness_tables,
    figures=_thickness_figures,
)
def _thickness(ctx: _Context):
    maps = ctx.rays
    on = maps.grid.on_target
    neh = maps.neh[on]
    radius = np.hypot(maps.grid.x[:, None], maps.grid.y[None, :])
    ring_means = []
    labels = []
    for lo, hi in zip(RING_EDGES_MM[:-1], RING_EDGES_MM[1:], strict=True):
        ring = (radius >= lo) & (radius < hi) & on
        ring_means.append(maps.neh[ring].mean() if ring.any() else np.nan)
        labels.append(f"{lo:g}-{hi:g}" if np.isfinite(hi) else f">{lo:g}")
    histogram = np.bincount(np.minimum(neh, 8), minlength=9) / max(len(neh), 1)
    scalars = {
        "neh_mean": scalar(neh.mean(), "chips", "mean NEH over the target's pixels"),
        "neh_max": scalar(maps.neh.max(initial=0), "chips", "largest NEH anywhere"),
        "pixel_mm": scalar(maps.grid.pixel_mm, "mm", "pixel side"),
    }
    profiles = {
        "neh_by_ring": profile(
            labels,
            ring_means,
            "distance from the target centre (mm)",
            "chips",
            "mean NEH of the target's pixels in rings around its centre",
        ),
        "neh_histogram": profile(
            [str(k) if k < 8 else "8+" for k in range(9)],
            histogram,
            "NEH",
            "",
            "fraction of the target's pixels with each NEH (8 and more together)",
        ),
    }
    return maps, {"scalars": scalars, "profiles": profiles}


# -- layer filling -------------------------------------------------------------------------
def _layer_tables(f: LayerFilling) -> dict[str, Table]:
    h = f.layer_mm
    header = ["layer", "z_low_mm", "z_high_mm", "chips", "chips_over_target", "full_layer"]
    header += ["solid_fraction", "porosity", "covered_fraction"]
    rows = (
        [
            k,
            fmt(k * h),
            fmt((k + 1) * h),
            int(f.chips[k]),
            int(f.chips_over_target[k]),
            fmt(f.full_layer),
            fmt(f.solid_fraction[k]),
            fmt(1 - f.solid_fraction[k]),
            fmt(f.covered_fraction[k]),
        ]
        for k in range(len(f.chips))
    )
    return {"layers.csv": (header, rows)}


def _layer_figures(filling: LayerFilling, section: dict[str, Any], folder: Path) -> list[str]:
    figures = _figures()
    layers = np.arange(len(filling.chips))
    figures.plot_layer_filling(
        folder / "layer_filling.png", layers, filling.chips, filling.full_layer
    )
    figures.plot_profile(
        folder / "porosity_profile.png",
        filling.layer_mm * (layers + 0.5),
        1.0 - filling.solid_fraction,
        "porosity over the target (per layer)",
        "Porosity through the thickness",
    )
    return ["layer_filling.png", "porosity_profile.png"]


def _layer_ensemble_figures(summary: dict[str, Any], folder: Path) -> list[str]:
    """Fig. 10 with 95 % confidence bands over the repeats."""
    figures = _figures()
    chips = summary["profiles"]["chips"]
    mean, low, high = bands(chips)
    full = summary["scalars"]["full_layer"]["mean"]
    figures.plot_layer_filling(
        folder / "layer_filling.png", np.array(chips["index"]), mean, full, low, high
    )
    return ["layer_filling.png"]


def _layer_comparison_figures(
    labels: tuple[str, str], summaries: tuple[dict[str, Any], dict[str, Any]], folder: Path
) -> list[str]:
    """Fig. 12: the two ensembles' layer filling side by side."""
    figures = _figures()
    series = []
    longest: list[Any] = []
    for label, summary in zip(labels, summaries, strict=True):
        chips = summary["profiles"]["chips"]
        mean, low, high = bands(chips)
        series.append((label, mean, low, high))
        longest = max(longest, chips["index"], key=len)
    full = summaries[0]["scalars"]["full_layer"]["mean"]
    figures.plot_layer_comparison(folder / "layer_filling.png", np.array(longest), series, full)
    return ["layer_filling.png"]


@_register(
    "layers",
    "layer filling by centre of mass, solid and covered fractions per layer",
    tables=_layer_tables,
    figures=_layer_figures,
    ensemble_figures=_layer_ensemble_figures,
    comparison_figures=_layer_comparison_figures,
    ensemble_scalars=("highest_layer",),
    headline=lambda section: f"highest layer {int(section['scalars']['highest_layer']['value'])}",
    order=50,
)
def _layers(ctx: _Context):
    filling: LayerFilling = layer_filling(ctx.final, ctx.union, ctx.spec.layer_mm)
    index = list(range(len(filling.chips)))
    nonempty = np.flatnonzero(filling.chips)
    scalars = {
        "full_layer": scalar(filling.full_layer, "chips", "chips per full layer"),
        "highest_layer": scalar(
            nonempty.max() if len(nonempty) else -1, "", "highest layer holding a centre"
        ),
        "nonempty_layers": scalar(len(nonempty), "", "layers holding at least one centre"),
    }
    h = filling.layer_mm
    profiles = {
        "chips": profile(index, filling.chips, "layer", "chips", f"chips per {h:g} mm layer"),
        "chips_cumulative": profile(
            index,
            np.cumsum(filling.chips),
            "layer",
            "chips",
            "chips whose centre lies in this layer or below (filling up to the layer's top)",
            pad="last",
        ),
        "chips_over_target": profile(
            index,
            filling.chips_over_target,
            "layer",
            "chips",
            "chips per layer, counting chips whose centre lies over the target",
        ),
        "solid_fraction": profile(
            index,
            filling.solid_fraction,
            "layer",
            "",
            "solid volume / layer volume over the target (porosity = 1 - this)",
        ),
        "covered_fraction": profile(
            index,
            filling.covered_fraction,
            "layer",
            "",
            "area of the target under the layer's solid / target area",
        ),
    }
    return filling, {"scalars": scalars, "profiles": profiles}


# -- overlaps ------------------------------------------------------------------------------
def _overlap_tables(o: Overlaps) -> dict[str, Table]:
    rows = (
        [int(i), int(j), fmt(a), fmt(v)]
        for (i, j), a, v in zip(o.pairs, o.projected_mm2, o.penetration_mm3, strict=True)
    )
    return {"overlaps.csv": (["chip_a", "chip_b", "projected_mm2", "penetration_mm3"], rows)}


@_register(
    "overlaps",
    "interpenetration volumes and projected overlap areas between chips",
    tables=_overlap_tables,
    chip_columns=lambda o: {
        "projected_overlap_mm2": [fmt(v) for v in o.per_chip_projected_mm2],
        "penetration_mm3": [fmt(v) for v in o.per_chip_penetration_mm3],
    },
    order=40,
)
def _overlaps(ctx: _Context):
    result: Overlaps = find_overlaps(ctx.final)
    a = ctx.final
    volume = sum(a.shapes[i].volume_mm3 for i in a.shape_index) or 1.0
    n = max(a.n_chips, 1)
    scalars = {
        "projected_total_mm2": scalar(
            result.total_projected_mm2, "mm2", "sum over pairs of footprint overlap areas"
        ),
        "projected_per_chip_mm2": scalar(
            2 * result.total_projected_mm2 / n,
            "mm2",
            "mean over chips of their footprint overlap with all other chips",
        ),
        "overlapping_pairs": scalar(len(result.pairs), "", "pairs with overlapping footprints"),
        "penetration_total_mm3": scalar(
            result.total_penetration_mm3, "mm3", "sum over pairs of interpenetration volumes"
        ),
        "penetration_fraction": scalar(
            result.total_penetration_mm3 / volume, "", "interpenetration / total chip volume"
        ),
        "penetration_max_mm3": scalar(
            result.penetration_mm3.max(initial=0.0), "mm3", "largest interpenetration of a pair"
        ),
    }
    return result, {"scalars": scalars, "profiles": {}}


# -- orientation ---------------------------------------------------------------------------
@dataclass(frozen=True)
class Orientation:
    tilt_deg: np.ndarray
    direction_deg: np.ndarray
    tensor: np.ndarray
    layer_tensors: dict[int, np.ndarray] = field(default_factory=dict)


@_register(
    "orientation",
    "chip tilt, in-plane direction and fibre orientation tensors",
    chip_columns=lambda o: {
        "tilt_deg": [fmt(v) for v in o.tilt_deg],
        "direction_deg": [fmt(v) for v in o.direction_deg],
    },
    order=10,
)
def _orientation(ctx: _Context):
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


# -- whole stack ---------------------------------------------------------------------------
def _stack_headline(section: dict[str, Any]) -> str:
    s = section["scalars"]
    return (
        f"mean height {s['height_mean_mm']['value']:.1f} mm, "
        f"volume fraction {s['volume_fraction']['value']:.3f}"
    )


@_register(
    "stack",
    "height, bulk volume fraction, bare and uneven target area",
    headline=_stack_headline,
    ensemble_scalars=("height_max_mm", "volume_fraction"),
    order=30,
)
def _stack(ctx: _Context):
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


# -- voxel image ---------------------------------------------------------------------------
def _voxel_files(image: VoxelImage, folder: Path) -> list[str]:
    write_voxel_image(folder / "voxels.vti", image)
    return ["voxels.vti"]


@_register(
    "voxels",
    "voxel image of chip ids and its porosity profile against the exact one",
    files=_voxel_files,
)
def _voxels(ctx: _Context):
    image: VoxelImage = voxelize(ctx.final, ctx.spec.voxel_mm)
    profile_voxels = voxel_solid_profile(image)
    h = image.voxel_mm
    edges = h * np.arange(image.labels.shape[2] + 1)
    exact, _ = slab_fractions(ctx.union, ctx.final.target_size_mm, edges)
    scalars = {
        "voxel_mm": scalar(h, "mm", "voxel side"),
        "shape_x": scalar(image.labels.shape[0], "voxels", "image size along x"),
        "shape_y": scalar(image.labels.shape[1], "voxels", "image size along y"),
        "shape_z": scalar(image.labels.shape[2], "voxels", "image size along z"),
        "profile_max_difference": scalar(
            np.abs(profile_voxels - exact).max(initial=0.0),
            "",
            "largest difference between voxel and exact solid fraction of a voxel layer",
        ),
    }
    z = list(h * (np.arange(len(exact)) + 0.5))
    profiles = {
        "solid_fraction_voxels": profile(
            z, profile_voxels, "z (mm)", "", "solid fraction of each voxel layer over the target"
        ),
        "solid_fraction_exact": profile(
            z, exact, "z (mm)", "", "exact solid fraction of the same slabs (manifold3d)"
        ),
    }
    return image, {"scalars": scalars, "profiles": profiles}


# -- running them --------------------------------------------------------------------------
@dataclass(frozen=True)
class Description:
    """Records (arrays) and JSON sections of the descriptors that were computed."""

    records: dict[str, Any]
    sections: dict[str, dict[str, Any]]
    timings_s: dict[str, float]
    spec: GeometrySpec

    def to_json(self) -> dict[str, Any]:
        return {
            "schema": SCHEMA,
            "parameters": {
                f.name: getattr(self.spec, f.name) for f in dataclasses.fields(self.spec)
            },
            "descriptors": self.sections,
        }  # timings go to the run's manifest: a result file holds only results


def check_names(names: Sequence[str] | None) -> list[str]:
    """The descriptors to compute, in registry order; raises naming an unknown one."""
    if names is None:
        return DESCRIPTORS.in_order()
    for name in names:
        DESCRIPTORS.get(name, key="descriptors")
    return [n for n in DESCRIPTORS.in_order() if n in set(names)]


def describe(
    history: Sequence[Arrangement],
    spec: GeometrySpec | None = None,
    names: Sequence[str] | None = None,
) -> Description:
    """Compute the named descriptors (all by default) of a stack's history.

    ``history``: the stack after each batch, in order; the last one is the stack.
    """
    if not history:
        raise InputError("history: no arrangement to describe")
    spec = spec or GeometrySpec()
    selected = check_names(names)
    ctx = _Context(history, spec)
    records, sections, timings = {}, {}, {}
    for name in selected:
        start = time.perf_counter()
        records[name], sections[name] = DESCRIPTORS.get(name).compute(ctx)
        timings[name] = time.perf_counter() - start
    return Description(records, sections, timings, spec)
