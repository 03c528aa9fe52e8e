"""What a line's users watch on a mat poured onto a belt: areal weight, thickness and chip
orientation (kind ``conveyor``; see docs/conveyor.md).

Pure functions of the chips' poses and shapes, in the belt's frame: x along the belt in
its direction of travel, y across it from the centre line, z up from the belt. The
panel cut from the mat goes through the geometry stage like any stack; these describe
the whole mat, which the panel is a window of.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import Delaunay
from scipy.spatial.transform import Rotation

from chipstack.core.errors import InputError

__all__ = [
    "areal_weight_map",
    "coefficient_of_variation",
    "surface_samples",
    "thickness_map",
    "orientation_distribution",
]


def _cells(low: float, high: float, cell_mm: float, inside: bool = False) -> np.ndarray:
    """Edges of cells of ``cell_mm`` over [low, high]: covering it from ``low`` (the last
    cell may stick out), or, ``inside``, only whole cells within it, centred (half the
    remainder left out at each end)."""
    if not (math.isfinite(cell_mm) and cell_mm > 0):
        raise InputError(f"cell_mm: must be positive, got {cell_mm!r}")
    if not high > low:
        raise InputError(f"range: needs low < high, got [{low}, {high}]")
    if not inside:
        count = max(1, math.ceil((high - low) / cell_mm - 1e-9))
        return low + cell_mm * np.arange(count + 1)
    count = math.floor((high - low) / cell_mm + 1e-9)
    if count < 1:
        raise InputError(
            f"cell_mm: a cell of {cell_mm:g} mm does not fit in [{low:.1f}, {high:.1f}] mm"
        )
    start = low + ((high - low) - count * cell_mm) / 2
    return start + cell_mm * np.arange(count + 1)


def areal_weight_map(
    xy_mm: np.ndarray,
    masses_g: np.ndarray,
    x_range_mm: tuple[float, float],
    y_range_mm: tuple[float, float],
    cell_mm: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Areal weight over square cells, in g/m^2 (each chip's whole mass in the cell of its
    centre of mass: right for cells several chips wide).

    xy_mm (n, 2) centres of mass; masses_g (n,). Whole cells tile ``x_range_mm`` x
    ``y_range_mm``, centred in each range: a range that is not a whole number of cells
    loses half the remainder at each end (a partial cell would read low). Returns
    (map (nx, ny) g/m^2, x edges, y edges) in mm.
    """
    xy = np.asarray(xy_mm, dtype=float).reshape(-1, 2)
    masses = np.asarray(masses_g, dtype=float).reshape(-1)
    if len(xy) != len(masses):
        raise InputError(f"masses_g: {len(masses)} masses for {len(xy)} chips")
    x_edges = _cells(*x_range_mm, cell_mm, inside=True)
    y_edges = _cells(*y_range_mm, cell_mm, inside=True)
    grams, _, _ = np.histogram2d(xy[:, 0], xy[:, 1], bins=(x_edges, y_edges), weights=masses)
    return grams / (cell_mm * cell_mm * 1e-6), x_edges, y_edges


def coefficient_of_variation(values: np.ndarray) -> float:
    """Standard deviation over mean (sample sd, ddof 1), dimensionless; NaN for fewer than
    two values or a zero mean."""
    values = np.asarray(values, dtype=float).reshape(-1)
    if len(values) < 2 or values.mean() == 0:
        return float("nan")
    return float(values.std(ddof=1) / values.mean())


def surface_samples(
    vertices: np.ndarray, convex_pieces: tuple[np.ndarray, ...], spacing_mm: float
) -> np.ndarray:
    """Points (m, 3) mm in a chip's frame covering its top and bottom faces (a grid of
    ``spacing_mm`` over its outline, at the lowest and highest local z of the piece under
    each point) plus its corners, for reading its height over the belt."""
    vertices = np.asarray(vertices, dtype=float)
    low, high = vertices.min(axis=0), vertices.max(axis=0)
    xs = np.arange(low[0], high[0] + 1e-9, spacing_mm)
    ys = np.arange(low[1], high[1] + 1e-9, spacing_mm)
    grid = np.stack(np.meshgrid(xs, ys, indexing="ij"), axis=-1).reshape(-1, 2)
    points = [vertices]
    for piece in convex_pieces:
        piece = np.asarray(piece, dtype=float)
        try:
            inside = Delaunay(piece[:, :2]).find_simplex(grid) >= 0
        except Exception:  # a piece flat in plan (a wall standing on edge): corners only
            continue
        if inside.any():
            for z in (piece[:, 2].min(), piece[:, 2].max()):
                points.append(np.column_stack([grid[inside], np.full(inside.sum(), z)]))
    return np.concatenate(points)


