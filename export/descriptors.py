"""Files of the geometry stage: descriptors.json, CSV tables and maps, the voxel image."""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Any

import numpy as np

from geometry.contacts import KINDS, PLACES
from geometry.describe import Description

__all__ = ["write_description", "write_voxel_image"]


def _write_csv(path: Path, header: list[str], rows) -> None:
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(header)
        writer.writerows(rows)


def _fmt(value: float, digits: int = 6) -> str:
    return f"{value:.{digits}g}" if np.isfinite(value) else ""


def write_voxel_image(path: Path, image) -> None:
    """The voxel image as VTK ImageData (.vti): cell array ``chip`` (1 + chip index, 0 void)."""
    import pyvista

    grid = pyvista.ImageData(
        dimensions=np.array(image.labels.shape) + 1,
        spacing=(image.voxel_mm,) * 3,
        origin=image.origin_mm,
    )
    grid.cell_data["chip"] = np.ascontiguousarray(image.labels).ravel(order="F")
    grid.save(str(path))


def write_description(
    folder: Path, description: Description, arrangement, extra: dict[str, Any]
) -> list[str]:
    """Write ``descriptors.json`` and the tables of every computed descriptor into ``folder``.

    ``arrangement`` is the described stack (its final state). Returns the files written.
    """
    written = [_write_chips(folder, description, arrangement)]
    data = {**description.to_json(), **extra}
    (folder / "descriptors.json").write_text(json.dumps(data, indent=2) + "\n")
    written.append("descriptors.json")
    records = description.records
    if "contacts" in records:
        history = records["contacts"]
        rows = []
        for batch, table in zip(history.batches, history.tables, strict=True):
            n = max(table.n_chips, 1)
            rows.append(
                [batch, table.n_chips]
                + [_fmt(np.sum(table.kind == k) / n) for k in range(len(KINDS))]
                + [_fmt(len(table) / n)]
            )
        _write_csv(
            folder / "contacts_by_batch.csv",
            ["batch", "chips"] + [f"{k}_per_chip" for k in KINDS] + ["total_per_chip"],
            rows,
        )
        final = history.tables[-1]
        places = (*PLACES, "")
        _write_csv(
            folder / "contacts.csv",
            [
                "chip_a",
                "chip_b",
                "kind",
                "extent_1_mm",
                "extent_2_mm",
                "extent_3_mm",
                "x_mm",
                "y_mm",
                "z_mm",
                "area_mm2",
                "b_seen_from_a",
                "a_seen_from_b",
            ],
            (
                [
                    int(final.chip_a[k]),
                    int(final.chip_b[k]),
                    KINDS[final.kind[k]],
                    *(_fmt(v) for v in final.extents_mm[k]),
                    *(_fmt(v) for v in final.centre_mm[k]),
                    _fmt(final.area_mm2[k]),
                    places[final.place_a[k]],
                    places[final.place_b[k]] if final.place_b[k] >= 0 else "",
                ]
                for k in range(len(final))
            ),
        )
        written += ["contacts_by_batch.csv", "contacts.csv"]
    if "layers" in records:
        f = records["layers"]
        h = f.layer_mm
        _write_csv(
            folder / "layers.csv",
            [
                "layer",
                "z_low_mm",
                "z_high_mm",
                "chips",
                "chips_over_target",
                "full_layer",
                "solid_fraction",
                "porosity",
                "covered_fraction",
            ],
            (
                [
                    k,
                    _fmt(k * h),
                    _fmt((k + 1) * h),
                    int(f.chips[k]),
                    int(f.chips_over_target[k]),
                    _fmt(f.full_layer),
                    _fmt(f.solid_fraction[k]),
                    _fmt(1 - f.solid_fraction[k]),
                    _fmt(f.covered_fraction[k]),
                ]
                for k in range(len(f.chips))
            ),
        )
        written.append("layers.csv")
    if "thickness" in records:
        maps = records["thickness"]
        grid = maps.grid
        _write_csv(
            folder / "neh_map.csv",
            ["x_mm", "y_mm", "on_target", "neh", "top_mm", "solid_mm"],
            (
                [
                    _fmt(grid.x[i]),
                    _fmt(grid.y[j]),
                    int(grid.on_target[i, j]),
                    int(maps.neh[i, j]),
                    _fmt(maps.top_mm[i, j]),
                    _fmt(maps.solid_mm[i, j]),
                ]
                for i in range(grid.nx)
                for j in range(grid.ny)
            ),
        )
        written.append("neh_map.csv")
    if "overlaps" in records:
        o = records["overlaps"]
        _write_csv(
            folder / "overlaps.csv",
            ["chip_a", "chip_b", "projected_mm2", "penetration_mm3"],
            (
                [int(i), int(j), _fmt(a), _fmt(v)]
                for (i, j), a, v in zip(o.pairs, o.projected_mm2, o.penetration_mm3, strict=True)
            ),
        )
        written.append("overlaps.csv")
    if "voxels" in records:
        write_voxel_image(folder / "voxels.vti", records["voxels"])
        written.append("voxels.vti")
    return written


def _write_chips(folder: Path, description: Description, arrangement) -> str:
    """chips.csv: one row per chip with every per-chip figure that was computed."""
    from geometry.contacts import contact_counts

    records = description.records
    n = arrangement.n_chips
    layer = np.floor(arrangement.positions[:, 2] / description.spec.layer_mm).astype(int)
    columns: dict[str, list] = {
        "chip": list(range(n)),
        "batch": arrangement.batch.tolist(),
        "layer": np.maximum(layer, 0).tolist(),
        "inside_target": arrangement.inside_target().astype(int).tolist(),
    }
    if "orientation" in records:
        columns["tilt_deg"] = [_fmt(v) for v in records["orientation"].tilt_deg]
        columns["direction_deg"] = [_fmt(v) for v in records["orientation"].direction_deg]
    if "contacts" in records:
        counts = contact_counts(records["contacts"].tables[-1])
        for k, kind in enumerate(KINDS):
            columns[f"{kind}_contacts"] = counts[:, k].sum(axis=1).tolist()
        for p, place in enumerate(PLACES):
            columns[f"contacts_{place}"] = counts[:, :, p].sum(axis=1).tolist()
    if "overlaps" in records:
        o = records["overlaps"]
        columns["projected_overlap_mm2"] = [_fmt(v) for v in o.per_chip_projected_mm2]
        columns["penetration_mm3"] = [_fmt(v) for v in o.per_chip_penetration_mm3]
    _write_csv(folder / "chips.csv", list(columns), zip(*columns.values(), strict=True))
    return "chips.csv"
