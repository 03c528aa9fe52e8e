"""The strengths a drop diagnosis tries for each effect and the discrepancy over them:
:class:`StrengthGrids` (the coarse grid over each effect's prior and the strengths
refined near the whole data's minimum, the curves and surfaces of energy distance over
them, the strength fitted alone or jointly with the release tilt), :class:`JointFit` (a
strength and a release tilt offset fitted together) and :func:`best_tilt` (the
baseline's release tilt refitted). Tilts in degrees, strengths in the effect's unit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from chipstack.diagnosis.drop_simulations import Dataset, DropSimulations
from chipstack.diagnosis.statistics import interval
from chipstack.diagnosis.strength_fit import (
    STRENGTH_RESOLUTION,
    quadratic_minimum,
    refined_strengths,
    smoothed_minimum,
    smoothed_minimum_value,
    snap,
    vertex,
)
from chipstack.packing.effects import EFFECTS

__all__ = ["TILT_RESOLUTION_DEG", "TILT_STEP_DEG", "JointFit", "StrengthGrids", "best_tilt"]

TILT_RESOLUTION_DEG = 0.1
# The joint fit's release tilts: the spec's, and this much either side (less below when
# the spec's tilt is smaller; every condition is shifted by the same offset).
TILT_STEP_DEG = 2.5


@dataclass
class JointFit:
    """An effect's strength and release tilt offset fitted together: the estimates, then
    one per resample (1 + B,), and the three grid strengths the surface was fitted on."""

    strength: np.ndarray
    offset: np.ndarray
    stencil: list[float]


def best_tilt(sims: DropSimulations, datasets: list[Dataset]) -> np.ndarray:
    """The release tilt closest to ``datasets`` (summed energy distance, vertex over
    ``sims.tilt_grid``): the estimate, then one per resample (1 + B,)."""
    grid = sims.tilt_grid
    curve = np.array(
        [
            sum(sims.energy(ds, sims.grid_setting(ds.condition, t, None, 0.0)) for ds in datasets)
            for t in grid
        ]
    )
    return vertex(list(grid), curve, TILT_RESOLUTION_DEG)


class StrengthGrids:
    """The strengths tried for each effect (simulated for every condition at its own
    release tilt, and near the fitted strength at shifted tilts) and the discrepancy
    curves and surfaces over them."""

    def __init__(
        self,
        sims: DropSimulations,
        effects: list[str],
        conditions: list[str],
        grid_points: int,
    ):
        self.sims = sims
        self.conditions = conditions
        self.points = grid_points
        self.grids = {effect: self._coarse(effect, grid_points) for effect in effects}
        # Each grid with the strengths ``refine`` adds near the whole data's minimum: the
        # reported fit's (``fine=True``); the folds' fits keep the coarse grids.
        self.fine = {effect: list(grid) for effect, grid in self.grids.items()}
        self.joint = sims.x.settings.release_tilt == "fitted"
        self._fits: dict[tuple, np.ndarray] = {}
        lowest = min(sims.own_tilt(c, None) for c in conditions)
        below = min(TILT_STEP_DEG, lowest)
        # Release tilts cannot be negative: with a spec tilt of 0 the offsets go upwards.
        self.offsets = (
            (-below, 0.0, TILT_STEP_DEG) if below > 0 else (0.0, TILT_STEP_DEG, 2 * TILT_STEP_DEG)
        )

    def _coarse(self, effect: str, points: int) -> list[float]:
        # The neutral strength is always tried: an effect must be able to do nothing.
        e = EFFECTS.get(effect)
        lo, hi = e.prior
        values = set(np.round(np.linspace(lo, hi, points), 12).tolist())
        values.add(self.neutral(effect))
        return sorted(values)

    def neutral(self, effect: str) -> float:
        return round(EFFECTS.get(effect).neutral(self.sims.contact), 12)

    def refine(self, datasets: list[Dataset]) -> list[tuple]:
        """Add strengths near the minimum of each effect's coarse curve on ``datasets`` to
        its fine grid, and return the new settings (every condition) to simulate: when
        the curve dips below its value at the neutral strength, its smoothed minimum and
        strengths a third and two thirds of a coarse step either side of it and of the
        curve's lowest grid point (``refined_strengths``). With the release tilt fitted
        jointly nothing is added: that fit is the quadratic surface over three coarse
        strengths, which refined points would not move.

        Why: the discrepancy is not smooth in the strength everywhere. Measured (five
        effects cases, 2026-11-27): at 200 mm, air drag 0.8 scored 0.28 to 0.89 where
        0.4 and 1.2 scored about 0.02, in every case; compliant floor 1.8 scored 0.41 to
        1.32 where 1.6 scored -0.08 to 0.14 (a chip's landing changes regime). With the
        truth at compliant floor 1.67, one fold's curve was lowest at 1.6 alone (0.05,
        its neighbours 0.88 and 0.51) and the smoothing over seven grid points (1.2 of
        the prior's 2) fitted 0.48. Denser points near the minimum narrow the smoothing
        there (it takes the nearest seven), so a narrow valley is fitted on its own
        points, and a lone low point that was noise is outvoted by its new neighbours.

        Why only the whole data's fit (the reported strength and its interval): with the
        folds' fits refined too (13 study cases, 2026-11-27) the strengths came closer
        to the truth (95 % intervals holding it in 12 of 13 against 9), but a narrower
        smoothing on half the drops is a noisier fit, and the held-out ranking got worse
        (identified 5 of 13 against 7)."""
        if self.joint:
            return []
        new_keys = []
        for effect, grid in self.grids.items():
            curve = self.curve(datasets, None, effect)[:, 0]
            prior = EFFECTS.get(effect).prior
            added = refined_strengths(grid, curve, self.neutral(effect), prior, self.points)
            self.fine[effect] = sorted(grid + added)
            new_keys += [
                self.sims.grid_setting(c, None, effect, s) for s in added for c in self.conditions
            ]
        return new_keys

    def keys(self) -> list[tuple]:
        """The settings of every grid, at every condition."""
        keys = []
        for effect, grid in self.grids.items():
            keys += [
                self.sims.grid_setting(c, None, effect, s) for s in grid for c in self.conditions
            ]
        return keys

    def _along(self, datasets: list[Dataset], effect: str, fine: bool) -> np.ndarray:
        """``fit`` at the spec's tilt, once per datasets, effect and grid (the stencil's
        keys and the joint fit both start from it)."""
        grid = self.fine[effect] if fine else self.grids[effect]
        memo = (tuple(id(ds) for ds in datasets), effect, tuple(grid))
        if memo not in self._fits:
            self._fits[memo] = self.fit(datasets, None, effect, fine)
        return self._fits[memo]

    def stencil(self, effect: str, strength: float) -> list[float]:
        """The three grid strengths around ``strength``."""
        grid = self.grids[effect]
        k = int(np.argmin(np.abs(np.asarray(grid) - strength)))
        k = min(max(k, 1), len(grid) - 2)
        return grid[k - 1 : k + 2]

    def stencil_keys(self, datasets: list[Dataset], effect: str) -> list[tuple]:
        """The settings the joint fit on ``datasets`` needs beyond the grid: the three grid
        strengths around the strength fitted at the spec's tilt, at the shifted tilts
        (with the tilt fitted nothing is refined: the fine grid is the coarse one)."""
        if not self.joint:
            return []
        around = self.stencil(effect, float(self._along(datasets, effect, False)[0]))
        return [
            self.sims.grid_at_offset(c, o, effect, v)
            for v in around
            for o in self.offsets
            if o != 0
            for c in dict.fromkeys(ds.condition for ds in datasets)
        ]

    def joint_fit(self, datasets: list[Dataset], effect: str, fine: bool = False) -> JointFit:
        """Strength and release tilt offset fitted together on ``datasets``: the
        strength at the spec's tilt first (``fit``, on the fine grid with ``fine``), then
        the quadratic surface over the three coarse grid strengths around it and the
        three tilts (``quadratic_minimum``).
        A resample whose strength at the spec's tilt falls outside those three keeps it
        (and the spec's tilt): the surface says nothing there."""
        lo, hi = EFFECTS.get(effect).prior
        along = self._along(datasets, effect, fine)
        around = self.stencil(effect, float(along[0]))
        if not self.joint:
            return JointFit(along, np.zeros_like(along), around)
        surface = np.array(
            [
                [
                    sum(
                        self.sims.energy(ds, self.sims.grid_at_offset(ds.condition, o, effect, v))
                        for ds in datasets
                    )
                    for o in self.offsets
                ]
                for v in around
            ]
        )
        strength, offset = quadratic_minimum(around, list(self.offsets), surface)
        strength = snap(strength, STRENGTH_RESOLUTION * (hi - lo), around[0], around[-1])
        offset = snap(offset, TILT_RESOLUTION_DEG, self.offsets[0], self.offsets[-1])
        outside = (along < around[0]) | (along > around[-1])
        return JointFit(np.where(outside, along, strength), np.where(outside, 0.0, offset), around)

    def plausible(self, effect: str, fitted: JointFit) -> list[tuple[float, float]]:
        """The grid settings (strength, tilt offset) within the fit's 95 % confidence
        set: the grid at the spec's tilt, and with the tilt fitted the stencil at the
        shifted tilts, inside the rectangle of the two 97.5 % intervals (which covers
        both with at least 95 %)."""
        level = 0.975 if self.joint else 0.95
        s_lo, s_hi = interval(fitted.strength[1:], level)
        o_lo, o_hi = interval(fitted.offset[1:], level)
        points = [(v, 0.0) for v in self.grids[effect]]
        if self.joint:
            points += [(v, o) for v in fitted.stencil for o in self.offsets if o != 0]
        return [(v, o) for v, o in points if s_lo <= v <= s_hi and o_lo <= o <= o_hi]

    def curve(
        self, datasets: list[Dataset], tilt: float, effect: str, grid: list[float] | None = None
    ) -> np.ndarray:
        """Energy distance summed over ``datasets``, (strengths, 1 + B): the estimate,
        then per resample of both the observed and the simulated drops."""
        setting = self.sims.grid_setting
        return np.array(
            [
                sum(self.sims.energy(ds, setting(ds.condition, tilt, effect, s)) for ds in datasets)
                for s in (self.grids[effect] if grid is None else grid)
            ]
        )

    def discrepancy(self, datasets: list[Dataset], effect: str) -> np.ndarray:
        """The discrepancy left at the strength fitted on ``datasets`` over the fine grid
        (the smoothed curve's value at its minimum, ``smoothed_minimum_value``): the
        estimate, then one per resample of the observed and simulated drops (1 + B,),
        each refitted."""
        grid = self.fine[effect]
        return smoothed_minimum_value(grid, self.curve(datasets, None, effect, grid))

    def fit(
        self, datasets: list[Dataset], tilt: float | None, effect: str, fine: bool = False
    ) -> np.ndarray:
        """The strength fitted on ``datasets`` at release tilt ``tilt`` (None: each
        condition's own), on the coarse grid or with ``fine`` the refined one: the
        estimate, then one per resample of the observed and simulated drops (1 + B,)."""
        lo, hi = EFFECTS.get(effect).prior
        grid = self.fine[effect] if fine else self.grids[effect]
        curve = self.curve(datasets, tilt, effect, grid)
        return smoothed_minimum(grid, curve, STRENGTH_RESOLUTION * (hi - lo))
