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
not stay hanging in the air (a slow mover wakes only the chips above its centre).
Chips buried deep under the pile's surface are never woken (``settling.buried_depth``).
A batch is settled when all its chips and all chips it woke have settled; the next batch
is released then. A batch still moving at ``settling.max_time_s`` is frozen where it is
and recorded as a warning.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable, Mapping

import numpy as np
from scipy.spatial.transform import Rotation

from chipstack.core.errors import InputError, SimulationError
from chipstack.core.overlap import box_penetration_depth, floor_penetration_mm
from chipstack.core.schema import Scenario
from chipstack.core.stack import BatchResult, Stack
from chipstack.packing.checkpoint import DepositionState, round_trip
from chipstack.packing.effects import (
    apply_effect_loads,
    check_effects,
    release_spin,
    setup_effects,
    shake_settled,
    shaped,
    spins_at_release,
)
from chipstack.packing.presets import PRESETS
from chipstack.packing.shapes import ChipShape, make_shape, varies_per_chip
from chipstack.packing.world import GRAVITY_MM_S2, ChipWorld

__all__ = [
    "deposit",
    "release_poses",
    "draw_shapes",
    "settle",
    "shape_table",
    "wake_near_movers",
]

log = logging.getLogger(__name__)

WAKE_MARGIN_MM = 0.5
CHECK_INTERVAL_S = 0.005  # how often speeds are read (simulated time)
ENERGY_BLOWUP_FACTOR = 10.0  # kinetic energy over what the moving chips brought
FELL_THROUGH_MM = 5.0  # a chip centre this far below the floor has tunnelled through it
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


def draw_shapes(
    scenario: Scenario, n: int, rng: np.random.Generator, cache: dict | None = None
) -> list[ChipShape]:
    """The shapes of ``n`` chips: a chip spec drawn by weight, a size factor drawn from its
    distribution, then the shape (random outlines drawn anew for every chip).

    ``cache`` keeps shapes that do not vary between chips, so they are built once.
    """
    specs = scenario.chips
    cache = {} if cache is None else cache
    weights = np.array([c.weight for c in specs], dtype=float)
    choice = (
        rng.choice(len(specs), size=n, p=weights / weights.sum())
        if len(specs) > 1
        else (np.zeros(n, dtype=int))
    )
    shapes = []
    for k in choice:
        spec = specs[k]
        size = _size_factor(spec, rng)
        key = (k, size)
        if varies_per_chip(spec) or key not in cache:
            shape = make_shape(spec, rng, size)
            if varies_per_chip(spec):
                shapes.append(shape)
                continue
            cache[key] = shape
        shapes.append(cache[key])
    return shapes


def _size_factor(spec, rng: np.random.Generator) -> float:
    """In-plane size factor of one chip (1 for `fixed`); see ``ChipSpec.size_distribution``."""
    spread = spec.size_spread
    if spec.size_distribution == "fixed":
        return 1.0
    if spec.size_distribution == "uniform":
        return float(rng.uniform(1 - spread, 1 + spread))
    for _ in range(1000):
        if spec.size_distribution == "normal":
            value = float(rng.normal(1.0, spread))
        else:
            value = float(np.exp(rng.normal(0.0, spread)))
        # A chip under a fifth or over five times nominal is not what a shredder makes.
        if 0.2 <= value <= 5.0:
            return value
    raise InputError("size_spread: the size distribution keeps drawing absurd sizes")


def _box_of(shapes: list[ChipShape], positions: np.ndarray, rotations: np.ndarray):
    """Oriented bounding boxes: centres (n, 3) mm and half sizes (n, 3) mm."""
    offsets = np.array([s.box_centre for s in shapes]).reshape(-1, 3)
    half = np.array([s.half_extents for s in shapes]).reshape(-1, 3)
    return positions + np.einsum("nij,nj->ni", rotations, offsets), half


