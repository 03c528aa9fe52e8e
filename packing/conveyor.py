"""A mat poured continuously onto a moving belt (kind ``conveyor``).

The line pours chips from a fixed pour zone onto a belt that carries the mat away along
+x. It is simulated in the belt's frame: there the belt is the floor at rest and the
pour zone moves along -x at the belt's speed, and a released chip starts with the
horizontal velocity ``feed speed - belt speed``. The two frames differ by a constant
velocity, so the contact and gravity physics are the same (Galilean invariance; the
model has no air): chips ride the belt by friction exactly as on a floor, nothing is
teleported. Positions are recorded in the belt's frame: x along the belt in its direction
of travel, 0 where the zone's centre was at the first pour, so the first chips poured
lie at the largest x; y across the belt from its centre line.

Chips are released ``deposition.batch_size`` at a time, one pour every
``batch_size / pour_rate`` seconds, at random points of the zone (its length along x,
its width across), at ``deposition.release_height_mm`` and ``deposition.orientation``,
clear of every chip still in the air. They settle, freeze and wake as in a stack
(:mod:`packing.deposition`), but the pours do not wait for one another: time runs on.

What keeps the cost per chip flat: a frozen chip farther downstream of the zone than
``conveyor.active_lengths`` chip lengths (and beyond every moving chip by two chip
lengths) leaves the physics world for good, its pose recorded (``ChipWorld.retire``). The
engine then holds only the chips near the zone, however long the mat grows.

A chip whose centre goes past an edge of the belt has fallen off: it is taken out and
reported as spilled. Every chip released is on the belt, spilled, or reported as having
left the domain (through the floor, or flung far away).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from chipstack.core.chipshape import ChipShape
from chipstack.core.errors import InputError
from chipstack.core.schema import Scenario
from chipstack.core.stack import Stack
from chipstack.core.stages import StageInputs
from chipstack.packing.deposition import _batch_result
from chipstack.packing.presets import PRESETS
from chipstack.packing.release import draw_shapes, release_poses, shape_table
from chipstack.packing.settling import CHECK_INTERVAL_S, RestTracker, wake_near_movers
from chipstack.packing.world import GRAVITY_MM_S2, ChipWorld

__all__ = [
    "pour",
    "MatRecord",
    "ConveyorResult",
    "pour_mat",
    "steady_range_mm",
    "ON_BELT",
    "SPILLED",
]

log = logging.getLogger(__name__)

ON_BELT, SPILLED, LEFT_DOMAIN = 0, 1, 2  # MatRecord.status
STATUS_NAMES = ("on belt", "spilled", "left the domain")
# A moving chip must be this many chip lengths upstream of a chip that is retired.
_CLEAR_OF_MOVERS_LENGTHS = 2.0


@dataclass(frozen=True)
class MatRecord:
    """Every chip of a poured mat, in the belt's frame (see the module docstring).

    shapes: the distinct shapes; shape_index (n,) into them; pour (n,) 1-based pour of each
    chip; positions (n, 3) mm and quaternions (n, 4) x, y, z, w, final; status (n,)
    ``ON_BELT``, ``SPILLED`` or ``LEFT_DOMAIN``; zone_x_mm (pours,) the x of the centre of
    the zone that poured, at each pour; steady_mm (x_low, x_high) the mat's steady part
    (:func:`steady_range_mm`); panel_centre_mm the centre (x, y) of the panel cut from it.
    """

    shapes: tuple[ChipShape, ...]
    shape_index: np.ndarray
    pour: np.ndarray
    positions: np.ndarray
    quaternions: np.ndarray
    status: np.ndarray
    zone_x_mm: np.ndarray
    steady_mm: tuple[float, float]
    panel_centre_mm: tuple[float, float]
    belt_width_mm: float
    masses_g: np.ndarray
    sim_time_s: float
    wall_time_s: float
    steps: int
    wakes: int
    settled: bool
    most_in_world: int  # the largest number of chips the engine held at once
    warnings: tuple[str, ...] = ()

    @property
    def n_chips(self) -> int:
        return len(self.pour)


@dataclass(frozen=True)
class ConveyorResult:
    """A poured mat and the panel cut from it (the stack later stages take)."""

    mat: MatRecord
    panel: Stack

    @property
    def warnings(self) -> tuple[str, ...]:
        return self.panel.warnings


def pour_timing(scenario: Scenario) -> tuple[int, float]:
    """(number of pours, seconds between pours)."""
    d, c = scenario.deposition, scenario.conveyor
    return -(-d.chips // d.batch_size), d.batch_size / c.pour_rate_chips_s


def landing_offset_mm(scenario: Scenario) -> float:
    """How far along x (belt frame) a chip lands from where it was released: its
    horizontal speed relative to the belt times the fall from the mean release height."""
    c = scenario.conveyor
    fall_s = math.sqrt(2.0 * float(np.mean(scenario.deposition.release_height_mm)) / GRAVITY_MM_S2)
    return (c.feed_speed_mm_s - c.belt_speed_mm_s) * fall_s


def steady_range_mm(scenario: Scenario) -> tuple[float, float]:
    """The mat's steady part (x_low, x_high, belt frame, mm): what the whole pour zone
    passed over, from the first pour's zone to the last's, less the first
    ``conveyor.run_in_mm`` (where the heap under the zone was forming). Nominal pour
    times; empty (low > high) when the mat is too short. At belt speed 0 it is the zone
    itself."""
    c = scenario.conveyor
    n_pours, interval = pour_timing(scenario)
    offset = landing_offset_mm(scenario)
    if c.belt_speed_mm_s == 0:
        return offset - c.zone_length_mm / 2, offset + c.zone_length_mm / 2
    # Zone k covered x in [k s - v T + l/2, k s - l/2] wholly; the steady part is what
    # every zone covered: from the last zone's low end to the first zone's high end.
    last_x = zone_offset_mm(scenario, c.zones - 1) - c.belt_speed_mm_s * (n_pours - 1) * interval
    return last_x + c.zone_length_mm / 2 + offset, -c.zone_length_mm / 2 + offset - c.run_in_mm


def zone_offset_mm(scenario: Scenario, zone: int) -> float:
    """Where zone ``zone`` (0-based) is along the line from zone 0, mm (downstream +)."""
    return zone * scenario.conveyor.zone_spacing_mm


def check_conveyor(scenario: Scenario, largest_across_mm: float) -> None:
    """Belt, zone and panel values that cannot work, refused naming the key."""
    c, d = scenario.conveyor, scenario.deposition
    if c.zone_width_mm > c.belt_width_mm:
        raise InputError(
            f"conveyor.zone_width_mm: the pour zone ({c.zone_width_mm:g} mm) is wider than "
            f"the belt (conveyor.belt_width_mm = {c.belt_width_mm:g} mm): chips would be "
            "poured off it"
        )
    if largest_across_mm > c.belt_width_mm:
        raise InputError(
            f"conveyor.belt_width_mm: the chips ({largest_across_mm:.1f} mm across) are wider "
            f"than the belt ({c.belt_width_mm:g} mm)"
        )
    if c.zones > 1 and c.zone_spacing_mm < c.zone_length_mm:
        raise InputError(
            f"conveyor.zone_spacing_mm: zones {c.zone_spacing_mm:g} mm apart overlap (each is "
            f"conveyor.zone_length_mm = {c.zone_length_mm:g} mm long)"
        )
    if c.cell_mm > c.belt_width_mm:
        raise InputError(
            f"conveyor.cell_mm: a cell of {c.cell_mm:g} mm is wider than the belt "
            f"(conveyor.belt_width_mm = {c.belt_width_mm:g} mm)"
        )
    if d.target_size_mm > c.belt_width_mm:
        raise InputError(
            f"deposition.target_size_mm: the panel ({d.target_size_mm:g} mm) is wider than "
            f"the belt (conveyor.belt_width_mm = {c.belt_width_mm:g} mm)"
        )
    if c.belt_speed_mm_s > 0:
        low, high = steady_range_mm(scenario)
        if d.target_size_mm > high - low:
            raise InputError(
                f"deposition.target_size_mm: the panel ({d.target_size_mm:g} mm) is longer "
                f"than the mat's steady part ({max(high - low, 0.0):.0f} mm: belt speed x "
                "pour time - zone length - conveyor.run_in_mm); raise deposition.chips or "
                "conveyor.belt_speed_mm_s, or cut a smaller panel"
            )


def pour_mat(
    scenario: Scenario, progress: Callable[[int, int], None] | None = None
) -> ConveyorResult:
    """Pour ``scenario``'s mat onto the belt and cut its panel.

    ``progress(pours done, pours)`` is called after each pour. All random draws come from
    ``numpy.random.default_rng(scenario.seed)``.
    """
    wall_start = time.perf_counter()
    preset = PRESETS.get(scenario.physics.preset, key="physics.preset")
    with ChipWorld(preset, scenario.physics) as world:
        if scenario.conveyor.side_guides:
            world.add_side_guides(scenario.conveyor.belt_width_mm / 2)
        line = _Line(world, scenario)
        line.run(progress)
        mat = line.record(time.perf_counter() - wall_start)
    panel = cut_panel(scenario, mat)
    return ConveyorResult(mat=mat, panel=panel)


class _Line:
    """The pouring loop's state: the world, the rest tracker, who is where."""

    def __init__(self, world: ChipWorld, scenario: Scenario) -> None:
        self.world, self.scenario = world, scenario
        c, s = scenario.conveyor, scenario.settling
        self.rng = np.random.default_rng(scenario.seed)
        self.n_pours, self.interval = pour_timing(scenario)
        dt = scenario.physics.time_step_s
        self.check_steps = max(1, round(CHECK_INTERVAL_S / dt))
        self.check_interval_s = self.check_steps * dt
        hold_checks = max(1, int(np.ceil(s.hold_time_s / self.check_interval_s)))
        mat_length = c.belt_speed_mm_s * self.n_pours * self.interval
        reach = max(c.belt_width_mm, max(scenario.deposition.release_height_mm))
        self.tracker = RestTracker(
            world, s.speed_mm_s * s.hold_time_s, hold_checks, mat_length + 20 * reach, s.freeze
        )
        self.shapes_of: list[ChipShape] = []
        self.pour_of: list[int] = []
        self.zone_x: list[float] = []
        self.status: dict[int, int] = {}
        self.live: set[int] = set()  # chips in the engine
        self.cache: dict = {}
        self.chip_length_mm = 0.0
        self.steps = self.wakes = 0
        self.most_in_world = 0
        self.settled = True
        self.warnings: list[str] = []

    def run(self, progress: Callable[[int, int], None] | None) -> None:
        s = self.scenario.settling
        world, tracker = self.world, self.tracker
        start = world.time_s
        pours = 0
        last_pour_s = 0.0
        while True:
            elapsed = world.time_s - start
            if pours < self.n_pours and elapsed >= pours * self.interval - 1e-9:
                pours += 1
                self._pour(pours, elapsed)
                last_pour_s = elapsed
                self._retire_behind(elapsed)
                if progress is not None:
                    progress(pours, self.n_pours)
            if pours == self.n_pours:
                if not tracker.moving():
                    break
                if elapsed - last_pour_s >= s.max_time_s:
                    self.settled = False
                    break
            world.step(self.check_steps)
            self.steps += self.check_steps
            moving = tracker.update(s.wake_speed_mm_s)
            # Out of the engine first: a chip that fell off or left must not be woken.
            self._drop_spilled()
            self._drop_left_domain()
            moving = [(chip, speed) for chip, speed in moving if chip in self.live]
            self.wakes += wake_near_movers(world, tracker, moving, set(), s, self.check_interval_s)
        if not self.settled:
            message = (
                f"the mat did not settle within {s.max_time_s:g} s of simulated time after "
                "the last pour; the chips still moving were frozen where they were"
            )
            log.warning(message)
            self.warnings.append(message)
        for chip in sorted(tracker.awake):
            world.freeze(chip)

    def _pour(self, pour: int, elapsed_s: float) -> None:
        """Release the next pour's chips over the zone where it now is (belt frame)."""
        world, scenario = self.world, self.scenario
        c, d = scenario.conveyor, scenario.deposition
        count = min(d.batch_size, d.chips - len(self.pour_of))
        shapes = draw_shapes(scenario, count, self.rng, self.cache)
        zone_x = zone_offset_mm(scenario, (pour - 1) % c.zones) - c.belt_speed_mm_s * elapsed_s
        live = sorted(self.live)
        positions, quaternions = world.poses_of(live)
        occupied = (positions, quaternions, [self.shapes_of[k] for k in live]) if live else None
        poses = release_poses(scenario, shapes, self.rng, occupied, zone_x)
        velocity = np.array([c.feed_speed_mm_s - c.belt_speed_mm_s, 0.0, 0.0])
        new = []
        for shape, p, q in zip(shapes, *poses, strict=True):
            chip = world.add_chip(shape, p, q)
            world.set_velocity(chip, velocity, np.zeros(3))
            new.append(chip)
            self.chip_length_mm = max(self.chip_length_mm, 2 * shape.circumradius_mm)
        self.shapes_of += shapes
        self.pour_of += [pour] * count
        self.zone_x.append(zone_x)
        self.live.update(new)
        self.most_in_world = max(self.most_in_world, len(self.live))
        self.tracker.add(new)

    def _retire_behind(self, elapsed_s: float) -> None:
        """Take out of the engine the frozen chips far enough downstream of the zone and
        of every moving chip that nothing can reach them any more."""
        if not self.scenario.settling.freeze:
            return  # the dynamic reference keeps every chip in the engine
        c = self.scenario.conveyor
        # Downstream of the last zone the belt passes under.
        line = zone_offset_mm(self.scenario, c.zones - 1) - c.belt_speed_mm_s * elapsed_s
        line += c.zone_length_mm / 2
        # Chips land downstream of where they are released when fed faster than the belt.
        line += max(0.0, landing_offset_mm(self.scenario))
        line += c.active_lengths * self.chip_length_mm
        tracker = self.tracker
        if tracker.positions and tracker.awake:
            movers = [tracker.positions[k][0] for k in tracker.awake if k in tracker.positions]
            if movers:
                line = max(line, max(movers) + _CLEAR_OF_MOVERS_LENGTHS * self.chip_length_mm)
        resting = sorted(self.live.difference(tracker.awake))
        if not resting:
            return
        positions = self.world.poses_of(resting)[0]
        for chip in np.asarray(resting)[positions[:, 0] > line]:
            self.world.retire(int(chip))
            self.live.discard(int(chip))

    def _drop_spilled(self) -> None:
        """Moving chips whose centre went past an edge of the belt fell off it."""
        half = self.scenario.conveyor.belt_width_mm / 2
        tracker = self.tracker
        for chip in [k for k in sorted(tracker.awake) if k in tracker.positions]:
            if abs(tracker.positions[chip][1]) > half:
                tracker.remove(chip)
                self._take_out(chip, SPILLED)

    def _drop_left_domain(self) -> None:
        for chip in self.tracker.left_domain:
            if chip in self.live:
                self._take_out(chip, LEFT_DOMAIN)

    def _take_out(self, chip: int, status: int) -> None:
        if chip in self.tracker.awake:
            self.tracker.remove(chip)
        self.world.retire(chip)
        self.live.discard(chip)
        self.status[chip] = status

    def record(self, wall_time_s: float) -> MatRecord:
        scenario = self.scenario
        positions, quaternions = self.world.poses()
        status = np.zeros(len(self.shapes_of), dtype=np.int8)
        for chip, value in self.status.items():
            status[chip] = value
        if self.tracker.left_domain:
            message = (
                f"{len(self.tracker.left_domain)} chips left the domain (through the belt, or "
                "flung far away); they are recorded with status 'left the domain'"
            )
            log.warning(message)
            self.warnings.append(message)
        shapes, shape_index = shape_table(self.shapes_of)
        low, high = steady_range_mm(scenario)
        return MatRecord(
            shapes=shapes,
            shape_index=shape_index,
            pour=np.array(self.pour_of, dtype=np.int64),
            positions=positions,
            quaternions=quaternions,
            status=status,
            zone_x_mm=np.array(self.zone_x),
            steady_mm=(float(low), float(high)),
            panel_centre_mm=(float((low + high) / 2), 0.0),
            belt_width_mm=scenario.conveyor.belt_width_mm,
            masses_g=np.array([self.world.mass_g(k) for k in range(len(self.shapes_of))]),
            sim_time_s=self.world.time_s,
            wall_time_s=wall_time_s,
            steps=self.steps,
            wakes=self.wakes,
            settled=self.settled,
            most_in_world=self.most_in_world,
            warnings=tuple(self.warnings),
        )


