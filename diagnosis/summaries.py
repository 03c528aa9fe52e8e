"""Summary statistics of one condition's drops: the features the amortised model choice
learns from (``diagnosis.model_choice``). Pure functions: arrays in, a flat vector out.

A drop scatter is summarised by what the effects move: how far the chips slide (the
distance quantiles, on a log scale as well because a slide has a heavy tail), the shape
of the scatter (offsets, spreads, the X-shaped anisotropy of order 4 and its neighbours
of orders 2 and 8 about the release yaw), how the chip turned (the circular moments of
the yaw over the chip's symmetry, the distribution of the turn) and how it came to rest
(the tilt quantiles, the share resting on an edge), and how these go together (the
correlations of distance, turn and tilt). Columns that need an angle the experiment did
not record are left out.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from chipstack.diagnosis.model import DropData

if TYPE_CHECKING:
    from chipstack.diagnosis.model import Experiment

__all__ = ["condition_summaries", "design_summaries", "summary_names"]

_R_QUANTILES = (0.05, 0.1, 0.25, 0.5, 0.75, 0.9, 0.95)
_TILT_QUANTILES = (0.1, 0.25, 0.5, 0.75, 0.9, 0.95)
_TURN_QUANTILES = (0.25, 0.5, 0.75, 0.9)
_TILT_THRESHOLDS_DEG = (2.0, 5.0, 20.0, 60.0)

_POSITION_NAMES = (
    *(f"r_q{int(100 * q):02d}" for q in _R_QUANTILES),
    "log_r_mean",
    "log_r_sd",
    "mean_x",
    "mean_y",
    "sd_along",
    "sd_across",
    "aniso2_c",
    "aniso2_s",
    "aniso4_c",
    "aniso4_s",
    "aniso8_c",
    "aniso8_s",
)
_YAW_NAMES = (
    "yaw1_c",
    "yaw1_s",
    "yaw_spread",
    "yaw2_c",
    *(f"turn_q{int(100 * q):02d}" for q in _TURN_QUANTILES),
    "corr_r_turn",
)
_TILT_NAMES = (
    *(f"tilt_q{int(100 * q):02d}" for q in _TILT_QUANTILES),
    "log_tilt_mean",
    *(f"tilt_over_{t:g}" for t in _TILT_THRESHOLDS_DEG),
    "corr_r_tilt",
)


def summary_names(has_yaw: bool, has_tilt: bool) -> list[str]:
    """Names of the columns :func:`condition_summaries` returns, in order."""
    return [
        *_POSITION_NAMES,
        *(_YAW_NAMES if has_yaw else ()),
        *(_TILT_NAMES if has_tilt else ()),
    ]


def _corr(a: np.ndarray, b: np.ndarray) -> float:
    sa, sb = a.std(), b.std()
    if sa < 1e-12 or sb < 1e-12:
        return 0.0
    return float(np.mean((a - a.mean()) * (b - b.mean())) / (sa * sb))


def condition_summaries(
    positions: np.ndarray,
    yaw_deg: np.ndarray | None,
    tilt_deg: np.ndarray | None,
    release_yaw_deg: float,
    order: int,
) -> np.ndarray:
    """Summary vector of one condition's drops.

    Parameters
    ----------
    positions : (n, 2) array
        Final positions (mm) relative to the release point.
    yaw_deg, tilt_deg : (n,) arrays or None
        Final yaw of the chip's x axis and tilt of its normal (deg); None when not
        recorded (their columns are left out).
    release_yaw_deg : float
        The condition's release yaw (deg): directions are taken relative to it.
    order : int
        The chip's symmetry order about its normal (4 for a square).

    Returns
    -------
    (k,) array
        In the order of :func:`summary_names`: distances in mm, log distances in
        log(mm), angles' quantiles in deg, shares and circular moments dimensionless.
    """
    positions = np.asarray(positions, dtype=float)
    x, y = positions[:, 0], positions[:, 1]
    r = np.hypot(x, y)
    yaw0 = np.radians(release_yaw_deg)
    theta = np.arctan2(y, x) - yaw0
    # In the frame of the release yaw: spreads along and across the chip's first side.
    along = x * np.cos(yaw0) + y * np.sin(yaw0)
    across = -x * np.sin(yaw0) + y * np.cos(yaw0)
    weight = (r > 1e-6).astype(float)
    total = max(weight.sum(), 1.0)
    log_r = np.log(r + 0.1)
    values = [
        *np.quantile(r, _R_QUANTILES),
        log_r.mean(),
        log_r.std(),
        x.mean(),
        y.mean(),
        along.std(),
        across.std(),
    ]
    for k in (2, 4, 8):
        values += [(weight * np.cos(k * theta)).sum() / total]
        values += [(weight * np.sin(k * theta)).sum() / total]
    if yaw_deg is not None:
        turn = np.radians(order * (np.asarray(yaw_deg, dtype=float) - release_yaw_deg))
        c1, s1 = np.cos(turn).mean(), np.sin(turn).mean()
        # The turn from the release yaw, folded into the chip's symmetry: (-180, 180] / order.
        folded = np.abs(np.degrees(np.angle(np.exp(1j * turn)))) / order
        values += [c1, s1, 1.0 - np.hypot(c1, s1), np.cos(2 * turn).mean()]
        values += [*np.quantile(folded, _TURN_QUANTILES), _corr(log_r, folded)]
    if tilt_deg is not None:
        tilt = np.abs(np.asarray(tilt_deg, dtype=float))
        values += [*np.quantile(tilt, _TILT_QUANTILES), np.log(tilt + 0.1).mean()]
        values += [float(np.mean(tilt > t)) for t in _TILT_THRESHOLDS_DEG]
        values += [_corr(log_r, np.log(tilt + 0.1))]
    return np.asarray(values, dtype=float)


def design_summaries(
    drops: dict[str, np.ndarray] | dict[str, DropData],
    experiment: Experiment,
    order: int,
    has_yaw: bool,
    has_tilt: bool,
) -> np.ndarray:
    """One dataset's summary vector: every condition's :func:`condition_summaries`, in
    the spec's order. ``drops`` per condition: (n, 4) arrays (x, y mm, yaw, tilt deg) or
    :class:`DropData`."""
    parts = []
    for c in experiment.conditions:
        d = drops[c.name]
        if isinstance(d, DropData):
            positions, yaw, tilt = d.positions, d.yaw_deg, d.tilt_deg
        else:
            positions, yaw, tilt = d[:, :2], d[:, 2], d[:, 3]
        parts.append(
            condition_summaries(
                positions,
                yaw if has_yaw else None,
                tilt if has_tilt else None,
                c.protocol.yaw_deg,
                order,
            )
        )
    return np.concatenate(parts)
