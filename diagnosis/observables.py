"""Observables of a drop scatter: pure functions of the final poses.

Every function takes positions (n, 2) mm relative to the release point and, where used,
final yaw and tilt (n,) deg, and returns plain floats in the units named.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.distance import cdist

from chipstack.packing.shapes import make_shape

__all__ = [
    "DROP_OBSERVABLES",
    "drop_features",
    "FeatureMetric",
    "drop_observables",
    "observable_names",
    "symmetry_order",
]

# name -> (unit, description)
DROP_OBSERVABLES: dict[str, tuple[str, str]] = {
    "r_q25": ("mm", "25th percentile of the distance to the release point"),
    "r_q50": ("mm", "median distance to the release point"),
    "r_q75": ("mm", "75th percentile of the distance"),
    "r_q90": ("mm", "90th percentile of the distance"),
    "r95": ("mm", "radius of the disc about the release point holding 95 % of the drops"),
    "mean_x": ("mm", "mean offset along x"),
    "mean_y": ("mm", "mean offset along y"),
    "aniso_c": ("", "X-shaped anisotropy: mean cos 4(theta - yaw0), + along the chip's sides"),
    "aniso_s": ("", "X-shaped anisotropy: mean sin 4(theta - yaw0)"),
    "yaw_spread": ("", "circular variance of the final yaw over the chip's symmetry (0 to 1)"),
    "tilt_q50": ("deg", "median final tilt of the chip's normal"),
    "tilt_q90": ("deg", "90th percentile of the final tilt"),
}
_NEEDS = {"yaw_spread": "yaw", "tilt_q50": "tilt", "tilt_q90": "tilt"}


def observable_names(has_yaw: bool, has_tilt: bool) -> list[str]:
    have = {"yaw": has_yaw, "tilt": has_tilt}
    return [n for n in DROP_OBSERVABLES if n not in _NEEDS or have[_NEEDS[n]]]


def symmetry_order(scenario) -> int:
    """How many times the scenario's chip maps onto itself in a turn about its normal (its
    geometry's :attr:`~core.chipshape.ChipShape.plan_symmetry`: 4 for a square, 6 for
    a hexagon, 5 for a five-pointed star, 1 for an irregular polygon). It was read from
    the shape's name before, which gave a hexagon 4 and a star 2."""
    return make_shape(scenario.chips[0], np.random.default_rng(scenario.seed)).plan_symmetry


def drop_observables(
    positions: np.ndarray,
    yaw_deg: np.ndarray | None,
    tilt_deg: np.ndarray | None,
    release_yaw_deg: float,
    order: int,
    names: list[str],
) -> np.ndarray:
    """The named observables of one scatter, in the order of ``names``.

    Also of many scatters at once: positions (..., n, 2) mm, yaw and tilt (..., n) deg
    give (..., K), one row per scatter (a permutation test's every relabelling in one
    call, rather than a Python loop over them).
    """
    positions = np.asarray(positions, dtype=float)
    x, y = positions[..., 0], positions[..., 1]
    r = np.hypot(x, y)
    theta = np.arctan2(y, x) - np.radians(release_yaw_deg)
    # Drops within a hair of the release point carry no direction.
    weight = (r > 1e-6).astype(float)
    total = np.maximum(weight.sum(axis=-1), 1.0)
    values = {}
    q = np.quantile(r, [0.25, 0.5, 0.75, 0.9, 0.95], axis=-1)
    values.update(r_q25=q[0], r_q50=q[1], r_q75=q[2], r_q90=q[3], r95=q[4])
    values["mean_x"], values["mean_y"] = x.mean(axis=-1), y.mean(axis=-1)
    values["aniso_c"] = (weight * np.cos(4 * theta)).sum(axis=-1) / total
    values["aniso_s"] = (weight * np.sin(4 * theta)).sum(axis=-1) / total
    if yaw_deg is not None:
        turn = np.radians(order * (np.asarray(yaw_deg, dtype=float) - release_yaw_deg))
        resultant = np.hypot(np.cos(turn).mean(axis=-1), np.sin(turn).mean(axis=-1))
        values["yaw_spread"] = 1.0 - resultant
    if tilt_deg is not None:
        # Quantiles, not the mean: one chip in a hundred may come to rest on its edge.
        tilt_q = np.quantile(np.asarray(tilt_deg, dtype=float), [0.5, 0.9], axis=-1)
        values["tilt_q50"], values["tilt_q90"] = tilt_q[0], tilt_q[1]
    return np.stack([np.asarray(values[n], dtype=float) for n in names], axis=-1)