def thickness_map(
    positions_mm: np.ndarray,
    quaternions: np.ndarray,
    samples: list[np.ndarray],
    sample_index: np.ndarray,
    x_range_mm: tuple[float, float],
    y_range_mm: tuple[float, float],
    pixel_mm: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Height of the mat's top surface over the belt (mm) per pixel: the highest sampled
    point of any chip over it, 0 where the belt is bare.

    positions_mm (n, 3), quaternions (n, 4) x, y, z, w; samples: per shape, points in its
    frame (:func:`surface_samples`); sample_index (n,) the shape of each chip. Returns
    (map (nx, ny) mm, x edges, y edges).
    """
    positions = np.asarray(positions_mm, dtype=float).reshape(-1, 3)
    quaternions = np.asarray(quaternions, dtype=float).reshape(-1, 4)
    index = np.asarray(sample_index).reshape(-1)
    x_edges = _cells(*x_range_mm, pixel_mm)
    y_edges = _cells(*y_range_mm, pixel_mm)
    top = np.zeros((len(x_edges) - 1, len(y_edges) - 1))
    for k, points in enumerate(samples):
        mine = np.flatnonzero(index == k)
        if mine.size == 0:
            continue
        matrices = Rotation.from_quat(quaternions[mine]).as_matrix()
        world = np.einsum("nij,mj->nmi", matrices, points) + positions[mine, None, :]
        world = world.reshape(-1, 3)
        i = np.floor((world[:, 0] - x_edges[0]) / pixel_mm).astype(np.int64)
        j = np.floor((world[:, 1] - y_edges[0]) / pixel_mm).astype(np.int64)
        keep = (i >= 0) & (i < top.shape[0]) & (j >= 0) & (j < top.shape[1])
        np.maximum.at(top, (i[keep], j[keep]), np.maximum(world[keep, 2], 0.0))
    return top, x_edges, y_edges


def orientation_distribution(quaternions: np.ndarray, bins: int = 18) -> dict:
    """How chips lie relative to the belt: the in-plane angle of each chip's local x axis
    from the belt's direction of travel, folded into [0, 180) deg, and its tilt (the angle
    of the chip's local z from the vertical, deg).

    Returns ``angle_edges_deg`` and ``angle_fraction`` (the histogram, fractions summing to
    1), ``order_cos2`` = <cos 2 theta> (1: all along the belt, -1: all across, 0: no
    preference; for a square chip x and y are alike, see ``order_cos4``), ``order_cos4``
    = <cos 4 theta>, ``mean_tilt_deg`` and ``flat_fraction`` (tilt under 10 deg).
    Chips standing on edge (local x nearly vertical) have no in-plane angle: left out of
    the angle statistics.
    """
    quaternions = np.asarray(quaternions, dtype=float).reshape(-1, 4)
    if len(quaternions) == 0:
        raise InputError("quaternions: no chips to describe")
    matrices = Rotation.from_quat(quaternions).as_matrix()
    axis_x, axis_z = matrices[:, :, 0], matrices[:, :, 2]
    in_plane = np.hypot(axis_x[:, 0], axis_x[:, 1]) > 0.1
    theta = np.degrees(np.arctan2(axis_x[in_plane, 1], axis_x[in_plane, 0])) % 180.0
    edges = np.linspace(0.0, 180.0, bins + 1)
    counts, _ = np.histogram(theta, bins=edges)
    tilt = np.degrees(np.arccos(np.clip(np.abs(axis_z[:, 2]), 0.0, 1.0)))
    radians = np.radians(theta)
    return {
        "angle_edges_deg": edges.tolist(),
        "angle_fraction": (counts / max(counts.sum(), 1)).tolist(),
        "order_cos2": float(np.mean(np.cos(2 * radians))) if len(theta) else float("nan"),
        "order_cos4": float(np.mean(np.cos(4 * radians))) if len(theta) else float("nan"),
        "mean_tilt_deg": float(tilt.mean()),
        "flat_fraction": float((tilt < 10.0).mean()),
        "chips_with_angle": int(len(theta)),
    }
