"""What every effect is made of: the :class:`Effect` base class with its hooks, the
:class:`ContactModel` the contact effects change, the :class:`FlightState` the flight
loads read, and the base of the effects that set one contact coefficient."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from chipstack.core.chipshape import ChipShape
from chipstack.core.errors import InputError

__all__ = ["AIR_DENSITY_G_MM3", "ContactModel", "Effect", "FlightState", "ContactCoefficient"]

AIR_DENSITY_G_MM3 = 1.204e-6  # dry air at 20 C, 1 atm


@dataclass(frozen=True)
class ContactModel:
    """What the contact effects may change.

    friction and restitution: chip-chip and chip-floor coefficients; floor_compliance_mm_n:
    0 for a rigid floor, else the floor's contact compliance (mm/N) with damping ratio
    floor_damping_ratio against the chip's mass.
    """

    friction: float
    restitution: float
    floor_compliance_mm_n: float = 0.0
    floor_damping_ratio: float = 0.3


class Effect:
    """Base class: every hook does nothing. Subclasses set the class attributes."""

    name: str = ""
    parameter: str = ""  # what the strength is
    unit: str = ""
    prior: tuple[float, float] = (0.0, 1.0)
    kinds: tuple[str, ...] = ("drop", "stack", "container")
    justification: str = ""
    # How long a simulation with the effect takes against the baseline's (schedulers
    # submit the long calls first): drop pools of the study's table, 6 CPU s a pool
    # without an effect, 19.4 with air drag, 27.5 with warp (bench_table_cost.py).
    simulation_cost: float = 1.0

    def neutral(self, contact: ContactModel) -> float:
        """The strength at which the effect is absent (the baseline's own value)."""
        return 0.0

    def shape(self, shape: ChipShape, strength: float) -> ChipShape:
        return shape

    def contact(self, model: ContactModel, strength: float) -> ContactModel:
        return model

    def release(self, unit_draws: np.ndarray, strength: float) -> np.ndarray | None:
        """Extra angular velocity (n, 3) rad/s from standard normal draws (n, 3), or None."""
        return None

    def loads(self, state: FlightState, strength: float) -> tuple[np.ndarray, np.ndarray] | None:
        """Forces (k, 3) g mm/s^2 and torques (k, 3) g mm^2/s^2 on flying chips, or None."""
        return None

    def after_batch(self, world, chips: list[int], strength: float, rng) -> bool:
        """Act on a settled pile; True if chips were set moving (they must settle again)."""
        return False

    def contact_loads(self, world, chips: list[int], strength: float) -> None:
        """Loads between touching chips, applied every step while chips move."""

    def acts_per_step(self) -> bool:
        return False

    def check(self, strength: float, key: str) -> None:
        lo, hi = self.prior
        if not math.isfinite(strength):
            raise InputError(f"{key}: strength must be a finite number, got {strength!r}")
        span = hi - lo
        if not lo - 1e-9 * span <= strength <= hi + 1e-9 * span:
            value = f"{strength:g} {self.unit}".strip()  # a coefficient has no unit
            raise InputError(
                f"{key}: strength {value} is outside the prior range [{lo:g}, {hi:g}] of "
                f"effect {self.name!r} ({self.parameter})"
            )


@dataclass(frozen=True)
class FlightState:
    """Flying chips in the world frame: positions (k, 3) mm, quaternions (k, 4),
    velocities (k, 3) mm/s, angular velocities (k, 3) rad/s, and their shapes and
    masses (g)."""

    positions: np.ndarray
    quaternions: np.ndarray
    velocities: np.ndarray
    angular: np.ndarray
    shapes: tuple[ChipShape, ...]
    masses_g: np.ndarray


class ContactCoefficient(Effect):
    """An effect that sets one coefficient of the contact model (its baseline value is
    the neutral strength)."""

    field: str = ""

    def neutral(self, contact: ContactModel) -> float:
        return getattr(contact, self.field)

    def contact(self, model: ContactModel, strength: float) -> ContactModel:
        return dataclasses.replace(model, **{self.field: strength})