def release_poses(
    scenario: Scenario,
    shapes: list[ChipShape],
    rng: np.random.Generator,
    occupied: tuple[np.ndarray, np.ndarray, list[ChipShape]] | None = None,
    zone_x_mm: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Draw non-overlapping release poses of ``shapes``: positions (n, 3) mm, quaternions.

    Stacks: centres uniform over the release square and the height range. Containers:
    over a disc above the rim. Conveyors: over the pour zone centred at ``zone_x_mm``
    (belt frame), clear of the side guides. A pose whose bounding box overlaps that of an
    already placed chip (or one in ``occupied``: positions, quaternions, shapes) is drawn
    again.
    """
    n = len(shapes)
    boxes = _PlacedBoxes(n, occupied)
    positions, quaternions = np.empty((n, 3)), np.empty((n, 4))
    for i, shape in enumerate(shapes):
        pose = _free_pose(scenario, shape, rng, boxes, zone_x_mm)
        if pose is None:
            raise scenario.chosen.site.no_room(scenario, n)
        position, rotation, box = pose
        positions[i], quaternions[i] = position, rotation.as_quat()[0]
        boxes.add(*box)
    return positions, quaternions


class _PlacedBoxes:
    """Oriented bounding boxes of the chips placed so far: those ``occupied`` (positions,
    quaternions, shapes) first, then up to ``n_new`` more as they are added."""

    def __init__(
        self, n_new: int, occupied: tuple[np.ndarray, np.ndarray, list[ChipShape]] | None
    ) -> None:
        m = 0 if occupied is None else len(occupied[0])
        self.centres, self.rotations = np.empty((m + n_new, 3)), np.empty((m + n_new, 3, 3))
        self.halves = np.empty((m + n_new, 3))
        if m:
            rotations = Rotation.from_quat(occupied[1]).as_matrix()
            self.centres[:m], self.halves[:m] = _box_of(occupied[2], occupied[0], rotations)
            self.rotations[:m] = rotations
        self.count = m

    def add(self, centre: np.ndarray, half: np.ndarray, rotation: np.ndarray) -> None:
        self.centres[self.count], self.halves[self.count] = centre, half
        self.rotations[self.count] = rotation
        self.count += 1

    def reach(self, shape: ChipShape) -> np.ndarray:
        """Centre distances (one per placed box) beyond which ``shape`` cannot overlap."""
        return shape.circumradius_mm + (
            np.linalg.norm(self.halves[: self.count], axis=1) if self.count else np.empty(0)
        )

    def overlap(
        self, centre: np.ndarray, half: np.ndarray, rotation: np.ndarray, reach: np.ndarray
    ) -> bool:
        """Whether the box (``centre``, ``half`` (1, 3), ``rotation`` (3, 3)) overlaps a
        placed one; ``reach`` from :meth:`reach`."""
        others = self.centres[: self.count]
        near = np.flatnonzero(np.linalg.norm(others - centre, axis=1) < reach)
        if near.size == 0:
            return False
        depth = box_penetration_depth(
            np.repeat(centre, near.size, 0),
            np.repeat(rotation[None], near.size, 0),
            np.repeat(half, near.size, 0),
            others[near],
            self.rotations[: self.count][near],
            self.halves[: self.count][near],
        )
        return depth.max() != 0  # boxes that only touch do not overlap


def _free_pose(
    scenario: Scenario,
    shape: ChipShape,
    rng: np.random.Generator,
    boxes: _PlacedBoxes,
    zone_x_mm: float = 0.0,
) -> tuple[np.ndarray, Rotation, tuple[np.ndarray, np.ndarray, np.ndarray]] | None:
    """A release pose of ``shape`` clear of ``boxes``: position, rotation and its box
    (centre, half sizes, rotation matrix); None if every try overlapped."""
    reach = boxes.reach(shape)
    for _ in range(_MAX_PLACEMENT_TRIES):
        position = _release_point(scenario, shape, rng, zone_x_mm)
        rotation = _random_rotations(scenario, 1, rng)
        matrix = rotation.as_matrix()[0]
        box_centre, box_half = _box_of([shape], position[None], matrix[None])
        if not boxes.overlap(box_centre, box_half, matrix, reach):
            return position, rotation, (box_centre[0], box_half[0], matrix)
    return None


def _release_point(
    scenario: Scenario, shape: ChipShape, rng: np.random.Generator, zone_x_mm: float = 0.0
):
    clearance = shape.circumradius_mm + 0.1  # no release pose may touch the floor
    return scenario.chosen.site.release_point(scenario, clearance, rng, zone_x_mm)


class _RestTracker:
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
    tracker = _RestTracker(
        world, s.speed_mm_s * s.hold_time_s, hold_checks, _domain_mm(scenario), s.freeze
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
    tracker: _RestTracker,
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


def _domain_mm(scenario: Scenario) -> float:
    """Twenty times the scenario's own size: a chip beyond has left the experiment."""
    d = scenario.deposition
    size = max(d.target_size_mm, max(d.release_height_mm))
    size = max(size, scenario.chosen.site.extent_mm(scenario))
    return 20.0 * size


def deposit(
    scenario: Scenario,
    progress: Callable[[int, BatchResult], None] | None = None,
    effects: Mapping[str, float] | None = None,
    resume: DepositionState | None = None,
    on_batch: Callable[[DepositionState], None] | None = None,
) -> Stack:
    """Run the batch deposition of ``scenario`` and return the settled :class:`Stack`.

    Kind ``stack``: ``deposition.chips`` chips in batches onto the square target. Kind
    ``container``: batches poured into the cylinder until it is full (a settled chip's
    centre of mass inside the wall's footprint at or above the rim) or
    ``deposition.chips`` have been poured; only the final state is recorded.
    ``progress`` is called after each batch with (batch number, its result; for
    containers the result of the last batch only, else ``None``).
    All random draws come from ``numpy.random.default_rng(scenario.seed)`` (a release
    effect's spins from a stream of the seed and the batch number).
    ``effects`` switches unmodelled effects on (``{name: strength}``, see
    :mod:`packing.effects`); the diagnosis uses them.

    Every batch of a stack (every ``pours_per_world`` pours of a container) runs in a new
    physics world built from the state the previous one left (:mod:`packing.checkpoint`);
    ``on_batch(state)`` is called with that state after each world, so a caller can save
    it, and ``resume`` continues from a saved one. A resumed deposition ends bit for bit
    where an uninterrupted one does.
    """
    preset = PRESETS.get(scenario.physics.preset, key="physics.preset")
    strengths = check_effects(effects or {}, scenario.kind)
    setup = setup_effects(preset, scenario.physics, strengths)
    if strengths:
        scenario = dataclasses.replace(scenario, physics=setup.physics)
    d = scenario.deposition
    n_batches = -(-d.chips // d.batch_size)
    state = _initial_state(scenario) if resume is None else resume
    if state.batches_done > n_batches or len(state.chip_batch) > d.chips:
        raise InputError(
            f"deposition state: {state.batches_done} batches and {len(state.chip_batch)} "
            f"chips done, more than the scenario's {n_batches} batches of {d.chips} chips"
        )
    pours = scenario.chosen.site.pours_per_world
    if not scenario.settling.freeze:
        # A dynamic pile rebuilt from saved poses loses the solver's contact history and
        # sags (median 1.1 mm in 50 ms for rods 10 x 2 mm, measured): one world, start
        # to end, so a run without freezing resumes from its start.
        pours = n_batches
    while state.batches_done < n_batches and not state.full:
        state = _deposit_batches(
            scenario, preset, setup, strengths, state, n_batches, progress, pours
        )
        # What a resumed run would read back from the state file: both go on from this.
        state = round_trip(state)
        if on_batch is not None:
            on_batch(state)
    return _stack_of(scenario, state)


def _stack_of(scenario: Scenario, state: DepositionState) -> Stack:
    """The stack a finished deposition leaves, with a warning if a container is not full."""
    site = scenario.chosen.site
    warnings = list(state.warnings)
    message = site.unfinished(scenario, state.full, len(state.chip_batch))
    if message is not None:
        log.warning(message)
        warnings.append(message)
    shapes, shape_index = shape_table([state.pool[i] for i in state.chip_shape])
    return Stack(
        shapes=shapes,
        shape_index=shape_index,
        batch=np.asarray(state.chip_batch),
        batches=state.results,
        target_size_mm=site.footprint_mm(scenario),
        warnings=tuple(warnings),
    )


def _initial_state(scenario: Scenario) -> DepositionState:
    return DepositionState(
        batches_done=0,
        time_s=0.0,
        rng_state=np.random.default_rng(scenario.seed).bit_generator.state,
        pool=(),
        chip_shape=np.empty(0, dtype=np.int64),
        chip_batch=np.empty(0, dtype=np.int64),
        positions=np.empty((0, 3)),
        quaternions=np.empty((0, 4)),
        results=(),
        warnings=(),
    )


@dataclasses.dataclass
class _WorkingState:
    """A :class:`DepositionState` unpacked into the forms a batch works on (a live random
    generator; lists; shapes keyed by identity), and packed again after the batch."""

    rng: np.random.Generator
    shapes_of: list[ChipShape]  # per chip
    batch_of: list[int]  # per chip
    cache: dict[tuple[int, float], ChipShape]  # draw_shapes' cache
    reshaped: dict[int, tuple[ChipShape, ChipShape]]  # id(drawn): (drawn, with shape effects)
    warnings: list[str]
    floor_reference_mass_g: float | None

    @classmethod
    def unpack(cls, state: DepositionState) -> _WorkingState:
        rng = np.random.Generator(np.random.PCG64())
        rng.bit_generator.state = state.rng_state
        pool = state.pool
        return cls(
            rng=rng,
            shapes_of=[pool[i] for i in state.chip_shape],
            batch_of=state.chip_batch.tolist(),
            cache={(k, size): pool[i] for k, size, i in state.cache},
            reshaped={id(pool[a]): (pool[a], pool[b]) for a, b in state.reshaped},
            warnings=list(state.warnings),
            floor_reference_mass_g=state.floor_reference_mass_g,
        )

    def pack(
        self,
        batch: int,
        time_s: float,
        poses: tuple[np.ndarray, np.ndarray],
        results: tuple[BatchResult, ...],
        full: bool,
    ) -> DepositionState:
        # Every shape a chip, the cache or the reshaping refers to, once, in a fixed order.
        pool: dict[int, ChipShape] = {}
        pairs = (x for pair in self.reshaped.values() for x in pair)
        for shape in [*self.shapes_of, *self.cache.values(), *pairs]:
            pool.setdefault(id(shape), shape)
        where = {key: k for k, key in enumerate(pool)}
        return DepositionState(
            batches_done=batch,
            time_s=time_s,
            rng_state=self.rng.bit_generator.state,
            pool=tuple(pool.values()),
            chip_shape=np.array([where[id(shape)] for shape in self.shapes_of], dtype=np.int64),
            chip_batch=np.array(self.batch_of, dtype=np.int64),
            positions=poses[0],
            quaternions=poses[1],
            results=results,
            warnings=tuple(self.warnings),
            cache=tuple((k, size, where[id(shape)]) for (k, size), shape in self.cache.items()),
            reshaped=tuple((where[a], where[id(b)]) for a, (_, b) in self.reshaped.items()),
            floor_reference_mass_g=self.floor_reference_mass_g,
            full=bool(full),
        )


def _deposit_batches(
    scenario: Scenario,
    preset,
    setup,
    strengths: dict[str, float],
    state: DepositionState,
    n_batches: int,
    progress: Callable[[int, BatchResult], None] | None,
    pours: int,
) -> DepositionState:
    """Release and settle the next ``pours`` batches (fewer once the last batch or, for a
    container, the rim is reached) in one world rebuilt from ``state``; returns the state
    after them."""
    site = scenario.chosen.site
    work = _WorkingState.unpack(state)
    results = state.results
    batch, full = state.batches_done, False
    with ChipWorld(preset, scenario.physics) as world:
        world.time_s = state.time_s
        _rebuild_world(world, scenario, state, work, setup.contact)
        last = min(n_batches, batch + pours)
        while batch < last and not full:
            wall_start = time.perf_counter()
            batch += 1
            new = _release_batch(world, scenario, strengths, work, batch)
            if work.floor_reference_mass_g is None:
                work.floor_reference_mass_g = world.mass_g(new[0])
                _soften_floor(world, setup.contact, work.floor_reference_mass_g)
            settled, steps, wakes, start_time = _settle_batch(
                world, scenario, setup, strengths, work, new, batch
            )
            poses = world.poses()
            full = site.is_full(scenario, poses[0])
            result = None
            if site.records_every_batch or batch == n_batches or full:
                wall = time.perf_counter() - wall_start
                result = _batch_result(
                    world, scenario, work.shapes_of, batch, start_time, steps, wakes, settled, wall
                )
                results = (*results, result)
                log.info(
                    "batch %d settled=%s in %.2f s simulated, %.2f s wall",
                    batch,
                    settled,
                    result.sim_time_s,
                    result.wall_time_s,
                )
            if progress is not None:
                progress(batch, result)
        time_s = world.time_s
    return work.pack(batch, time_s, poses, results, full)


def _rebuild_world(
    world: ChipWorld, scenario: Scenario, state: DepositionState, work: _WorkingState, contact
) -> None:
    """The world as the previous batch left it: the container wall, the pile (frozen) and,
    once known, the compliant floor."""
    scenario.chosen.site.build(world, scenario)
    for shape, p, q in zip(work.shapes_of, state.positions, state.quaternions, strict=True):
        chip = world.add_chip(shape, p, q)
        if scenario.settling.freeze:
            world.freeze(chip)
    if work.floor_reference_mass_g is not None:
        _soften_floor(world, contact, work.floor_reference_mass_g)


def _soften_floor(world: ChipWorld, contact, reference_mass_g: float) -> None:
    world.set_floor_compliance(
        contact.floor_compliance_mm_n, contact.floor_damping_ratio, reference_mass_g
    )


_RELEASE_STREAM = 0x5E1E  # tags the release effects' random stream (any fixed number)


def _release_batch(
    world: ChipWorld,
    scenario: Scenario,
    strengths: dict[str, float],
    work: _WorkingState,
    batch: int,
) -> list[int]:
    """Draw the next batch's chips and release them clear of the pile; returns their
    chip indices."""
    d = scenario.deposition
    count = min(d.batch_size, d.chips - len(work.batch_of))
    shapes = draw_shapes(scenario, count, work.rng, work.cache)
    if strengths:
        shapes = _with_shape_effects(shapes, strengths, work.reshaped)
    occupied = (*world.poses(), work.shapes_of) if world.n_chips else None
    positions, quaternions = release_poses(scenario, shapes, work.rng, occupied)
    new = [
        world.add_chip(shape, p, q)
        for shape, p, q in zip(shapes, positions, quaternions, strict=True)
    ]
    # Release effects (a spin as the chip leaves its holder), as in a drop. Their draws
    # come from a stream of their own (the scenario's seed and the batch), so that a
    # stack with the effect at strength 0 is the stack without it.
    if spins_at_release(strengths):
        draws = np.random.default_rng([scenario.seed, batch, _RELEASE_STREAM]).normal(
            size=(count, 3)
        )
        for chip, omega in zip(new, release_spin(strengths, draws), strict=True):
            if omega.any():
                world.set_velocity(chip, np.zeros(3), omega)
    work.batch_of += [batch] * count
    work.shapes_of += shapes
    return new


def _with_shape_effects(
    shapes: list[ChipShape],
    strengths: dict[str, float],
    reshaped: dict[int, tuple[ChipShape, ChipShape]],
) -> list[ChipShape]:
    """The shapes with the shape effects applied; ``reshaped`` remembers each drawn shape's
    result, so a shape shared by many chips is reshaped once and stays shared."""
    for shape in shapes:
        if id(shape) not in reshaped:
            reshaped[id(shape)] = (shape, shaped(shape, strengths))
    return [reshaped[id(shape)][1] for shape in shapes]


def _settle_batch(
    world: ChipWorld,
    scenario: Scenario,
    setup,
    strengths: dict[str, float],
    work: _WorkingState,
    new: list[int],
    batch: int,
) -> tuple[bool, int, int, float]:
    """Settle the new chips, then let each after-batch effect (vibration taps) shake the
    pile and settle it again. Returns (settled, steps, wakes, start time) as
    :func:`settle`, steps summed over every settling."""
    loads = _per_step_loads(world, setup)
    settled, steps, wakes, start_time = settle(world, new, scenario, loads, work.warnings)

    def settle_all(everyone: list[int]) -> int:
        nonlocal settled
        settled, more, _, _ = settle(world, everyone, scenario, loads, work.warnings)
        return more

    steps += shake_settled(world, strengths, work.rng, settle_all)
    if not settled:
        message = (
            f"batch {batch} did not settle within {scenario.settling.max_time_s:g} s of "
            "simulated time; the chips still moving were frozen where they were"
        )
        log.warning(message)
        work.warnings.append(message)
    return settled, steps, wakes, start_time


def _per_step_loads(world: ChipWorld, setup) -> Callable[[list[int]], None] | None:
    """The loads the per-step effects apply before every step, or None without any."""
    per_step = list(setup.per_step)
    if not per_step:
        return None

    def loads(awake: list[int]) -> None:
        apply_effect_loads(world, awake, per_step)

    return loads


def shape_table(shapes_of: list[ChipShape]) -> tuple[tuple[ChipShape, ...], np.ndarray]:
    """The distinct shapes of per-chip ``shapes_of`` (by identity, in order of first use,
    renamed apart where names clash: :func:`_unique_names`) and each chip's index (n,)
    into them."""
    distinct = list(dict.fromkeys(shapes_of))
    index = {id(shape): k for k, shape in enumerate(distinct)}
    return (
        tuple(_unique_names(distinct)),
        np.array([index[id(shape)] for shape in shapes_of], dtype=int),
    )


def _unique_names(shapes: list[ChipShape]) -> list[ChipShape]:
    """Shapes renamed ``name #k`` where several distinct shapes share a name (random
    outlines), so files can refer to each by name."""
    counts: dict[str, int] = {}
    for shape in shapes:
        counts[shape.name] = counts.get(shape.name, 0) + 1
    seen: dict[str, int] = {}
    renamed = []
    for shape in shapes:
        if counts[shape.name] > 1:
            seen[shape.name] = seen.get(shape.name, 0) + 1
            shape = dataclasses.replace(shape, name=f"{shape.name} #{seen[shape.name]}")
        renamed.append(shape)
    return renamed


def _batch_result(
    world: ChipWorld,
    scenario: Scenario,
    shapes: list[ChipShape],
    batch: int,
    start_time: float,
    steps: int,
    wakes: int,
    settled: bool,
    wall: float,
) -> BatchResult:
    positions, quaternions = world.poses()
    contacts = world.contacts(scenario.output.contact_distance_mm)
    between_chips = contacts.chip_b >= 0
    chip_depth = float(np.maximum(-contacts.distance[between_chips], 0.0).max(initial=0.0))
    groups: dict[int, tuple[ChipShape, list[int]]] = {}
    for k, shape in enumerate(shapes):
        groups.setdefault(id(shape), (shape, []))[1].append(k)
    floor = max(
        (
            float(floor_penetration_mm(positions[idx], quaternions[idx], shape.vertices).max())
            for shape, idx in groups.values()
        ),
        default=0.0,
    )
    outside = scenario.chosen.site.outside(scenario, positions)
    return BatchResult(
        batch=batch,
        positions=positions,
        quaternions=quaternions,
        contacts=contacts,
        sim_time_s=world.time_s - start_time,
        wall_time_s=wall,
        steps=steps,
        settled=settled,
        wakes=wakes,
        max_floor_penetration_mm=max(floor, 0.0),
        max_chip_penetration_mm=chip_depth,
        outside_target=int(outside.sum()),
    )
