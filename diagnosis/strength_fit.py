"""One strength (or a strength and a release tilt) fitted on a noisy discrepancy, as the
drop and the stack diagnoses both fit it: the vertex of the parabola through a curve's
lowest grid points (:func:`vertex`), the curve's minimum once smoothed by local quadratic
regression (:func:`smoothed_minimum`, :func:`smoothed_minimum_value`), the strengths a
refined grid adds near it (:func:`refined_strengths`), the fits' rounding lattice
(:func:`snap`), the minimum of a quadratic surface over two parameters
(:func:`quadratic_minimum`), and the grid values within a fit's 95 % interval
(:func:`within`). Strengths are in the effect's own unit, curves are energy distances
(one column per resample).
"""

from __future__ import annotations

import functools

import numpy as np

from chipstack.diagnosis.statistics import interval

__all__ = [
    "REFINE_OFFSETS",
    "SMOOTHING_POINTS",
    "SMOOTHING_SPAN",
    "STRENGTH_RESOLUTION",
    "SURFACE_POINTS",
    "quadratic_minimum",
    "refined_strengths",
    "smoothed_minimum",
    "smoothed_minimum_value",
    "snap",
    "vertex",
    "within",
]

# Points per side of the fine grid the joint fit's quadratic surface is minimised on.
SURFACE_POINTS = 81
# Fitted strengths are rounded to this share of the prior's range (one setting for
# fits that land within it of each other).
STRENGTH_RESOLUTION = 1e-3
# A strength is fitted on its discrepancy curve smoothed over this many grid points
# (``smoothed_minimum``), minimised on this many points across the grid (the result is
# then rounded to STRENGTH_RESOLUTION of the prior, finer than their spacing).
SMOOTHING_SPAN = 7
SMOOTHING_POINTS = 401
# Where the whole data's coarse curve dips below its value at the neutral strength, the
# strengths this far (in coarse grid steps) from its lowest point and from its smoothed
# minimum are simulated too (``StrengthGrids.refine``); a new strength closer than a
# sixth of a step to one already tried is not added.
REFINE_OFFSETS = (-2 / 3, -1 / 3, 0.0, 1 / 3, 2 / 3)


def vertex(grid: list[float], curve: np.ndarray, resolution: float) -> np.ndarray:
    """The minimum of a discrepancy curve (S, R) over ``grid`` (S,), per column: the
    vertex of the parabola through the lowest grid point and its two neighbours, kept
    between those neighbours (at an end of the grid, the end's three points, kept
    between the end and its neighbour), rounded to ``resolution``. A smooth surrogate of
    the curve, not the argmin of the grid: strengths between grid points are found, and
    one noisy grid point moves the estimate a little, not by a whole grid step."""
    x = np.asarray(grid, dtype=float)
    curve = np.asarray(curve, dtype=float).reshape(len(x), -1)
    k = curve.argmin(axis=0)
    if len(x) < 3:
        return x[k]
    centre = np.clip(k, 1, len(x) - 2)
    cols = np.arange(curve.shape[1])
    x0, x1, x2 = x[centre - 1], x[centre], x[centre + 1]
    y0, y1, y2 = curve[centre - 1, cols], curve[centre, cols], curve[centre + 1, cols]
    num = (x1 - x0) ** 2 * (y1 - y2) - (x1 - x2) ** 2 * (y1 - y0)
    den = (x1 - x0) * (y1 - y2) - (x1 - x2) * (y1 - y0)
    with np.errstate(divide="ignore", invalid="ignore"):
        # den < 0: the three points bend upwards (a minimum between them).
        v = np.where(den < 0, x1 - 0.5 * num / den, x[k])
    v = np.clip(v, x[np.maximum(k - 1, 0)], x[np.minimum(k + 1, len(x) - 1)])
    return snap(v, resolution, x[0], x[-1])


