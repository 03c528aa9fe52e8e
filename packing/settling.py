"""Settling: when a chip is at rest (it strays less than a speed times the hold time
over the hold time) and is frozen, and which frozen chips a mover wakes (within reach
before the next speed check; never those buried deep under the pile's surface)."""

from __future__ import annotations

import logging
from collections.abc import Callable

import numpy as np

from chipstack.core.errors import SimulationError
from chipstack.core.schema import Scenario
from chipstack.packing.world import GRAVITY_MM_S2, ChipWorld

__all__ = [
    "RestTracker",
    "settle",
    "wake_near_movers",
    "buried_under",
    "domain_mm",
    "CHECK_INTERVAL_S",
]

log = logging.getLogger(__name__)

WAKE_MARGIN_MM = 0.5
CHECK_INTERVAL_S = 0.005  # how often speeds are read (simulated time)
ENERGY_BLOWUP_FACTOR = 10.0  # kinetic energy over what the moving chips brought
FELL_THROUGH_MM = 5.0  # a chip centre this far below the floor has tunnelled through it


def domain_mm(scenario: Scenario) -> float:
    """Twenty times the scenario's own size: a chip beyond has left the experiment."""
    d = scenario.deposition
    size = max(d.target_size_mm, max(d.release_height_mm))
    size = max(size, scenario.chosen.site.extent_mm(scenario))
    return 20.0 * size


class RestTracker:
    """Which chips are still moving, and freezing the ones that have come to rest.

    A chip is at rest when no point of it strays more than ``stray_mm`` (speed threshold x
    hold time) from where it was at the start of a window of ``hold_checks`` checks: its
    speed, averaged over the hold time, stays below the threshold. Averaging, rather than
    requiring every instantaneous reading to be low, lets a chip that trembles in place
    on the solver's contact noise settle, while a chip creeping away never does.
    """

    def __init__(
        self,
        world: ChipWorld,
        stray_mm: float,
        hold_checks: int,
        domain_mm: float = np.inf,
        freezes: bool = True,
    ) -> None:
        self.world, self.stray_mm, self.hold_checks = world, stray_mm, hold_checks
        # Without freezing, a chip at rest stays dynamic and tracked (its count stays at
        # or above hold_checks until it strays again, its window renewed every hold time).
        self.freezes = freezes
        self.awake: dict[int, int] = {}  # chip -> checks spent inside its window
        self.positions: dict[int, np.ndarray] = {}  # where update() last saw each chip
        self._anchor: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        # Physics sanity: the kinetic energy of the moving chips can never exceed what
        # they brought (their kinetic and potential energy above the floor when added);
        # chips farther than domain_mm from the origin, or below the floor, have left it.
        self.domain_mm = domain_mm
        self.energy_budget = 0.0
        self.left_domain: list[int] = []

    def add(self, chips: list[int]) -> None:
        if not chips:
            return
        positions, quaternions, _ = self.world.states(chips)
        masses = np.array([self.world.mass_g(c) for c in chips])
        self.energy_budget += float(
            self.world.last_kinetic_energy.sum()
            + (masses * GRAVITY_MM_S2 * np.maximum(positions[:, 2], 0.0)).sum()
        )
        for k, chip in enumerate(chips):
            self.awake[chip] = 0
            self._anchor[chip] = (positions[k], quaternions[k])

    def _check_physics(self, chips: list[int], positions: np.ndarray) -> None:
        energy = self.world.last_kinetic_energy
        if energy.sum() > ENERGY_BLOWUP_FACTOR * self.energy_budget + 1e3:
            worst = [chips[k] for k in np.argsort(energy)[::-1][:5]]
            raise SimulationError(
                f"kinetic energy grew to {energy.sum() * 1e-9:.3g} J, "
                f"{energy.sum() / max(self.energy_budget, 1e-12):.3g} times what the moving "
                f"chips brought, at t = {self.world.time_s:.3f} s (the solver blew up; most "
                f"energetic chips {worst}); try a smaller physics.time_step_s"
            )
        gone = (np.linalg.norm(positions, axis=1) > self.domain_mm) | (
            positions[:, 2] < -FELL_THROUGH_MM
        )
        for k in np.flatnonzero(gone):
            self.left_domain.append(chips[k])
            self.remove(chips[k])

    def update(self, wake_speed_mm_s: float) -> list[tuple[int, float]]:
        """Read every awake chip and freeze the settled ones.

        Returns (chip, speed mm/s) of the chips that moved since the last check: faster
        than ``wake_speed_mm_s``, or strayed out of their rest window.
        """
        chips = sorted(self.awake)
        positions, quaternions, speed = self.world.states(chips)
        self._check_physics(chips, positions)
        if self.left_domain:
            kept = np.array([c in self.awake for c in chips], dtype=bool)
            chips = [c for c, keep in zip(chips, kept, strict=True) if keep]
            positions, quaternions, speed = positions[kept], quaternions[kept], speed[kept]
        self.positions = dict(zip(chips, positions, strict=True))  # read once per check
        if not chips:
            return []
        anchor_pos = np.array([self._anchor[c][0] for c in chips])
        anchor_quat = np.array([self._anchor[c][1] for c in chips])
        cos_half = np.clip(np.abs(np.einsum("ij,ij->i", quaternions, anchor_quat)), 0.0, 1.0)
        turned = 2.0 * np.arccos(cos_half)
        stray = np.linalg.norm(positions - anchor_pos, axis=1)
        stray += turned * self.world.circumradius_mm(chips)
        moving = []
        for k, chip in enumerate(chips):
            if speed[k] > wake_speed_mm_s or stray[k] > self.stray_mm:
                moving.append((chip, float(speed[k])))
            if stray[k] > self.stray_mm:
                self.awake[chip] = 0
                self._anchor[chip] = (positions[k], quaternions[k])
                continue
            self.awake[chip] += 1
            if self.awake[chip] < self.hold_checks:
                continue
            if self.freezes:
                self.world.freeze(chip)
                del self.awake[chip], self._anchor[chip]
            elif self.awake[chip] >= 2 * self.hold_checks:
                # Still at rest, judged from here over the next hold time: a dynamic chip
                # creeping slower than the rest speed must not be counted as moving only
                # because its drift since a long-ago anchor has added up.
                self.awake[chip] = self.hold_checks
                self._anchor[chip] = (positions[k], quaternions[k])
        return moving

    def moving(self) -> bool:
        """Whether some tracked chip has not been at rest for the hold time."""
        if self.freezes:  # a chip at rest is frozen and untracked at once
            return bool(self.awake)
        return any(count < self.hold_checks for count in self.awake.values())

    def remove(self, chip: int) -> None:
        """Freeze a chip now, whatever its speed."""
        self.world.freeze(chip)
        del self.awake[chip], self._anchor[chip]


