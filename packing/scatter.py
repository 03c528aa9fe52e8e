"""Where dropped chips come to rest: spread and angular anisotropy of final positions.

Metrics of a set of points in the target plane (paper, section 4.2 and Fig. 15), as pure
functions. Lengths in mm, angles in degrees.
"""

from __future__ import annotations

import math

import numpy as np

from chipstack.core.errors import InputError

__all__ = ["drop_statistics", "rayleigh_p", "disc_radius"]


def disc_radius(distances: np.ndarray, fraction: float = 0.95) -> float:
    """Radius (mm) of the smallest disc centred on (0, 0) that holds at least ``fraction``
    of the points: the ceil(fraction N)-th smallest distance."""
    distances = np.sort(np.asarray(distances, dtype=float))
    if distances.size == 0:
        raise InputError("positions: no points")
    k = max(1, math.ceil(fraction * distances.size - 1e-9))
    return float(distances[k - 1])


def rayleigh_p(resultant: float, n: int) -> float:
    """p-value of Rayleigh's test that angles are uniform, given the mean resultant length
    ``resultant`` of n angles (Zar, Biostatistical Analysis, eq. 27.4)."""
    if n < 2:
        return 1.0
    z = n * resultant**2
    p = math.exp(-z) * (
        1 + (2 * z - z**2) / (4 * n) - (24 * z - 132 * z**2 + 76 * z**3 - 9 * z**4) / (288 * n**2)
    )
    return float(min(max(p, 0.0), 1.0))


def drop_statistics(xy: np.ndarray, yaw_deg: float = 0.0, harmonic: int = 4) -> dict:
    """Spread and anisotropy of final positions ``xy`` (N, 2) mm around (0, 0).

    * ``distance_sd_mm``: standard deviation (ddof 1) of the distance to (0, 0);
      ``rms_distance_mm`` the root mean square distance; ``disc95_mm`` the radius of the
      smallest disc centred on (0, 0) holding 95 % of the points;
    * the ``harmonic``-fold anisotropy: ``anisotropy`` is the length of the mean of
      exp(i k theta) over the points' polar angles (0: isotropic, 1: all points on k
      rays); ``anisotropy_p`` its Rayleigh p-value; ``axis_deg`` the direction in
      [0, 360/k) of the rays; ``corner_offset_deg`` how far those rays are from the
      chip's corner directions (yaw + 45 deg + multiples of 90 deg), 0 to 45/... deg.
    Points at (0, 0) have no angle and are left out of the anisotropy.
    """
    xy = np.asarray(xy, dtype=float).reshape(-1, 2)
    if len(xy) == 0:
        raise InputError("positions: no points")
    distance = np.hypot(xy[:, 0], xy[:, 1])
    moved = distance > 1e-9
    theta = np.arctan2(xy[moved, 1], xy[moved, 0])
    mean = np.exp(1j * harmonic * theta).mean() if moved.any() else 0j
    period = 360.0 / harmonic
    axis = (math.degrees(np.angle(mean)) / harmonic) % period if moved.any() else float("nan")
    corner = (yaw_deg + 45.0) % period
    offset = abs((axis - corner + period / 2) % period - period / 2)
    return {
        "drops": int(len(xy)),
        "mean_x_mm": float(xy[:, 0].mean()),
        "mean_y_mm": float(xy[:, 1].mean()),
        "mean_distance_mm": float(distance.mean()),
        "distance_sd_mm": float(distance.std(ddof=1)) if len(xy) > 1 else 0.0,
        "rms_distance_mm": float(np.sqrt((distance**2).mean())),
        "disc95_mm": disc_radius(distance, 0.95),
        "harmonic": harmonic,
        "anisotropy": float(abs(mean)),
        "anisotropy_p": rayleigh_p(float(abs(mean)), int(moved.sum())),
        "axis_deg": float(axis),
        "corner_offset_deg": float(offset),
    }
