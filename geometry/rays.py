"""Vertical rays through the stack: local stack thickness (NEH) and the top surface.

Section 3.1.2 of the paper: a vertical ray is cast at the centre of every pixel of a grid
over the target and the area around it, and every chip it passes through is counted (not
only the first hit). Rays are intersected with the exact convex pieces of each chip, so a
tilted chip is counted exactly where its footprint is.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from chipstack.core.arrangement import Arrangement
from chipstack.core.errors import InputError
from chipstack.geometry.solids import shape_pieces

__all__ = ["PixelGrid", "pixel_grid", "column_intervals", "RayMaps", "ray_maps"]

_VERTICAL = 1e-9  # |n_z| below this: a vertical face, a constraint on (x, y) only


@dataclass(frozen=True)
class PixelGrid:
    """A square-pixel grid in the plane; pixel (i, j) spans x0 + i p .. x0 + (i + 1) p."""

    x0: float
    y0: float
    pixel_mm: float
    nx: int
    ny: int
    target_size_mm: float

    @cached_property
    def x(self) -> np.ndarray:
        """(nx,) mm, pixel centres along x."""
        return self.x0 + self.pixel_mm * (np.arange(self.nx) + 0.5)

    @cached_property
    def y(self) -> np.ndarray:
        """(ny,) mm, pixel centres along y."""
        return self.y0 + self.pixel_mm * (np.arange(self.ny) + 0.5)

    @cached_property
    def on_target(self) -> np.ndarray:
        """(nx, ny) bool: the pixel's centre lies over the target square."""
        half = self.target_size_mm / 2
        inside_x = np.abs(self.x) <= half
        inside_y = np.abs(self.y) <= half
        return inside_x[:, None] & inside_y[None, :]


def pixel_grid(arrangement: Arrangement, pixel_mm: float) -> PixelGrid:
    """A grid aligned on the target's corner that covers the target and every chip.

    The target's lower-left corner is a pixel corner, so a target whose side is a multiple
    of the pixel is tiled exactly (150 mm by 3 mm: 50 x 50 pixels).
    """
    if not (math.isfinite(pixel_mm) and pixel_mm > 0):
        raise InputError(f"pixel_mm: must be positive, got {pixel_mm!r}")
    half = arrangement.target_size_mm / 2
    low, high = np.array([-half, -half]), np.array([half, half])
    if arrangement.n_chips:
        low = np.minimum(low, arrangement.bounds[:, 0, :2].min(axis=0))
        high = np.maximum(high, arrangement.bounds[:, 1, :2].max(axis=0))
    before = np.ceil((-half - low) / pixel_mm)
    after = np.ceil((high - half) / pixel_mm)
    n_target = math.ceil(2 * half / pixel_mm - 1e-9)
    nx, ny = (before + after).astype(int) + n_target
    if nx * ny > 50_000_000:
        raise InputError(f"pixel_mm: {pixel_mm} mm gives {nx} x {ny} pixels; choose a larger one")
    return PixelGrid(
        float(-half - before[0] * pixel_mm),
        float(-half - before[1] * pixel_mm),
        float(pixel_mm),
        int(nx),
        int(ny),
        float(arrangement.target_size_mm),
    )


def column_intervals(
    arrangement: Arrangement, x: np.ndarray, y: np.ndarray, order: np.ndarray | None = None
) -> Iterator[tuple[int, slice, slice, np.ndarray, np.ndarray]]:
    """Where vertical lines through a grid of points cross each convex piece of each chip.

    ``x`` (nx,) and ``y`` (ny,) are sorted, evenly spaced coordinates (mm). Yields, per piece,
    (chip, x slice, y slice, bottom, top): the (sx, sy) block of lines that can meet the piece
    and, on each, the heights (mm) where it enters and leaves; ``bottom >= top`` where the
    line misses the piece. Chips come in index order, or in ``order`` when given.
    """
    if len(x) == 0 or len(y) == 0:
        return
    step_x = x[1] - x[0] if len(x) > 1 else 1.0
    step_y = y[1] - y[0] if len(y) > 1 else 1.0
    bounds = arrangement.bounds
    for chip in range(arrangement.n_chips) if order is None else order:
        chip = int(chip)
        shape = arrangement.shapes[arrangement.shape_index[chip]]
        sx = _covered(x, step_x, bounds[chip, 0, 0], bounds[chip, 1, 0])
        sy = _covered(y, step_y, bounds[chip, 0, 1], bounds[chip, 1, 1])
        if sx.start >= sx.stop or sy.start >= sy.stop:
            continue
        rotation, position = arrangement.rotations[chip], arrangement.positions[chip]
        px, py = x[sx][:, None], y[sy][None, :]
        for piece in shape_pieces(shape):
            normals = piece.normals @ rotation.T
            offsets = piece.offsets + normals @ position
            top = np.full((len(x[sx]), len(y[sy])), np.inf)
            bottom = np.full_like(top, -np.inf)
            for (nx_, ny_, nz_), d in zip(normals, offsets, strict=True):
                rest = d - nx_ * px - ny_ * py
                if nz_ > _VERTICAL:
                    np.minimum(top, rest / nz_, out=top)
                elif nz_ < -_VERTICAL:
                    np.maximum(bottom, rest / nz_, out=bottom)
                else:
                    outside = rest < 0
                    top[np.broadcast_to(outside, top.shape)] = -np.inf
            yield chip, sx, sy, bottom, top


def _covered(centres: np.ndarray, step: float, low: float, high: float) -> slice:
    first = max(0, math.ceil((low - centres[0]) / step - 1e-9))
    last = min(len(centres), math.floor((high - centres[0]) / step + 1e-9) + 1)
    return slice(first, max(first, last))


@dataclass(frozen=True)
class RayMaps:
    """Per-pixel results of vertical rays over a :class:`PixelGrid`.

    neh: (nx, ny) int, number of distinct chips each ray passes through (NEH).
    top_mm: (nx, ny) mm, height of the highest solid point on the ray (0: bare conveyor).
    solid_mm: (nx, ny) mm, total length of the ray inside chips (overlaps counted twice).
    """

    grid: PixelGrid
    neh: np.ndarray
    top_mm: np.ndarray
    solid_mm: np.ndarray


def ray_maps(arrangement: Arrangement, pixel_mm: float = 3.0) -> RayMaps:
    """Cast one vertical ray per pixel centre through the stack (see :class:`RayMaps`)."""
    grid = pixel_grid(arrangement, pixel_mm)
    neh = np.zeros((grid.nx, grid.ny), dtype=np.int64)
    top_map = np.zeros((grid.nx, grid.ny))
    solid = np.zeros((grid.nx, grid.ny))
    # The pieces of one chip come one after another over the same block of pixels; a ray
    # through two pieces of a non-convex chip still counts the chip once.
    current: tuple[int, slice, slice, np.ndarray] | None = None
    for chip, sx, sy, bottom, top in column_intervals(arrangement, grid.x, grid.y):
        hit = top > bottom
        if current is not None and current[0] != chip:
            neh[current[1], current[2]] += current[3]
            current = None
        if current is None:
            current = (chip, sx, sy, hit)
        else:
            current = (chip, sx, sy, current[3] | hit)
        if not hit.any():
            continue
        solid[sx, sy] += np.where(hit, top - bottom, 0.0)
        np.maximum(top_map[sx, sy], np.where(hit, top, 0.0), out=top_map[sx, sy])
    if current is not None:
        neh[current[1], current[2]] += current[3]
    for array in (neh, top_map, solid):
        array.setflags(write=False)
    return RayMaps(grid, neh, top_map, solid)