def settle(
    world: ChipWorld,
    new: list[int],
    scenario: Scenario,
    loads: Callable[[list[int]], None] | None = None,
    warnings: list[str] | None = None,
) -> tuple[bool, int, int, float]:
    """Step until the chips in ``new`` (and those they wake) have settled or time runs out.

    ``loads(awake chips)``, if given, applies extra loads before every step (effects such
    as cohesion). Returns (settled, steps, wakes, simulated start time). Chips still
    moving at the cap are frozen where they are.
    """
    s = scenario.settling
    site = scenario.chosen.site
    check_steps = max(1, round(CHECK_INTERVAL_S / scenario.physics.time_step_s))
    check_interval_s = check_steps * scenario.physics.time_step_s
    hold_checks = max(1, int(np.ceil(s.hold_time_s / check_interval_s)))
    tracker = RestTracker(
        world, s.speed_mm_s * s.hold_time_s, hold_checks, domain_mm(scenario), s.freeze
    )
    # Without freezing every chip is dynamic, so every chip is watched until all rest.
    tracker.add(new if s.freeze else list(range(world.n_chips)))
    buried = _buried(world, new, s.buried_depth) if s.freeze else set()
    start_time, steps, wakes = world.time_s, 0, 0
    while tracker.moving() and world.time_s - start_time < s.max_time_s:
        if loads is None:
            world.step(check_steps)
        else:
            awake = sorted(tracker.awake)
            for _ in range(check_steps):
                loads(awake)
                world.step()
        steps += check_steps
        wakes += wake_near_movers(
            world, tracker, tracker.update(s.wake_speed_mm_s), buried, s, check_interval_s
        )
        site.after_check(world, tracker, scenario)
    still_moving = tracker.moving()
    if still_moving and s.freeze:
        for chip in sorted(tracker.awake):
            world.freeze(chip)
    if tracker.left_domain:
        message = (
            f"chips {sorted(tracker.left_domain)[:20]} left the domain (farther than "
            f"{tracker.domain_mm:g} mm from the target centre, or through the floor) and were "
            "frozen where they were"
        )
        log.warning(message)
        if warnings is not None:
            warnings.append(message)
    return not still_moving, steps, wakes, start_time


