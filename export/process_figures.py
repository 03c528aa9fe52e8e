"""Figures of the process around the stack: a drop experiment's landings (the paper's
Figure 15), a mat on the belt, a sweep's scalars, a press's force against travel."""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patches import Circle

from chipstack.core.errors import InputError
from chipstack.export.figures import DPI, _new_figure, _path, _save, _vector

__all__ = ["plot_drops", "plot_force_displacement", "plot_loose_press", "plot_mat", "plot_sweep"]


def plot_drops(path: object, xy: np.ndarray, statistics: Mapping, yaw_deg: float = 0.0) -> Path:
    """Fig. 15: final positions of dropped chips (mm) with the disc holding 95 % of them
    and the chip's corner directions at release (dashed), the 4-fold axis (solid)."""
    path = _path(path)
    xy = np.asarray(xy, dtype=float).reshape(-1, 2)
    if not np.isfinite(xy).all():
        raise InputError("xy: positions hold NaN or infinite values")
    figure, ax = _new_figure((5.2, 5.2))
    radius = float(statistics["disc95_mm"])
    ax.add_patch(
        Circle(
            (0, 0),
            radius,
            fill=False,
            color="tab:red",
            lw=1.5,
            label=f"95 % disc, r = {radius:.1f} mm",
        )
    )
    ax.scatter(xy[:, 0], xy[:, 1], s=14, color="tab:red", alpha=0.8, label="final positions")
    reach = max(radius, float(np.abs(xy).max(initial=1.0))) * 1.1
    for k in range(4):
        angle = math.radians(yaw_deg + 45 + 90 * k)
        ax.plot(
            [0, reach * math.cos(angle)],
            [0, reach * math.sin(angle)],
            ls="--",
            color="0.5",
            lw=0.8,
            label="corner directions" if k == 0 else None,
        )
        axis = math.radians(float(statistics["axis_deg"]) + 90 * k)
        ax.plot(
            [0, reach * math.cos(axis)],
            [0, reach * math.sin(axis)],
            color="tab:blue",
            lw=0.8,
            label="4-fold axis of the scatter" if k == 0 else None,
        )
    ax.set_xlim(-reach, reach)
    ax.set_ylim(-reach, reach)
    ax.set_aspect("equal")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_title(
        f"{statistics['drops']} drops: anisotropy {statistics['anisotropy']:.2f} "
        f"(p = {statistics['anisotropy_p']:.2g})",
        fontsize=9,
    )
    ax.legend(loc="upper right", fontsize=7)
    _save(figure, path)
    return path


def plot_force_displacement(path: str | os.PathLike, press_mm, force_n) -> None:
    """The platen force against the press of a compaction, from (0, 0)."""
    path = _path(path)
    press, force = _vector(press_mm, "press_mm"), _vector(force_n, "force_n")
    if len(press) != len(force) or not len(press):
        raise InputError("press_mm, force_n: need the same, non-zero number of values")
    figure, ax = _new_figure((6.0, 4.5))
    ax.plot(np.concatenate([[0.0], press]), np.concatenate([[0.0], force]), "o-", linewidth=2)
    ax.set_xlabel("press of the top platen (mm)")
    ax.set_ylabel("platen force (N)")
    ax.set_title("Compaction of the stack")
    ax.grid(alpha=0.3)
    _save(figure, path)