def smoothed_minimum(
    grid: list[float], curve: np.ndarray, resolution: float, span: int = SMOOTHING_SPAN
) -> np.ndarray:
    """The minimum of a noisy discrepancy curve (S, R) over ``grid`` (S,), per column:
    the curve smoothed by local quadratic regression (LOESS: at each point of a fine
    grid, a parabola fitted by weighted least squares to the ``span`` nearest grid
    points, tricube weights) and minimised on the fine grid, rounded to ``resolution``.

    Why not ``vertex``: each grid point is its own simulation, and when an effect moves
    the drops little for its strength (air drag below 2) the noise of one point is as
    large as the whole curve's bend; the parabola through the lowest point and its two
    neighbours then follows that one point (measured, sweep case air drag 1.33: grid
    sums 0.40, 0.45, 0.40, 0.39 at 0.8 to 2.0, 0.09 at 1.33, folds fitted 1.86 and
    0.87). Pooling ``span`` points divides the noise's variance by about that many,
    at the price of a little bias where the curve bends sharply."""
    x = np.asarray(grid, dtype=float)
    curve = np.asarray(curve, dtype=float).reshape(len(x), -1)
    if len(x) <= 3:
        return vertex(grid, curve, resolution)
    fine, smooth, k = _smoothed(x, curve, span)
    return snap(fine[k], resolution, x[0], x[-1])


def smoothed_minimum_value(
    grid: list[float], curve: np.ndarray, span: int = SMOOTHING_SPAN
) -> np.ndarray:
    """The value of the smoothed curve (S, R) at ``smoothed_minimum``'s point, per column
    (R,): the discrepancy left at the fitted strength, read off the same local-quadratic
    fit (on three grid points or fewer, the lowest grid value)."""
    x = np.asarray(grid, dtype=float)
    curve = np.asarray(curve, dtype=float).reshape(len(x), -1)
    if len(x) <= 3:
        return curve.min(axis=0)
    _, smooth, k = _smoothed(x, curve, span)
    return smooth[k, np.arange(curve.shape[1])]


def _smoothed(x: np.ndarray, curve: np.ndarray, span: int) -> tuple:
    """The fine grid (F,), the smoothed curve on it (F, R) and the index of each column's
    minimum (R,), an end of the grid kept only where the raw curve is lowest there."""
    fine = np.linspace(x[0], x[-1], SMOOTHING_POINTS)
    # The same grid is fitted for every fold, dataset and resample: its map is built once.
    smooth = _loess_matrix(tuple(x.tolist()), max(3, min(span, len(x)))) @ curve  # (F, R)
    k = smooth.argmin(axis=0)
    # A parabola fitted at an end of the grid leans on neighbours all on one side, so its
    # value there is twice as noisy as mid-grid: on flat noise alone 39 % of minima land
    # on an end (the vertex: 17 %). An end is kept only where the raw curve is lowest
    # at that end point too; elsewhere the smoothed curve's minimum between the second
    # and the second-to-last grid points is taken (17 % on flat noise).
    raw = curve.argmin(axis=0)
    astray = ((k == 0) & (raw != 0)) | ((k == len(fine) - 1) & (raw != len(x) - 1))
    if astray.any():
        inner = np.flatnonzero((fine >= x[1]) & (fine <= x[-2]))
        k[astray] = inner[smooth[inner][:, astray].argmin(axis=0)]
    return fine, smooth, k


@functools.lru_cache(maxsize=64)
def _loess_matrix(grid: tuple[float, ...], span: int) -> np.ndarray:
    """The linear map from values on ``grid`` to their local-quadratic fit at the
    ``SMOOTHING_POINTS`` points across it (SMOOTHING_POINTS, len(grid)): row i holds the
    weights of the intercept of the parabola fitted there. The bandwidth reaches just
    past the ``span``-th nearest grid point (so that it weighs in; ``span`` >= 3, as a
    parabola needs three)."""
    x = np.asarray(grid)
    step = np.min(np.diff(x))
    rows = []
    for u in np.linspace(x[0], x[-1], SMOOTHING_POINTS):
        d = np.abs(x - u)
        h = np.sort(d)[span - 1] + 0.5 * step
        w = np.clip(1 - (d / h) ** 3, 0.0, None) ** 3
        design = np.column_stack([np.ones_like(x), x - u, (x - u) ** 2])
        weighted = design * w[:, None]
        rows.append(np.linalg.solve(design.T @ weighted, weighted.T)[0])
    matrix = np.array(rows)
    matrix.flags.writeable = False  # shared by every caller through the cache
    return matrix