def wake_near_movers(
    world: ChipWorld,
    tracker: RestTracker,
    moving: list[tuple[int, float]],
    buried: set[int],
    settling,
    check_interval_s: float,
) -> int:
    """Wake the frozen chips the ``moving`` chips (chip, speed mm/s) can reach before the
    next check; returns how many were woken."""
    wakes = 0
    for chip, speed in moving:
        # A fast chip wakes every frozen chip it can reach before the next check, so an
        # impact pushes what it hits instead of bouncing off a static chip. A slow one
        # that crept out of its rest window wakes those above its centre only: a chip
        # resting on one that slides away must not stay hanging in the air, but the chips
        # under a creeping one hold it up as well static as moving (waking them too made
        # every pour into a container wake its whole top layer, over and over: 1.5 times
        # the cost of a fill).
        reach = WAKE_MARGIN_MM + speed * check_interval_s
        near = [
            c for c in world.chips_near(chip, reach) if c not in tracker.awake and c not in buried
        ]
        woken = world.within(chip, near, reach)
        if woken and speed <= settling.wake_speed_mm_s:
            heights = world.kinematics(woken)[0][:, 2]  # no energy bookkeeping
            floor = tracker.positions[chip][2]
            woken = [c for c, z in zip(woken, heights, strict=True) if z > floor]
        for other in woken:
            world.wake(other)
        tracker.add(woken)
        wakes += len(woken)
    return wakes


def _buried(world: ChipWorld, new: list[int], depth_lengths: float) -> set[int]:
    """The settled chips (all but ``new``) buried in the pile (:func:`buried_under`)."""
    settled = np.ones(world.n_chips, dtype=bool)
    settled[new] = False
    if not settled.any():
        return set()
    chips = np.flatnonzero(settled)
    positions = world.poses()[0][settled]
    deep = buried_under(positions, world.circumradius_mm(chips.tolist()), depth_lengths)
    return set(chips[deep].tolist())


def buried_under(positions: np.ndarray, reach_mm: np.ndarray, depth_lengths: float) -> np.ndarray:
    """Which chips of a settled pile are buried (n,) bool: their top lies more than
    ``depth_lengths`` chip lengths below the pile's surface over them.

    positions (n, 3) mm chip centres; reach_mm (n,) circumradii. A chip's top is its
    centre's height plus its circumradius; the chip length is twice the largest
    circumradius; the surface over a chip is the highest top among the chips whose centre
    lies in its cell of a square grid one chip length wide or in the eight around it.
    What lands on a pile disturbs its top: a chip that deep stays static support and is
    never woken, so the cost of a pour does not grow with the pile below it. The rule is
    applied before every settling, so a chip the surface comes down to is wakeable again.
    """
    positions = np.asarray(positions, dtype=float).reshape(-1, 3)
    reach = np.asarray(reach_mm, dtype=float).reshape(-1)
    if len(positions) == 0:
        return np.zeros(0, dtype=bool)
    length = 2.0 * float(reach.max())
    top = positions[:, 2] + reach
    cells = np.floor(positions[:, :2] / length).astype(np.int64)
    offsets = np.array([(a, b) for a in (-1, 0, 1) for b in (-1, 0, 1)])
    # Each chip's top raises the surface of its cell and of the eight around it.
    spread = (cells[:, None, :] + offsets[None, :, :]).reshape(-1, 2)
    keys, inverse = np.unique(spread, axis=0, return_inverse=True)
    surface = np.full(len(keys), -np.inf)
    np.maximum.at(surface, inverse.reshape(-1), np.repeat(top, len(offsets)))
    own = inverse.reshape(-1, len(offsets))[:, 4]  # offset (0, 0)
    return top < surface[own] - depth_lengths * length
