"""The diagnosis's data model: a parsed experiment, its conditions and settings, and the
observations by condition. Everything of the diagnosis imports it; it imports no part of
the diagnosis."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from chipstack.core.schema import Scenario
from chipstack.packing.drop import DropProtocol
from chipstack.packing.effects import EFFECTS

__all__ = ["Condition", "DiagnosisSettings", "DropData", "Experiment", "QuantityData"]


@dataclass(frozen=True)
class Condition:
    """One experimental condition: a drop protocol (drops) or a scenario (stacks,
    containers) with the number of simulated repeats per setting."""

    name: str
    protocol: DropProtocol | None = None
    scenario: Scenario | None = None
    repeats: int = 2


@dataclass(frozen=True)
class DiagnosisSettings:
    """How hard the diagnosis works (the ``[diagnosis]`` table)."""

    sim_drops: int = 120  # simulated drops per condition and setting
    bootstrap: int = 200  # resamples of the observations for intervals
    grid_points: int = 11  # strengths tried across each effect's prior range
    # What each fitted model is judged on (drop experiments): "halves" of every
    # condition's drops, or whole "conditions" left out one at a time.
    held_out: str = "halves"
    # Drop experiments: the release tilt range "known" (the conditions' tilt_deg; effects
    # are fitted at it, and the refitted baseline is a candidate of its own), or
    # "fitted" jointly with every effect's strength (for a release nobody measured).
    release_tilt: str = "known"
    effects: tuple[str, ...] = ()  # candidates; () = every effect for this kind
    alpha: float = 0.05
    # Drop experiments: "which" by the amortised model choice ("amortised", the default:
    # a classifier trained on a reference table of simulated datasets of the design) or
    # by refitting every effect to the data ("refit", the earlier method, kept as a
    # cross-check). ``table_pools``: the most pools per effect the reference table grows to.
    method: str = "amortised"
    table_pools: int = 24
    # Drop experiments, amortised method: how a gap is detected. "combined" (the default):
    # the exact max-T test and the model choice's learned test (the posterior probability
    # of "no effect" against effect-free simulated datasets of the design) joined by
    # Simes's rule, so an effect the hand-made observables miss is found when the learned
    # summary sees it; it needs the design's reference table even when there is no gap.
    # "exact": the max-T test alone (no table unless a gap is found).
    detection: str = "combined"


@dataclass(frozen=True)
class Experiment:
    """A parsed spec: ``scenario`` carries the chip, physics and settling rules."""

    name: str
    kind: str
    scenario: Scenario
    conditions: tuple[Condition, ...]
    observations: Path
    position_sd_mm: float = 0.0
    angle_sd_deg: float = 0.0
    settings: DiagnosisSettings = DiagnosisSettings()

    def condition(self, name: str) -> Condition:
        return next(c for c in self.conditions if c.name == name)

    @property
    def candidate_effects(self) -> tuple[str, ...]:
        return self.settings.effects or tuple(
            n for n in EFFECTS.names() if self.kind in EFFECTS.get(n).kinds
        )


@dataclass(frozen=True)
class DropData:
    """Measured drops of one condition: positions (n, 2) mm, optional yaw and tilt
    (n,) deg."""

    positions: np.ndarray
    yaw_deg: np.ndarray | None = None
    tilt_deg: np.ndarray | None = None

    @property
    def n(self) -> int:
        return len(self.positions)

    def take(self, index: np.ndarray) -> DropData:
        return DropData(
            self.positions[index],
            None if self.yaw_deg is None else self.yaw_deg[index],
            None if self.tilt_deg is None else self.tilt_deg[index],
        )


@dataclass(frozen=True)
class QuantityData:
    """A measured quantity of one condition: value, its sd (nan if not given) and the
    number of measurements behind it (1 if not given)."""

    value: float
    sd: float = math.nan
    n: int = 1