def plot_loose_press(path: str | os.PathLike, travel_mm, pressure_mpa, area_mm2, voids) -> Path:
    """A loose press against the platen's travel (mm): the nominal pressure (MPa), the
    contact area between chips (mm^2) and the void fraction of the stack's box (%)."""
    path = _path(path)
    travel = _vector(travel_mm, "travel_mm")
    series = [_vector(v, n) for v, n in ((pressure_mpa, "pressure_mpa"), (area_mm2, "area_mm2"))]
    voids = _vector(voids, "voids")
    if not len(travel) or any(len(v) != len(travel) for v in (*series, voids)):
        raise InputError("travel_mm, pressure_mpa, area_mm2, voids: need the same, non-zero length")
    figure = Figure(figsize=(11.0, 3.8), dpi=DPI, layout="constrained")
    FigureCanvasAgg(figure)
    axes = figure.subplots(1, 3)
    for ax, values, label in zip(
        axes,
        (*series, 100 * voids),
        ("nominal pressure (MPa)", "contact area between chips (mm$^2$)", "voids in the box (%)"),
        strict=True,
    ):
        ax.plot(travel, values, "o-", markersize=3, linewidth=1.5)
        ax.set_xlabel("platen travel (mm)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    figure.suptitle("The loose stack pressed")
    _save(figure, path)
    return path


def plot_mat(path: object, record: Mapping) -> Path:
    """A poured mat (``mat.json``'s record): areal-weight map over the belt (g/m^2), the
    thickness profiles along and across the belt (mm), and the chips' in-plane angles
    from the belt's direction of travel."""
    path = _path(path)
    weight, thickness = record["areal_weight"], record["thickness"]
    orientation = record["orientation"]
    figure = Figure(figsize=(11.0, 6.4), dpi=DPI, layout="constrained")
    FigureCanvasAgg(figure)
    grid = figure.add_gridspec(2, 3)
    ax = figure.add_subplot(grid[0, :])
    x_edges, y_edges = np.asarray(weight["x_edges_mm"]), np.asarray(weight["y_edges_mm"])
    mesh = ax.pcolormesh(
        x_edges, y_edges, np.asarray(weight["map_g_m2"]).T, cmap="viridis", shading="flat"
    )
    figure.colorbar(mesh, ax=ax, label="areal weight (g/m$^2$)")
    ax.set_aspect("equal")
    ax.set_xlabel("x along the belt (mm)")
    ax.set_ylabel("y across (mm)")
    ax.set_title(
        f"areal weight over {weight['cell_mm']:g} mm cells: mean {weight['mean_g_m2']:.0f} "
        f"g/m$^2$, CV {weight['cv']:.3f}"
    )
    ax = figure.add_subplot(grid[1, 0])
    ax.plot(thickness["along_x_mm"], thickness["along_mm"], color="tab:blue")
    ax.set_xlabel("x along the belt (mm)")
    ax.set_ylabel("mean top height (mm)")
    ax.set_title(f"along the belt, CV {thickness['cv_along']:.3f}")
    ax = figure.add_subplot(grid[1, 1])
    ax.plot(thickness["across_y_mm"], thickness["across_mm"], color="tab:red")
    ax.set_xlabel("y across the belt (mm)")
    ax.set_ylabel("mean top height (mm)")
    ax.set_title(f"across the belt, CV {thickness['cv_across']:.3f}")
    ax = figure.add_subplot(grid[1, 2])
    edges = np.asarray(orientation["angle_edges_deg"])
    ax.bar(
        edges[:-1],
        orientation["angle_fraction"],
        width=np.diff(edges),
        align="edge",
        color="tab:green",
        edgecolor="white",
    )
    ax.set_xlabel("chip x axis from the belt direction (deg)")
    ax.set_ylabel("fraction of chips")
    ax.set_title(f"<cos 2θ> = {orientation['order_cos2']:.3f}")
    _save(figure, path)
    return path


def plot_sweep(path: object, record: Mapping, key: str, columns: int = 5) -> Path:
    """Every scalar of a sweep (``sweep.json``'s record) against the swept ``key``: the
    mean over the repeats and its 95 % interval at each point, one line for each
    combination of the other swept keys."""
    path = _path(path)
    points = record["points"]
    others = [k for k in record["keys"] if k != key]
    names = sorted({n for p in points for n, s in p["scalars"].items() if s["mean"] is not None})
    if not names:
        raise InputError("record: the sweep has no scalar to draw")
    rows = math.ceil(len(names) / columns)
    figure = Figure(figsize=(3.2 * columns, 2.4 * rows), dpi=DPI, layout="constrained")
    FigureCanvasAgg(figure)
    values = [p["values"][key] for p in points]
    numeric = all(isinstance(v, int | float) and not isinstance(v, bool) for v in values)
    order = sorted(set(values), key=lambda v: v if numeric else str(v))
    groups: dict[tuple, list[Mapping]] = {}
    for p in points:
        groups.setdefault(tuple(p["values"][k] for k in others), []).append(p)
    for index, name in enumerate(names):
        ax = figure.add_subplot(rows, columns, index + 1)
        for label, members in groups.items():
            members = sorted(members, key=lambda p: order.index(p["values"][key]))
            x = [p["values"][key] if numeric else order.index(p["values"][key]) for p in members]
            stats = [p["scalars"].get(name, {}) for p in members]
            mean = np.array([np.nan if s.get("mean") is None else s["mean"] for s in stats])
            low = np.array([np.nan if s.get("ci_low") is None else s["ci_low"] for s in stats])
            high = np.array([np.nan if s.get("ci_high") is None else s["ci_high"] for s in stats])
            text = ", ".join(f"{k}={v}" for k, v in zip(others, label, strict=True))
            ax.errorbar(
                x,
                mean,
                yerr=[np.nan_to_num(mean - low), np.nan_to_num(high - mean)],
                marker="o",
                ms=3,
                capsize=2,
                label=text or None,
            )
        unit = next((p["scalars"][name].get("unit") for p in points if name in p["scalars"]), "")
        ax.set_title(name + (f" ({unit})" if unit else ""), fontsize=7)
        ax.tick_params(labelsize=6)
        if not numeric:
            ax.set_xticks(range(len(order)), [str(v) for v in order])
        if others and index == 0:
            ax.legend(fontsize=5)
    figure.suptitle(
        f"{record['scenario']}: every scalar against {key} (mean and 95 % interval over "
        f"{record['repeats']} repeats)",
        fontsize=9,
    )
    _save(figure, path)
    return path
