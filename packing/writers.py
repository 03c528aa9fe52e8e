"""The packing stage's files and manifest entries, written: the stack writers that
:mod:`packing.files` declares (the exact record, the poses, the contacts, the VTK series),
and the files and summaries of the drops, the container and the conveyor's mat (each
scenario kind names these, :mod:`packing.kinds`). Imported when a stack is
first written: the declarations are read at every command-line start, these bring numpy,
scipy and the packing's records."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from chipstack.core.overlap import vertex_heights_mm
from chipstack.core.schema import Scenario
from chipstack.export.figure_kinds import DropScatter, draw_figures
from chipstack.export.tables import write_contacts_csv, write_drops_csv, write_poses_csv
from chipstack.export.vtk import stack_polydata, write_pvd, write_stack_vtp
from chipstack.packing.checkpoint import stack_to_arrays
from chipstack.packing.conveyor import LEFT_DOMAIN, ON_BELT, SPILLED
from chipstack.packing.files import STACK_WRITERS, StackWriter
from chipstack.packing.fill import container_fill
from chipstack.packing.mat import (
    areal_weight_map,
    coefficient_of_variation,
    orientation_distribution,
    surface_samples,
    thickness_map,
)
from chipstack.packing.scatter import drop_statistics
from chipstack.packing.shapes import shape_record

if TYPE_CHECKING:
    from chipstack.core.stack import BatchResult, Stack
    from chipstack.packing.conveyor import MatRecord
    from chipstack.packing.drop import DropResult

__all__ = [
    "container_summary",
    "mat_summary",
    "packing_summary",
    "top_mm",
    "write_drop_files",
    "write_mat_files",
]


def _write_record(folder: Path, stack: Stack) -> list[str]:
    shapes = {"schema": "chipstack.shapes/1", "shapes": [shape_record(s) for s in stack.shapes]}
    (folder / "shapes.json").write_text(json.dumps(shapes) + "\n")
    # The exact record (float64 poses, contacts) later stages start from.
    np.savez(folder / "stack.npz", **stack_to_arrays(stack))
    return ["shapes.json", "stack.npz"]


def _per_batch(folder: Path, stack: Stack, pattern: str, write) -> list[str]:
    """``write(path, result)`` once per batch, to ``pattern`` with the batch's number."""
    written = []
    for result in stack.batches:
        name = pattern.format(result.batch)
        write(folder / name, result)
        written.append(name)
    return written


def _write_poses(folder: Path, stack: Stack) -> list[str]:
    return _per_batch(
        folder, stack, "poses_after_batch_{:02d}.csv", lambda p, r: write_poses_csv(p, stack, r)
    )


def _write_contacts(folder: Path, stack: Stack) -> list[str]:
    return _per_batch(folder, stack, "contacts_after_batch_{:02d}.csv", write_contacts_csv)


def _write_vtk_series(folder: Path, stack: Stack) -> list[str]:
    series = []
    for result in stack.batches:
        n = len(result.positions)
        mesh = stack_polydata(
            stack.shapes,
            stack.shape_index[:n],
            result.positions,
            result.quaternions,
            stack.batch[:n],
        )
        name = f"stack_after_batch_{result.batch:02d}.vtp"
        write_stack_vtp(folder / name, mesh)
        series.append((float(result.batch), name))
    write_pvd(folder / "stack.pvd", series)
    return [name for _, name in series] + ["stack.pvd"]


for _writer in (
    StackWriter(
        "record",
        "shapes.json, stack.npz",
        "the exact record later stages start from: every chip's shape, float64 poses and "
        "contacts after each batch",
        _write_record,
        record=True,
    ),
    StackWriter(
        "poses",
        "poses_after_batch_NN.csv",
        "every chip's batch, shape, position (mm), quaternion and whether it landed inside "
        "the target, after each batch",
        _write_poses,
        record=True,
    ),
    StackWriter(
        "contacts",
        "contacts_after_batch_NN.csv",
        "every contact point between chips and with the conveyor after each batch",
        _write_contacts,
    ),
    StackWriter(
        "vtk",
        "stack_after_batch_NN.vtp, stack.pvd",
        "the chips as polydata after each batch, and the series for ParaView",
        _write_vtk_series,
    ),
):
    STACK_WRITERS.register(_writer.name, _writer)


