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

from chipstack.core.errors import InputError
from chipstack.core.overlap import floor_penetration_mm
from chipstack.core.schema import Scenario
from chipstack.core.stack import BatchResult, Stack
from chipstack.core.stages import StageInputs
from chipstack.packing.checkpoint import (
    DepositionState,
    round_trip,
    state_from_arrays,
    state_to_arrays,
)
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
from chipstack.packing.release import draw_shapes, release_poses, shape_table
from chipstack.packing.settling import settle
from chipstack.packing.shapes import ChipShape
from chipstack.packing.world import ChipWorld

__all__ = ["deposit_stack", "deposit"]

log = logging.getLogger(__name__)


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


def deposit_stack(inputs: StageInputs, stage_name: str) -> Stack:
    """The batch deposition of ``inputs.scenario``, resumed from its checkpoint and saving
    one after every batch when the run keeps them, reporting each batch."""
    scenario = inputs.scenario
    n_batches = -(-scenario.deposition.chips // scenario.deposition.batch_size)
    report = inputs.options.progress

    def progress(batch: int, result: BatchResult | None) -> None:
        if report is not None:
            detail = {}
            if result is not None:  # containers report only their last batch
                detail = {"chips": len(result.positions), "sim_s": f"{result.sim_time_s:.2f}"}
            report(stage_name, batch, n_batches, detail)

    checkpoint = inputs.checkpoint
    resume = checkpoint.resume(state_from_arrays) if checkpoint is not None else None
    if resume is not None:
        progress(resume.batches_done, resume.results[-1] if resume.results else None)
    on_batch = None
    if checkpoint is not None:

        def on_batch(state) -> None:
            checkpoint.save(state_to_arrays(state), state.batches_done)

    return deposit(scenario, progress=progress, resume=resume, on_batch=on_batch)
