"""Batch deposition (paper, section 2.3.3) with local settling.

Each batch of chips is released at rest, at random positions over the target, random
heights and random orientations, without overlapping one another or the pile. Gravity
does the rest. A chip *settles* when, for ``settling.hold_time_s`` of simulated time, no
point of it strays more than ``settling.speed_mm_s x settling.hold_time_s`` from where it
was (its speed averaged over the hold time stays below the threshold); it is then frozen
(made static) so it no longer costs solver time or trembles. A frozen chip is woken
again when a moving chip (faster than ``settling.wake_speed_mm_s``, or one that strayed
out of its rest window) could reach it before the next speed check (surfaces within
0.5 mm plus the distance the mover travels in a check interval): impacts push the pile
instead of bouncing off static chips, and a chip resting on one that slides away does
not stay hanging in the air. A batch is settled when all its chips and all chips it woke
have settled; the next batch is released then. A batch still moving at
``settling.max_time_s`` is frozen where it is and recorded as a warning.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

import numpy as np
from scipy.spatial.transform import Rotation

from packing.config import Scenario
from packing.errors import InputError
from packing.overlap import box_penetration_depth, floor_penetration_mm, penetrating_pairs
from packing.presets import PRESETS
from packing.shapes import ChipShape, make_shape
from packing.stack import BatchResult, Stack
from packing.world import ChipWorld

__all__ = ["deposit", "release_poses"]

log = logging.getLogger(__name__)

WAKE_MARGIN_MM = 0.5
CHECK_INTERVAL_S = 0.005  # how often speeds are read (simulated time)
_MAX_PLACEMENT_TRIES = 2000


def _random_rotations(scenario: Scenario, n: int, rng: np.random.Generator) -> Rotation:
    d = scenario.deposition
    if d.orientation == "uniform":
        return Rotation.from_quat(_unit_quaternions(n, rng))
    angles = np.column_stack(
        [
            rng.uniform(*np.radians(r), size=n)
            for r in (d.roll_range_deg, d.pitch_range_deg, d.yaw_range_deg)
        ]
    )
    return Rotation.from_euler("xyz", angles)


def _unit_quaternions(n: int, rng: np.random.Generator) -> np.ndarray:
    """Uniform random rotations (normalised 4-D Gaussians), x, y, z, w."""
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def release_poses(
    scenario: Scenario,
    shape: ChipShape,
    n: int,
    rng: np.random.Generator,
    occupied: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Draw ``n`` non-overlapping release poses: positions (n, 3) mm, quaternions (n, 4).

    Centres are uniform over the release square and the height range; a pose that
    overlaps an already placed chip (or one in ``occupied``) is drawn again.
    """
    d = scenario.deposition
    half = d.release_side_mm / 2
    # Every chip a new pose must not overlap: the pile, then this batch as it is placed.
    m = 0 if occupied is None else len(occupied[0])
    placed_pos, placed_rot = np.empty((m + n, 3)), np.empty((m + n, 3, 3))
    if m:
        placed_pos[:m] = occupied[0]
        placed_rot[:m] = Rotation.from_quat(occupied[1]).as_matrix()
    positions, quaternions = np.empty((n, 3)), np.empty((n, 4))
    reach = 2 * shape.circumradius_mm
    for i in range(n):
        others, others_rot = placed_pos[: m + i], placed_rot[: m + i]
        for _ in range(_MAX_PLACEMENT_TRIES):
            centre = np.array([*rng.uniform(-half, half, 2), rng.uniform(*d.release_height_mm)])
            rotation = _random_rotations(scenario, 1, rng)
            matrix = rotation.as_matrix()[0]
            near = np.flatnonzero(np.linalg.norm(others - centre, axis=1) < reach)
            if near.size == 0:
                break
            depth = box_penetration_depth(
                np.repeat(centre[None], near.size, 0),
                np.repeat(matrix[None], near.size, 0),
                shape.half_extents,
                others[near],
                others_rot[near],
                shape.half_extents,
            )
            if depth.max() == 0:
                break
        else:
            raise InputError(
                "deposition: cannot release "
                f"{n} chips without overlap in a {d.release_side_mm:g} mm square between "
                f"{d.release_height_mm[0]:g} and {d.release_height_mm[1]:g} mm; "
                "widen release_height_mm or lower batch_size"
            )
        positions[i], quaternions[i] = centre, rotation.as_quat()[0]
        placed_pos[m + i], placed_rot[m + i] = centre, matrix
    return positions, quaternions


class _RestTracker:
    """Which chips are still moving, and freezing the ones that have come to rest.

    A chip is at rest when no point of it strays more than ``stray_mm`` (speed threshold x
    hold time) from where it was at the start of a window of ``hold_checks`` checks: its
    speed, averaged over the hold time, stays below the threshold. Averaging, rather than
    requiring every instantaneous reading to be low, lets a chip that trembles in place
    on the solver's contact noise settle, while a chip creeping away never does.
    """

    def __init__(self, world: ChipWorld, stray_mm: float, hold_checks: int) -> None:
        self.world, self.stray_mm, self.hold_checks = world, stray_mm, hold_checks
        self.awake: dict[int, int] = {}  # chip -> checks spent inside its window
        self._anchor: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def add(self, chips: list[int]) -> None:
        if not chips:
            return
        positions, quaternions, _ = self.world.states(chips)
        for k, chip in enumerate(chips):
            self.awake[chip] = 0
            self._anchor[chip] = (positions[k], quaternions[k])

    def update(self, wake_speed_mm_s: float) -> list[tuple[int, float]]:
        """Read every awake chip and freeze the settled ones.

        Returns (chip, speed mm/s) of the chips that moved since the last check: faster
        than ``wake_speed_mm_s``, or strayed out of their rest window.
        """
        chips = sorted(self.awake)
        positions, quaternions, speed = self.world.states(chips)
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
            if self.awake[chip] >= self.hold_checks:
                self.world.freeze(chip)
                del self.awake[chip], self._anchor[chip]
        return moving


