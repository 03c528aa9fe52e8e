"""The packing stage's scenario tables: deposition, physics, settling and output, and the
tables of the kinds it alone runs (drop, container, conveyor; each listed by its kind in
:mod:`packing.kinds`).

Each is a frozen :class:`~core.schema.Section` declared with :func:`~core.schema.key`
(type, unit, default, one-line description and check), so that the validator, the key
table of docs/scenarios.md and the resolved scenario come from these declarations; the
stage lists them in ``PackingStage.owned_sections`` and the core assembles the scenario
from what the stages own.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from chipstack.core.errors import InputError, brief
from chipstack.core.keys import (
    MAX_LENGTH_MM,
    between,
    duration,
    key,
    length,
    non_negative,
    one_of,
    positive,
    value_range,
)
from chipstack.core.schema import Section

__all__ = [
    "DepositionSpec",
    "PhysicsSpec",
    "SettlingSpec",
    "OutputSpec",
    "DropSpec",
    "ContainerSpec",
    "ConveyorSpec",
    "SECTIONS",
]


@dataclass(frozen=True)
class DepositionSpec(Section):
    """Batch deposition onto a square target centred on (0, 0), z up."""

    table: ClassVar[str] = "deposition"

    chips: int = key(270, "", "number of chips in the stack", positive)
    batch_size: int = key(54, "", "chips released together; next batch once settled", positive)
    target_size_mm: float = key(
        150.0,
        "mm",
        "side of the square deposition target (conveyor: of the panel cut from the mat)",
        length,
    )
    release_area_mm: float = key(
        0.0,
        "mm",
        "side of the square over which centres are drawn (0: the target)",
        between(0.0, MAX_LENGTH_MM),
    )
    release_height_mm: tuple[float, float] = key(
        (100.0, 200.0),
        "mm",
        "range of the chip centre's height above the target",
        value_range(0.0, MAX_LENGTH_MM),
    )
    orientation: str = key(
        "uniform",
        "",
        "`uniform`: uniform random rotation; `ranges`: Euler angles drawn from the ranges below",
        one_of("uniform", "ranges"),
    )
    roll_range_deg: tuple[float, float] = key(
        (-180.0, 180.0), "deg", "rotation about x (with `ranges`)", value_range(-360.0, 360.0)
    )
    pitch_range_deg: tuple[float, float] = key(
        (-180.0, 180.0), "deg", "rotation about y (with `ranges`)", value_range(-360.0, 360.0)
    )
    yaw_range_deg: tuple[float, float] = key(
        (-180.0, 180.0), "deg", "rotation about z (with `ranges`)", value_range(-360.0, 360.0)
    )

    @property
    def release_side_mm(self) -> float:
        return self.release_area_mm or self.target_size_mm

    def check(self) -> None:
        if self.batch_size > self.chips:
            raise InputError(
                f"deposition.batch_size: {self.batch_size} is larger than deposition.chips "
                f"({self.chips})"
            )
        if self.chips > 200_000:
            raise InputError(
                f"deposition.chips: {self.chips} is beyond what one run can hold (200000)"
            )


@dataclass(frozen=True)
class PhysicsSpec(Section):
    """Contact model preset and the numerics of the rigid-body solver."""

    table: ClassVar[str] = "physics"

    preset: str = key("default", "", "physics preset: `default` or `paper`")
    friction: float = key(-1.0, "", "override the preset's friction coefficient (-1: keep)")
    restitution: float = key(-1.0, "", "override the preset's restitution (-1: keep)")
    time_step_s: float = key(5e-4, "s", "integration step", between(1e-5, 5e-3))
    solver_iterations: int = key(10, "", "constraint-solver iterations per step", between(1, 500))

    def check(self) -> None:
        for name in ("friction", "restitution"):
            value = getattr(self, name)
            if value != -1.0 and not 0 <= value <= 10:
                raise InputError(
                    f"physics.{name}: must be between 0 and 10 (or -1 to keep the "
                    f"preset's), got {brief(value)}"
                )


@dataclass(frozen=True)
class SettlingSpec(Section):
    """When a chip, and a batch, count as settled (see README: Settling)."""

    table: ClassVar[str] = "settling"

    speed_mm_s: float = key(
        5.0,
        "mm/s",
        "a chip is at rest while every point of it moves slower than this, "
        "on average over the hold time",
        positive,
    )
    hold_time_s: float = key(0.05, "s", "how long a chip must stay at rest to settle", duration)
    wake_speed_mm_s: float = key(
        20.0,
        "mm/s",
        "a chip this fast wakes the settled chips it can reach before the next check",
        positive,
    )
    max_time_s: float = key(
        10.0, "s", "simulated-time cap per batch; hitting it is a warning", duration
    )
    buried_depth: float = key(
        2.0,
        "chip lengths",
        "a settled chip whose top lies this far below the pile's surface over it is buried: "
        "never woken, static support only (1e6: every chip stays wakeable)",
        between(0.5, 1e6),
    )
    freeze: bool = key(
        True,
        "",
        "freeze chips at rest (false: every chip stays dynamic and a pour ends when all "
        "are at rest; the reference that freezing is checked against, its cost grows with "
        "the pile)",
    )

    def check(self) -> None:
        if self.hold_time_s >= self.max_time_s:
            raise InputError("settling.hold_time_s: must be shorter than settling.max_time_s")


@dataclass(frozen=True)
class OutputSpec(Section):
    """What is recorded in the run directory."""

    table: ClassVar[str] = "output"

    contact_distance_mm: float = key(
        0.05, "mm", "surfaces closer than this are recorded as a contact", non_negative
    )


@dataclass(frozen=True)
class DropSpec(Section):
    """The single-chip drop experiment (kind `drop`; paper section 4.2)."""

    table: ClassVar[str] = "drop"
    kinds: ClassVar[tuple[str, ...]] = ("drop",)

    drops: int = key(50, "", "independent drops, each onto an empty target", between(1, 100000))
    height_mm: float = key(
        200.0, "mm", "height of the chip's centre above the target at release", length
    )
    tilt_deg: float = key(
        5.7296,
        "deg",
        "tilts about x and about y are drawn uniform in [-tilt, tilt] (paper: 0.1 rad)",
        between(0.0, 90.0),
    )
    yaw_deg: float = key(
        0.0, "deg", "rotation about z at release (0: sides along x and y)", between(-360, 360)
    )


@dataclass(frozen=True)
class ContainerSpec(Section):
    """Filling a cylindrical container (kind `container`; paper section 5)."""

    table: ClassVar[str] = "container"
    kinds: ClassVar[tuple[str, ...]] = ("container",)

    radius_mm: float = key(25.0, "mm", "inner radius of the cylinder", length)
    height_mm: float = key(100.0, "mm", "height of the cylinder wall", length)
    wall_segments: int = key(64, "", "flat panels approximating the round wall", between(12, 1024))
    release_radius: float = key(
        0.5,
        "",
        "chip centres are released over a disc of this fraction of the radius",
        between(0.0, 1.0),
    )
    release_gap_mm: tuple[float, float] = key(
        (5.0, 30.0),
        "mm",
        "range of the clearance between the rim and a released chip's lowest possible point",
        value_range(0.0, MAX_LENGTH_MM),
    )


@dataclass(frozen=True)
class ConveyorSpec(Section):
    """A belt carrying the mat along +x, fed continuously (kind `conveyor`; see
    docs/conveyor.md). Chips are released `deposition.batch_size` at a time, at
    `deposition.release_height_mm` and `deposition.orientation`; the square panel of side
    `deposition.target_size_mm` cut from the middle of the mat is the stack that later
    stages take."""

    table: ClassVar[str] = "conveyor"
    kinds: ClassVar[tuple[str, ...]] = ("conveyor",)

    belt_speed_mm_s: float = key(
        20.0,
        "mm/s",
        "speed of the belt along +x (0: the chips pile up under the pour zone)",
        between(0.0, 1e5),
    )
    pour_rate_chips_s: float = key(36.0, "chips/s", "chips released per second", between(1e-6, 1e6))
    zone_length_mm: float = key(
        40.0,
        "mm",
        "length along the belt of the pour zone (a falling curtain's thickness)",
        length,
    )
    zone_width_mm: float = key(
        150.0, "mm", "width across the belt of the pour zone, centred on the belt", length
    )
    zones: int = key(
        1,
        "",
        "pour zones (feeders) in a row along the line, `zone_spacing_mm` apart; the belt "
        "passes under zone 0 first, and the pours take turns",
        between(1, 100),
    )
    zone_spacing_mm: float = key(
        100.0, "mm", "distance between the centres of neighbouring pour zones", length
    )
    belt_width_mm: float = key(
        200.0,
        "mm",
        "width of the belt; without side guides, a chip whose centre goes past an edge has "
        "fallen off (spilled)",
        length,
    )
    side_guides: bool = key(
        True,
        "",
        "walls along both edges of the belt, frictionless (a guide fixed in the line slides "
        "along the moving mat; that friction is not modelled); false: chips can fall off",
    )
    feed_speed_mm_s: float = key(
        0.0,
        "mm/s",
        "horizontal speed along +x of a released chip, in the line's frame (an inclined "
        "feeding belt's end; 0: a falling curtain)",
        between(-1e5, 1e5),
    )
    active_lengths: float = key(
        5.0,
        "chip lengths",
        "settled chips this far downstream of the pour zone, with no moving chip near, "
        "leave the physics world (their poses are recorded): the cost per chip stays flat",
        between(1.0, 1e6),
    )
    run_in_mm: float = key(
        200.0,
        "mm",
        "the first this many mm of mat are left out of its steady part: the heap under the "
        "pour zone is still forming there (the built-in line's thickness reaches its "
        "plateau after about 200 mm; docs/conveyor.md)",
        between(0.0, MAX_LENGTH_MM),
    )
    cell_mm: float = key(
        50.0,
        "mm",
        "side of the square cells of the areal-weight map (its coefficient of variation is "
        "taken over the cells of the mat's steady part)",
        length,
    )


# The tables of every kind; a kind's own table is declared by its scenario kind
# (packing.kinds: drop, container, conveyor).
SECTIONS = (DepositionSpec, PhysicsSpec, SettlingSpec, OutputSpec)