def write_drop_files(folder: Path, scenario: Scenario, drops: DropResult, figures: bool) -> dict:
    """Every final pose, the statistics and, with figures, the drops' figures (Fig. 15,
    ``export.figure_kinds``); returns the statistics."""
    write_drops_csv(folder / "drops.csv", drops)
    statistics = drop_statistics(drops.positions[:, :2], scenario.drop.yaw_deg)
    statistics["settled"] = int(drops.settled.sum())
    (folder / "drop_statistics.json").write_text(json.dumps(statistics, indent=2) + "\n")
    if figures:
        scatter = DropScatter(drops.positions[:, :2], statistics, scenario.drop.yaw_deg)
        draw_figures("drops", folder / "figures", scatter)
    return statistics


def packing_summary(stack: Stack) -> dict[str, Any]:
    """The packing's manifest entry: per batch, counts, times and penetrations."""
    batches = [
        {
            "batch": r.batch,
            "chips": len(r.positions),
            "settled": r.settled,
            "sim_time_s": round(r.sim_time_s, 4),
            "wall_time_s": round(r.wall_time_s, 3),
            "steps": r.steps,
            "wakes": r.wakes,
            "contact_points": len(r.contacts),
            "outside_target": r.outside_target,
            "max_floor_penetration_mm": round(r.max_floor_penetration_mm, 5),
            "max_chip_penetration_mm": round(r.max_chip_penetration_mm, 5),
            "top_mm": round(top_mm(stack, r), 3),
        }
        for r in stack.batches
    ]
    return {
        "chips": stack.n_chips,
        "batches": batches,
        "outside_target": stack.batches[-1].outside_target,
        "all_settled": all(r.settled for r in stack.batches),
    }


def container_summary(stack: Stack, scenario: Scenario) -> dict[str, Any]:
    """How full the container is (volume fraction by centres of mass)."""
    volumes = np.array([stack.shapes[k].volume_mm3 for k in stack.shape_index])
    c = scenario.container
    return container_fill(stack.positions, volumes, c.radius_mm, c.height_mm)


def top_mm(stack: Stack, result: BatchResult) -> float:
    """Height of the highest point of any chip after ``result``'s batch (mm)."""
    n = len(result.positions)
    top = 0.0
    for k, shape in enumerate(stack.shapes):
        mine = stack.shape_index[:n] == k
        if mine.any():
            heights = vertex_heights_mm(
                result.positions[mine], result.quaternions[mine], shape.vertices
            )
            top = max(top, float(heights.max()))
    return top


