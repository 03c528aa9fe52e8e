"""Deposition sites, one per scenario kind that deposits chips: where the chips are
released, what holds them besides the floor, what counts as outside, and when a pour is
over (a square target for ``stack``, a cylinder for ``container``, a pour zone over a
belt for ``conveyor``; a ``drop`` has the bare floor).

The deposition asks the scenario's site (``scenario.chosen.site``) and never tests
the kind's name; a package adds one through the ``chipstack.sites`` entry points, beside
its scenario kind (:mod:`packing.kinds`).
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from chipstack.core.errors import InputError
from chipstack.core.schema import Scenario
from chipstack.packing.site_kinds import SITES

__all__ = ["SITES", "Site", "SquareTarget", "Cylinder", "PourZone", "reaches_rim"]

SPILL_MARGIN_MM = 5.0  # beyond the wall's outer face: spilled out of a container


class Site:
    """The bare floor, nothing else holding the chips (a drop's site).

    Subclasses that deposit batches say where chips are released (``release_point``,
    ``no_room``), and may add walls, act on moving chips and end a pour early."""

    pours_per_world: ClassVar[int] = 1  # batches one physics world runs before a rebuild
    records_every_batch: ClassVar[bool] = True  # else only the last batch is recorded

    def extent_mm(self, scenario: Scenario) -> float:
        """The size of what the site adds to the scene (mm; a chip twenty times the
        scenario's size from the origin has left it)."""
        return 0.0

    def after_check(self, world, tracker, scenario: Scenario) -> None:
        """Act on the moving chips after each rest check of a settling."""

    def build(self, world, scenario: Scenario) -> None:
        """Add what holds the chips besides the floor."""

    def is_full(self, scenario: Scenario, positions: np.ndarray) -> bool:
        """Whether the pour is over before its last batch."""
        return False

    def unfinished(self, scenario: Scenario, full: bool, chips: int) -> str | None:
        """A warning when the pour ended short of what the site needs, else None."""
        return None

    def release_point(
        self, scenario: Scenario, clearance_mm: float, rng: np.random.Generator, zone_x_mm: float
    ) -> np.ndarray:
        """A chip centre's release point (mm), at least ``clearance_mm`` above the floor."""
        raise NotImplementedError(f"{type(self).__name__} releases no batches")

    def no_room(self, scenario: Scenario, n: int) -> InputError:
        """The error when ``n`` chips cannot be released without overlap."""
        raise NotImplementedError(f"{type(self).__name__} releases no batches")

    def outside(self, scenario: Scenario, positions: np.ndarray) -> np.ndarray:
        """Which chip centres (n, 3) lie outside the target."""
        return (np.abs(positions[:, :2]) > scenario.deposition.target_size_mm / 2).any(axis=1)

    def footprint_mm(self, scenario: Scenario) -> float:
        """The side of the square the stack is described over (mm)."""
        return scenario.deposition.target_size_mm


class DropSite(Site):
    """The bare floor a single chip is dropped on from ``[drop]``'s height."""

    def extent_mm(self, scenario: Scenario) -> float:
        return scenario.drop.height_mm


class SquareTarget(Site):
    """Batches released over a square above the target (``[deposition]``)."""

    def release_point(
        self, scenario: Scenario, clearance_mm: float, rng: np.random.Generator, zone_x_mm: float
    ) -> np.ndarray:
        """A chip centre's release point (mm), at least ``clearance_mm`` above the floor."""
        d = scenario.deposition
        half = d.release_side_mm / 2
        height = max(rng.uniform(*d.release_height_mm), clearance_mm)
        return np.array([*rng.uniform(-half, half, 2), height])

    def no_room(self, scenario: Scenario, n: int) -> InputError:
        """The error when ``n`` chips cannot be released without overlap."""
        d = scenario.deposition
        return InputError(
            f"deposition: cannot release {n} chips without overlap (in a "
            f"{d.release_side_mm:g} mm square between {d.release_height_mm[0]:g} and "
            f"{d.release_height_mm[1]:g} mm; widen release_height_mm or lower batch_size)"
        )


def reaches_rim(positions: np.ndarray, radius_mm: float, height_mm: float) -> bool:
    """Whether a container is full: a chip's centre of mass lies inside the wall's
    footprint at or above the rim."""
    positions = np.asarray(positions, dtype=float).reshape(-1, 3)
    inside = np.hypot(positions[:, 0], positions[:, 1]) <= radius_mm
    return bool((positions[inside, 2] >= height_mm).any())


class Cylinder(Site):
    """A cylindrical container (``[container]``) filled until a settled chip's centre of
    mass is inside the wall's footprint at or above the rim."""

    # A container is filled a few rods at a time, in hundreds of pours: rebuilding the
    # world from the saved state before every pour would cost time in proportion to the
    # rods already in (a fill's cost growing as its square), so one world serves this many
    # pours and the state a resumed run starts from is saved after them (a stack's batches
    # are few and large: each gets its own world). Only the final state of a fill is
    # recorded.
    pours_per_world = 25
    records_every_batch = False

    def extent_mm(self, scenario: Scenario) -> float:
        return max(scenario.container.height_mm, scenario.container.radius_mm)

    def release_point(
        self, scenario: Scenario, clearance_mm: float, rng: np.random.Generator, zone_x_mm: float
    ) -> np.ndarray:
        c = scenario.container
        radius = c.release_radius * c.radius_mm * np.sqrt(rng.uniform())
        angle = rng.uniform(0, 2 * np.pi)
        height = c.height_mm + clearance_mm + rng.uniform(*c.release_gap_mm)
        return np.array([radius * np.cos(angle), radius * np.sin(angle), height])

    def no_room(self, scenario: Scenario, n: int) -> InputError:
        return InputError(
            f"deposition: cannot release {n} chips without overlap (over the container; "
            "lower deposition.batch_size or widen container.release_gap_mm)"
        )

    def build(self, world, scenario: Scenario) -> None:
        c = scenario.container
        world.add_container_wall(c.radius_mm, c.height_mm, c.wall_segments)

    def after_check(self, world, tracker, scenario: Scenario) -> None:
        # Chips that fell outside the wall, below its rim, cannot get back in and take no
        # further part: frozen where they are (on a bare floor a spilled rod would roll on
        # for many seconds). Where the tracker read them this check (chips it has just
        # woken were at rest).
        c = scenario.container
        chips = [chip for chip in sorted(tracker.awake) if chip in tracker.positions]
        if not chips:
            return
        positions = np.array([tracker.positions[chip] for chip in chips])
        outside = np.hypot(positions[:, 0], positions[:, 1]) > c.radius_mm + SPILL_MARGIN_MM
        for chip in np.asarray(chips)[outside & (positions[:, 2] < c.height_mm)]:
            tracker.remove(int(chip))

    def outside(self, scenario: Scenario, positions: np.ndarray) -> np.ndarray:
        return np.hypot(positions[:, 0], positions[:, 1]) > scenario.container.radius_mm

    def footprint_mm(self, scenario: Scenario) -> float:
        return 2 * scenario.container.radius_mm

    def is_full(self, scenario: Scenario, positions: np.ndarray) -> bool:
        c = scenario.container
        return reaches_rim(positions, c.radius_mm, c.height_mm)

    def unfinished(self, scenario: Scenario, full: bool, chips: int) -> str | None:
        if full:
            return None
        return (
            f"the container is not full after {chips} chips (deposition.chips); raise "
            "deposition.chips"
        )


class PourZone(SquareTarget):
    """A pour zone over a moving belt (``[conveyor]``), released at the zone's current
    position along the belt; the panel cut from the mat is the square target."""

    def release_point(
        self, scenario: Scenario, clearance_mm: float, rng: np.random.Generator, zone_x_mm: float
    ) -> np.ndarray:
        d, c = scenario.deposition, scenario.conveyor
        half_width = c.zone_width_mm / 2
        if c.side_guides:  # a chip released into a guide is shot out across the belt
            half_width = min(half_width, c.belt_width_mm / 2 - clearance_mm)
        return np.array(
            [
                zone_x_mm + rng.uniform(-c.zone_length_mm / 2, c.zone_length_mm / 2),
                rng.uniform(-half_width, half_width),
                max(rng.uniform(*d.release_height_mm), clearance_mm),
            ]
        )

    def no_room(self, scenario: Scenario, n: int) -> InputError:
        d, c = scenario.deposition, scenario.conveyor
        return InputError(
            f"deposition.batch_size: cannot release {n} chips without overlap over the pour "
            f"zone ({c.zone_length_mm:g} x {c.zone_width_mm:g} mm, "
            f"{d.release_height_mm[0]:g}-{d.release_height_mm[1]:g} mm high); lower "
            "batch_size or widen the zone or the release heights"
        )


# The sites' objects; packing/site_kinds.py registers them by scenario kind.
SQUARE_TARGET = SquareTarget()
DROP_SITE = DropSite()
CYLINDER = Cylinder()
POUR_ZONE = PourZone()