def panel_members(scenario: Scenario, mat: MatRecord) -> np.ndarray:
    """Indices of the chips on the belt that reach into the panel (a square of side
    ``deposition.target_size_mm`` centred on ``mat.panel_centre_mm``): every chip whose
    centre lies within its circumradius of the square, so the material inside the
    square is complete. At belt speed 0, every chip on the belt."""
    if scenario.conveyor.belt_speed_mm_s == 0:
        # A belt at rest makes a pile, not a mat: the stack is the whole pile, and the
        # panel's square is the target its descriptors are taken over, as in a stack.
        return np.flatnonzero(mat.status == ON_BELT)
    half = scenario.deposition.target_size_mm / 2
    radius = np.array([mat.shapes[k].circumradius_mm for k in mat.shape_index])
    offset = np.abs(mat.positions[:, :2] - np.asarray(mat.panel_centre_mm))
    near = (offset <= half + radius[:, None]).all(axis=1)
    return np.flatnonzero(near & (mat.status == ON_BELT))


def cut_panel(scenario: Scenario, mat: MatRecord) -> Stack:
    """The panel as a stack centred on (0, 0): its chips, their contacts and
    penetrations read in a world that holds them (frozen) and nothing else."""
    members = panel_members(scenario, mat)
    shift = np.array([*mat.panel_centre_mm, 0.0])
    shapes_of = [mat.shapes[k] for k in mat.shape_index[members]]
    preset = PRESETS.get(scenario.physics.preset, key="physics.preset")
    with ChipWorld(preset, scenario.physics) as world:
        for shape, p, q in zip(
            shapes_of, mat.positions[members] - shift, mat.quaternions[members], strict=True
        ):
            world.freeze(world.add_chip(shape, p, q))
        world.time_s = mat.sim_time_s
        result = _batch_result(
            world, scenario, shapes_of, 1, 0.0, mat.steps, mat.wakes, mat.settled, mat.wall_time_s
        )
    shapes, shape_index = shape_table(shapes_of)
    return Stack(
        shapes=shapes,
        shape_index=shape_index,
        batch=np.ones(len(members), dtype=int),
        batches=(result,),
        target_size_mm=scenario.deposition.target_size_mm,
        warnings=mat.warnings,
    )


def pour(inputs: StageInputs, stage_name: str) -> ConveyorResult:
    """The conveyor's mat poured for ``inputs.scenario``, reporting each pour."""
    report = inputs.options.progress

    def progress(done: int, pours: int) -> None:
        if report is not None:
            report(stage_name, done, pours, {})

    if report is not None:
        report(stage_name, 0, pour_timing(inputs.scenario)[0], {})
    return pour_mat(inputs.scenario, progress)