def mat_summary(scenario: Scenario, mat: MatRecord) -> tuple[dict[str, Any], dict[str, Any]]:
    """The mat's descriptors: (manifest entry of scalars, the full record with maps and
    profiles for ``mat.json``). Areal weight, thickness and orientation are taken over
    the mat's steady part (:func:`packing.conveyor.steady_range_mm`), across the belt."""
    c = scenario.conveyor
    low, high = mat.steady_mm
    half = c.belt_width_mm / 2
    on = mat.status == ON_BELT
    steady = on & (mat.positions[:, 0] >= low) & (mat.positions[:, 0] <= high)
    n = max(mat.n_chips, 1)
    summary: dict[str, Any] = {
        "chips": {
            "released": int(mat.n_chips),
            "on_belt": int(on.sum()),
            "spilled": int((mat.status == SPILLED).sum()),
            "left_domain": int((mat.status == LEFT_DOMAIN).sum()),
        },
        # From the first pour's zone to the last's (the mat's nominal extent).
        "mat_length_mm": float(np.ptp(mat.zone_x_mm) + c.zone_length_mm)
        if len(mat.zone_x_mm)
        else 0.0,
        "steady_mm": [float(low), float(high)],
        "panel_mm": scenario.deposition.target_size_mm,
        "panel_centre_mm": list(mat.panel_centre_mm),
        "time": {
            "wall_s": round(mat.wall_time_s, 3),
            "ms_per_chip": round(1e3 * mat.wall_time_s / n, 3),
            "sim_s": round(mat.sim_time_s, 4),
            "steps": int(mat.steps),
            "wakes": int(mat.wakes),
            "most_chips_in_engine": int(mat.most_in_world),
        },
        "settled": bool(mat.settled),
    }
    record: dict[str, Any] = dict(summary)
    if high - low >= c.cell_mm:
        weights, x_edges, y_edges = areal_weight_map(
            mat.positions[on, :2], mat.masses_g[on], (low, high), (-half, half), c.cell_mm
        )
        summary["areal_weight"] = {
            "cell_mm": c.cell_mm,
            "mean_g_m2": float(weights.mean()),
            "cv": coefficient_of_variation(weights),
            "cells": int(weights.size),
            **_panel_weights(mat, on, (low, high), scenario.deposition.target_size_mm),
        }
        record["areal_weight"] = {
            **summary["areal_weight"],
            "map_g_m2": weights.tolist(),
            "x_edges_mm": x_edges.tolist(),
            "y_edges_mm": y_edges.tolist(),
        }
    else:
        summary["areal_weight"] = None
        record["areal_weight"] = None
    if steady.any() and high > low:
        pixel = scenario.geometry.pixel_mm
        samples = [surface_samples(s.vertices, s.convex_pieces, pixel / 2) for s in mat.shapes]
        reach = max(shape.circumradius_mm for shape in mat.shapes)
        near = on & (mat.positions[:, 0] >= low - reach) & (mat.positions[:, 0] <= high + reach)
        heights, x_edges, y_edges = thickness_map(
            mat.positions[near],
            mat.quaternions[near],
            samples,
            mat.shape_index[near],
            (low, high),
            (-half, half),
            pixel,
        )
        along, across = heights.mean(axis=1), heights.mean(axis=0)
        # Whether the steady part is steady: the change of the mean thickness from its
        # first third poured to its last third (x decreases as the mat is poured).
        thirds = np.array_split(along[::-1], 3)
        drift = (
            float((thirds[2].mean() - thirds[0].mean()) / along.mean())
            if len(along) >= 3 and along.mean() > 0 and c.belt_speed_mm_s > 0
            else float("nan")  # a belt at rest makes a pile: no steady state to check
        )
        summary["thickness"] = {
            "pixel_mm": pixel,
            "mean_mm": float(heights.mean()),
            "cv_along": coefficient_of_variation(along),
            "cv_across": coefficient_of_variation(across),
            "bare_fraction": float((heights == 0).mean()),
            "drift": drift,
        }
        record["thickness"] = {
            **summary["thickness"],
            "along_mm": along.tolist(),
            "along_x_mm": (0.5 * (x_edges[1:] + x_edges[:-1])).tolist(),
            "across_mm": across.tolist(),
            "across_y_mm": (0.5 * (y_edges[1:] + y_edges[:-1])).tolist(),
        }
        orientation = orientation_distribution(mat.quaternions[steady])
        summary["orientation"] = {
            k: orientation[k]
            for k in ("order_cos2", "order_cos4", "mean_tilt_deg", "flat_fraction")
        }
        record["orientation"] = orientation
    else:
        summary["thickness"] = summary["orientation"] = None
        record["thickness"] = record["orientation"] = None
    return summary, record


def _panel_weights(mat: MatRecord, on, steady: tuple[float, float], panel_mm: float) -> dict:
    """Panel to panel: the mass of each whole panel-long stretch of the steady part, across
    the whole belt, one after another (g), and their coefficient of variation (None with
    fewer than two)."""
    low, high = steady
    count = int((high - low) // panel_mm)
    if count < 2:
        return {"panels": count, "panel_cv": None}
    edges = low + panel_mm * np.arange(count + 1)
    masses, _ = np.histogram(mat.positions[on, 0], bins=edges, weights=mat.masses_g[on])
    return {
        "panels": count,
        "panel_cv": coefficient_of_variation(masses),
        "panel_mass_g": masses.tolist(),
    }


def write_mat_files(folder: Path, scenario: Scenario, mat: MatRecord, figures: bool) -> dict:
    """The whole mat (``mat.npz``, ``mat_shapes.json``), its descriptors (``mat.json``)
    and, with figures, the mat's figures (``export.figure_kinds``); returns the manifest
    entry."""
    shapes = {"schema": "chipstack.shapes/1", "shapes": [shape_record(s) for s in mat.shapes]}
    (folder / "mat_shapes.json").write_text(json.dumps(shapes) + "\n")
    np.savez(
        folder / "mat.npz",
        positions=mat.positions,
        quaternions=mat.quaternions,
        shape_index=mat.shape_index,
        pour=mat.pour,
        status=mat.status,
        zone_x_mm=mat.zone_x_mm,
    )
    summary, record = mat_summary(scenario, mat)
    (folder / "mat.json").write_text(json.dumps(record, indent=1) + "\n")
    if figures:
        draw_figures("mat", folder / "figures", record)
    return summary