def deposit(
    scenario: Scenario,
    progress: Callable[[int, BatchResult], None] | None = None,
) -> Stack:
    """Run the batch deposition of ``scenario`` and return the settled :class:`Stack`.

    ``progress`` is called after each batch with (batch number, its result).
    All random draws come from ``numpy.random.default_rng(scenario.seed)``.
    """
    shape = make_shape(scenario.chip)
    preset = PRESETS.get(scenario.physics.preset, key="physics.preset")
    rng = np.random.default_rng(scenario.seed)
    d, s = scenario.deposition, scenario.settling
    check_steps = max(1, round(CHECK_INTERVAL_S / scenario.physics.time_step_s))
    check_interval_s = check_steps * scenario.physics.time_step_s
    hold_checks = max(1, int(np.ceil(s.hold_time_s / check_interval_s)))
    batch_of: list[int] = []
    results: list[BatchResult] = []
    warnings: list[str] = []

    with ChipWorld(preset, scenario.physics) as world:
        n_batches = -(-d.chips // d.batch_size)
        for batch in range(1, n_batches + 1):
            wall_start = time.perf_counter()
            count = min(d.batch_size, d.chips - len(batch_of))
            occupied = world.poses() if world.n_chips else None
            positions, quaternions = release_poses(scenario, shape, count, rng, occupied)
            new = [world.add_chip(shape, p, q) for p, q in zip(positions, quaternions, strict=True)]
            batch_of += [batch] * count
            tracker = _RestTracker(world, s.speed_mm_s * s.hold_time_s, hold_checks)
            tracker.add(new)
            start_time, steps, wakes = world.time_s, 0, 0
            while tracker.awake and world.time_s - start_time < s.max_time_s:
                world.step(check_steps)
                steps += check_steps
                for chip, speed in tracker.update(s.wake_speed_mm_s):
                    # Wake every frozen chip this one can reach before the next check, so an
                    # impact pushes what it hits instead of bouncing off a static chip, and a
                    # chip resting on one that slides away does not stay hanging in the air.
                    reach = WAKE_MARGIN_MM + speed * check_interval_s
                    near = [c for c in world.chips_near(chip, reach) if c not in tracker.awake]
                    woken = world.within(chip, near, reach)
                    for other in woken:
                        world.wake(other)
                    tracker.add(woken)
                    wakes += len(woken)
            awake = sorted(tracker.awake)
            settled = not awake
            if not settled:
                speeds = dict(zip(awake, world.states(awake)[2].tolist(), strict=True))
                message = (
                    f"batch {batch} did not settle within {s.max_time_s:g} s of simulated time: "
                    f"{len(speeds)} chips still moving (fastest {max(speeds.values()):.1f} mm/s, "
                    f"chips {sorted(speeds)[:10]}); they were frozen where they were"
                )
                log.warning(message)
                warnings.append(message)
                for chip in speeds:
                    world.freeze(chip)
            result = _batch_result(
                world,
                scenario,
                shape,
                batch,
                start_time,
                steps,
                wakes,
                settled,
                time.perf_counter() - wall_start,
            )
            results.append(result)
            log.info(
                "batch %d settled=%s in %.2f s simulated, %.2f s wall",
                batch,
                settled,
                result.sim_time_s,
                result.wall_time_s,
            )
            if progress is not None:
                progress(batch, result)

    return Stack(
        shapes=(shape,),
        shape_index=np.zeros(len(batch_of), dtype=int),
        batch=np.asarray(batch_of),
        batches=tuple(results),
        target_size_mm=d.target_size_mm,
        warnings=tuple(warnings),
    )


def _batch_result(
    world: ChipWorld,
    scenario: Scenario,
    shape: ChipShape,
    batch: int,
    start_time: float,
    steps: int,
    wakes: int,
    settled: bool,
    wall: float,
) -> BatchResult:
    positions, quaternions = world.poses()
    _, depth = penetrating_pairs(positions, quaternions, shape.half_extents)
    floor = floor_penetration_mm(positions, quaternions, shape.vertices)
    half = scenario.deposition.target_size_mm / 2
    return BatchResult(
        batch=batch,
        positions=positions,
        quaternions=quaternions,
        contacts=world.contacts(scenario.output.contact_distance_mm),
        sim_time_s=world.time_s - start_time,
        wall_time_s=wall,
        steps=steps,
        settled=settled,
        wakes=wakes,
        max_floor_penetration_mm=float(floor.max(initial=0.0)),
        max_chip_penetration_mm=float(depth.max(initial=0.0)),
        outside_target=int((np.abs(positions[:, :2]) > half).any(axis=1).sum()),
    )