def drop_features(
    positions: np.ndarray,
    yaw_deg: np.ndarray | None,
    tilt_deg: np.ndarray | None,
    release_yaw_deg: float,
    order: int,
) -> np.ndarray:
    """Per-drop features (n, d) for whole-distribution comparisons: x and y (mm); the
    final yaw over the chip's symmetry as a point on the unit circle, cos and sin of
    ``order`` (yaw - release yaw) (dimensionless; a square chip turned by 90 deg is the
    same chip); the tilt (deg). Columns the data lack are left out."""
    columns = [np.asarray(positions, dtype=float)]
    if yaw_deg is not None:
        turn = np.radians(order * (np.asarray(yaw_deg, dtype=float) - release_yaw_deg))
        columns.append(np.column_stack([np.cos(turn), np.sin(turn)]))
    if tilt_deg is not None:
        columns.append(np.asarray(tilt_deg, dtype=float)[:, None])
    return np.hstack(columns)


@dataclass(frozen=True)
class FeatureMetric:
    """How one condition's drop features are compared: each block (position, yaw,
    tilt) gets its own distance, and a drop-to-drop distance is their sum, so that a
    noisy block (the yaw of a chip that spins freely) does not drown a clear one.

    Position and tilt have heavy tails (a chip that slides 2 m, one that comes to rest
    on its edge): both are compressed, the distance from the release point r to
    r0 log(1 + r / r0) (direction kept) and the tilt t to t0 log(1 + t / t0), r0 and
    t0 being the pooled drops' medians; then every column is divided by its pooled
    standard deviation (the two yaw columns by one, so the circle stays round). Fixed
    from the experiment pooled with the baseline simulation, it is the same under any
    relabelling of those drops, which keeps the permutation tests exact."""

    r0_mm: float
    t0_deg: float
    scale: np.ndarray  # (d,) of the compressed columns
    blocks: dict[str, tuple[int, ...]]  # block name -> its columns

    @classmethod
    def of(cls, pooled: np.ndarray, has_yaw: bool, has_tilt: bool) -> FeatureMetric:
        blocks = {"position": (0, 1)}
        if has_yaw:
            blocks["yaw"] = (2, 3)
        if has_tilt:
            blocks["tilt"] = (pooled.shape[1] - 1,)
        r0 = max(float(np.median(np.hypot(pooled[:, 0], pooled[:, 1]))), 1e-3)
        t0 = max(float(np.median(pooled[:, -1])), 1e-2) if has_tilt else 1.0
        unscaled = cls(r0, t0, np.ones(pooled.shape[1]), blocks)
        sd = unscaled.compress(pooled).std(axis=0)
        if has_yaw:
            sd[2:4] = np.sqrt(np.mean(sd[2:4] ** 2))
        return cls(r0, t0, np.where(sd > 1e-9, sd, 1.0), blocks)

    def compress(self, raw: np.ndarray) -> np.ndarray:
        out = np.array(raw, dtype=float)
        r = np.hypot(out[:, 0], out[:, 1])
        squeezed = self.r0_mm * np.log1p(r / self.r0_mm)
        out[:, :2] *= np.where(r > 0, squeezed / np.maximum(r, 1e-300), 0.0)[:, None]
        if "tilt" in self.blocks:
            out[:, -1] = self.t0_deg * np.log1p(np.abs(out[:, -1]) / self.t0_deg)
        return out

    def apply(self, raw: np.ndarray) -> np.ndarray:
        """Compressed, standardised features (n, d) of raw ``drop_features``."""
        return self.compress(raw) / self.scale

    def distances(self, a: np.ndarray, b: np.ndarray | None = None) -> np.ndarray:
        """Per-block Euclidean distances (blocks, n, m) between standardised features."""
        b = a if b is None else b
        return np.stack([cdist(a[:, list(c)], b[:, list(c)]) for c in self.blocks.values()])


def anisotropy(aniso_c: float, aniso_s: float, release_yaw_deg: float) -> tuple[float, float]:
    """Strength (0 to 1) and axis (deg, world frame, in [0, 90)) of the X-shaped scatter."""
    strength = float(np.hypot(aniso_c, aniso_s))
    axis = (np.degrees(np.arctan2(aniso_s, aniso_c)) / 4 + release_yaw_deg) % 90.0
    return strength, float(axis)
