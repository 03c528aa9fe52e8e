"""Physics presets: the contact model and material of the chips, registered by name.

All values are physical (mm, g, s). The conversion to the solver's internal world happens
in :mod:`packing.world` and nowhere else.

``default`` — physically scaled chips (see the README, "Physics presets", for sources):
  * density 1.70 g/cm3: PA6 (1.14 g/cm3) with 60 wt % E-glass (2.54 g/cm3) by the rule of
    mixtures on volume, 1 / (0.6 / 2.54 + 0.4 / 1.14) = 1.70; a 20 x 20 x 2 mm chip is 1.36 g.
  * rolling resistance with a 1 um lever arm (a coefficient of 0.001 for a 1 mm radius
    rod, the order of hard plastics and glass on hard surfaces), on round chips (and the
    floor and walls) only: they would otherwise roll for ever; a flat chip cannot roll.
  * rigid (non-penetrating) contacts, Coulomb friction 0.5 (smooth nylon 6 is about 0.3 in
    handbooks; the twill texture and sheared, glass-rich edges of a chip put it higher)
    and restitution 0.3 (an estimate for a thin stiff plate; no measurement found). Both
    are uncertain to about +-0.15; the README gives the sources.

``paper`` — Table 1 of the packing paper, read in the world the paper built: chip
dimensions in millimetres with PyBullet's default gravity of 9.81 (so the paper's clock ran
sqrt(1000) ~ 31.6 times slow). That reading is the only one under which Table 1 is
physically sensible: a contact stiffness of 1000 with mass 1 gives a static deflection
m g / k of 0.01 mm (0.5 % of the thickness); read in SI units it would be 9.8 mm, five
chip thicknesses, and chips would sink through one another. We keep the dimensionless
groups of that world (deflection over thickness, damping ratio 0.032, friction,
restitution) and run on the physical clock: stiffness 1000 x 1000 = 1e6 and damping
2 x sqrt(1000) = 63.2 per unit mass per second.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from chipstack.core.registry import Registry

__all__ = ["PhysicsPreset", "PRESETS"]


@dataclass(frozen=True)
class PhysicsPreset:
    """Contact and material parameters in physical units (mm, g, s)."""

    name: str
    friction: float
    restitution: float
    # Rolling resistance as the lever arm of the normal force (mm): the torque resisting
    # rolling is this times the normal force (a rolling-resistance coefficient times the
    # radius). Without it a round rod on a flat floor gains energy in Bullet and never
    # comes to rest.
    rolling_resistance_mm: float = 0.0
    spinning_friction: float = 0.0
    density_g_mm3: float | None = 1.70e-3  # mass from volume when set
    mass_g: float | None = None  # fixed mass per chip when set
    contact_stiffness_per_g: float | None = None  # k / m, 1/s^2; None: rigid contacts
    contact_damping_per_g: float | None = None  # c / m, 1/s
    contact_processing_threshold_mm: float | None = None
    description: str = ""

    def chip_mass_g(self, volume_mm3: float) -> float:
        if self.mass_g is not None:
            return self.mass_g
        assert self.density_g_mm3 is not None  # the dataclass invariant, not user input
        return self.density_g_mm3 * volume_mm3


PRESETS: Registry = Registry("physics preset", "chipstack.presets")

PRESETS.register(
    "default",
    PhysicsPreset(
        name="default",
        friction=0.5,
        restitution=0.3,
        rolling_resistance_mm=1e-3,
        density_g_mm3=1.70e-3,
        description="physically scaled PA6/60 wt% glass chips, rigid contacts",
    ),
)

_PAPER_TIME_DILATION = math.sqrt(9810.0 / 9.81)  # the paper's world ran this much slow

PRESETS.register(
    "paper",
    PhysicsPreset(
        name="paper",
        friction=1.0,
        restitution=1.0,
        rolling_resistance_mm=0.0,
        spinning_friction=0.0,
        density_g_mm3=None,
        mass_g=1.0,
        contact_stiffness_per_g=1000.0 * _PAPER_TIME_DILATION**2,
        contact_damping_per_g=2.0 * _PAPER_TIME_DILATION,
        contact_processing_threshold_mm=1e-4,
        description="Table 1 of the paper (mm world, default gravity; see module docstring)",
    ),
)