def refined_strengths(
    grid: list[float],
    curve: np.ndarray,
    neutral: float,
    prior: tuple[float, float],
    coarse_points: int,
) -> list[float]:
    """The strengths to add to ``grid`` (a coarse grid of ``coarse_points`` over
    ``prior``, plus the ``neutral`` strength) near the minima of ``curve`` ((S,), on
    ``grid``): when it is lower somewhere than at the neutral strength, the
    strengths ``REFINE_OFFSETS`` coarse steps from its lowest grid point and from its
    smoothed minimum (the smoothed minimum itself among them), on the fits' rounding
    lattice, none closer than a sixth of a step to a strength already there."""
    lo, hi = prior
    step = (hi - lo) / max(coarse_points - 1, 1)
    resolution = STRENGTH_RESOLUTION * (hi - lo)
    at_neutral = int(np.argmin(np.abs(np.asarray(grid) - neutral)))
    if abs(grid[at_neutral] - neutral) > 1e-9:
        raise ValueError(f"the neutral strength {neutral} is not on the grid {grid}")
    curve = np.asarray(curve, dtype=float)
    if not curve.min() < curve[at_neutral]:
        return []
    lowest = grid[int(np.argmin(curve))]
    smoothed = float(smoothed_minimum(grid, curve[:, None], resolution)[0])
    added: list[float] = []
    for centre in sorted({lowest, smoothed}):
        for offset in REFINE_OFFSETS:
            v = float(snap(np.array(centre + offset * step), resolution, lo, hi))
            if min(abs(v - g) for g in [*grid, *added]) > step / 6:
                added.append(v)
    return added


def snap(values: np.ndarray, resolution: float, low: float, high: float) -> np.ndarray:
    """``values`` rounded to ``resolution`` and kept within [low, high] (rounding must
    not leave a grid: a prior starting at 0.1, rounded to 0.0009, gives 0.0999)."""
    return np.clip(np.round(np.round(values / resolution) * resolution, 12), low, high)


def quadratic_minimum(
    xs: list[float], ys: list[float], surface: np.ndarray, points: int = SURFACE_POINTS
) -> tuple[np.ndarray, np.ndarray]:
    """The minimum over the box ``xs`` x ``ys`` (3 values each) of the quadratic surface
    (constant, linear, square and cross terms) fitted by least squares to ``surface``
    (3, 3, C), per column: a smooth surrogate of a noisy two-parameter discrepancy, found
    on a fine grid of the box, so that a saddle or a ridge still gives a point inside."""
    x, y = np.asarray(xs, dtype=float), np.asarray(ys, dtype=float)
    x0, xr = x[1], x[-1] - x[0]
    y0, yr = y[1], y[-1] - y[0]

    def design(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        return np.column_stack([np.ones_like(u), u, v, u**2, v**2, u * v])

    u, v = (g.ravel() for g in np.meshgrid((x - x0) / xr, (y - y0) / yr, indexing="ij"))
    coef, *_ = np.linalg.lstsq(design(u, v), surface.reshape(9, -1), rcond=None)
    fu, fv = (
        g.ravel()
        for g in np.meshgrid(
            np.linspace(u.min(), u.max(), points),
            np.linspace(v.min(), v.max(), points),
            indexing="ij",
        )
    )
    k = (design(fu, fv) @ coef).argmin(axis=0)
    return x0 + fu[k] * xr, y0 + fv[k] * yr


def within(grid, fitted: np.ndarray) -> list[float]:
    """The values of ``grid`` within the 95 % interval of a fit (``fitted``: the
    estimate, then one per resample)."""
    lo, hi = interval(np.asarray(fitted)[1:])
    return [float(v) for v in grid if lo <= v <= hi]
