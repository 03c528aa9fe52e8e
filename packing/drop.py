"""The single-chip drop experiment (paper, section 4.2): one chip released many times.

Every drop starts from the same place, ``drop.height_mm`` above (0, 0), with the chip's
sides along x and y turned by ``drop.yaw_deg`` about z, and tilted about x and about y by
angles drawn uniform in [-tilt, tilt]: without that freedom every simulated chip would land
flat and stay at (0, 0). Each drop runs in a fresh world on an empty target, until the
chip has settled by the scenario's settling rule.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from chipstack.core.chipshape import ChipShape
from chipstack.core.errors import SimulationError
from chipstack.core.schema import Scenario
from chipstack.packing.effects import apply_effect_loads, release_spin, setup_effects, shaped
from chipstack.packing.presets import PRESETS
from chipstack.packing.release import draw_shapes
from chipstack.packing.settling import CHECK_INTERVAL_S, RestTracker, settle
from chipstack.packing.world import ChipWorld

__all__ = [
    "DropProtocol",
    "DropResult",
    "DropSample",
    "drop_chips",
    "release_places",
    "simulate_drops",
]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DropResult:
    """Final poses of every drop.

    shapes: the chip shape of each drop; positions (N, 3) mm; quaternions (N, 4) x, y, z,
    w; tilts_rad (N, 2) the release tilts about x and y; settled (N,) bool; sim_time_s (N,)
    simulated time to settle; wall_time_s the whole experiment.
    """

    shapes: tuple[ChipShape, ...]
    positions: np.ndarray
    quaternions: np.ndarray
    tilts_rad: np.ndarray
    settled: np.ndarray
    sim_time_s: np.ndarray
    wall_time_s: float
    warnings: tuple[str, ...] = ()

    @property
    def n_drops(self) -> int:
        return len(self.positions)


def drop_chips(
    scenario: Scenario, progress: Callable[[int, int], None] | None = None
) -> DropResult:
    """Run ``drop.drops`` independent drops; ``progress(done, total)`` after each."""
    spec = scenario.drop
    preset = PRESETS.get(scenario.physics.preset, key="physics.preset")
    rng = np.random.default_rng(scenario.seed)
    tilt = np.radians(spec.tilt_deg)
    yaw = np.radians(spec.yaw_deg)
    cache: dict = {}
    shapes, positions, quaternions, tilts, settled, times = [], [], [], [], [], []
    start = time.perf_counter()
    for k in range(spec.drops):
        (shape,) = draw_shapes(scenario, 1, rng, cache)
        angles = rng.uniform(-tilt, tilt, size=2)
        rotation = Rotation.from_euler("xyz", [angles[0], angles[1], yaw])
        with ChipWorld(preset, scenario.physics) as world:
            chip = world.add_chip(shape, np.array([0.0, 0.0, spec.height_mm]), rotation.as_quat())
            done, _, _, t0 = settle(world, [chip], scenario)
            pose = world.poses()
            times.append(world.time_s - t0)
        shapes.append(shape)
        positions.append(pose[0][0])
        quaternions.append(pose[1][0])
        tilts.append(angles)
        settled.append(done)
        if progress is not None:
            progress(k + 1, spec.drops)
    warnings = []
    if not all(settled):
        message = (
            f"{spec.drops - sum(settled)} of {spec.drops} drops did not settle within "
            f"{scenario.settling.max_time_s:g} s of simulated time"
        )
        log.warning(message)
        warnings.append(message)
    return DropResult(
        shapes=tuple(shapes),
        positions=np.array(positions),
        quaternions=np.array(quaternions),
        tilts_rad=np.array(tilts),
        settled=np.array(settled),
        sim_time_s=np.array(times),
        wall_time_s=time.perf_counter() - start,
        warnings=tuple(warnings),
    )


# Below this speed air loads are under 0.05 % of a chip's weight: stop stepping one by one.
_FLIGHT_SPEED_MM_S = 100.0
# Distance between neighbouring release points, in circumradii: a tilted chip's bounding
# box is at most two circumradii wide, so released chips never share the broad phase.
RELEASE_SPACING = 3.0


def release_places(n: int, spacing_mm: float) -> np.ndarray:
    """The release points (n, 2) mm of ``n`` drops sharing one world: a square spiral
    from the origin, ``spacing_mm`` apart, drop k's place depending on k alone (so that a
    drop lands where it lands whatever number of drops is simulated with it)."""
    places = np.zeros((n, 2))
    x = y = 0
    dx, dy = 1, 0
    leg, walked, turns = 1, 0, 0
    for k in range(1, n):
        x, y = x + dx, y + dy
        places[k] = x, y
        walked += 1
        if walked == leg:
            walked, turns = 0, turns + 1
            dx, dy = -dy, dx
            if turns % 2 == 0:
                leg += 1
    return places * spacing_mm


@dataclass(frozen=True)
class DropProtocol:
    """How one experimental condition releases the chip: centre ``height_mm`` above
    (0, 0), sides turned ``yaw_deg`` about z, tilts about x and y uniform in
    [-tilt_deg, tilt_deg]."""

    height_mm: float = 200.0
    yaw_deg: float = 0.0
    tilt_deg: float = 5.7296


@dataclass(frozen=True)
class DropSample:
    """Where the drops of one condition came to rest.

    positions (n, 2) mm from the release point; yaw_deg (n,) final in-plane turn of the
    chip's local x axis (deg, in (-180, 180]); tilt_deg (n,) final angle between the
    chip's normal and the vertical, folded to [0, 90]; settled (n,) bool.
    """

    positions: np.ndarray
    yaw_deg: np.ndarray
    tilt_deg: np.ndarray
    settled: np.ndarray


def final_angles(quaternions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Yaw of the local x axis and tilt of the normal (deg) of rest orientations."""
    matrices = Rotation.from_quat(quaternions).as_matrix()
    yaw = np.degrees(np.arctan2(matrices[:, 1, 0], matrices[:, 0, 0]))
    tilt = np.degrees(np.arccos(np.clip(np.abs(matrices[:, 2, 2]), 0.0, 1.0)))
    return yaw, tilt


def simulate_drops(
    scenario: Scenario,
    protocol: DropProtocol,
    n: int,
    strengths: dict[str, float] | None = None,
    seed: int = 0,
) -> DropSample:
    """``n`` drops of the scenario's chip under ``protocol`` with effects switched on.

    The drops share one world and touch only the floor, so they cost one world, not n;
    each falls at its own release point (``release_places``; positions are reported from
    it) and is independent of the others given the parameters: drop k's random draws (tilt
    fractions, spin directions) come from its own stream (``seed`` and k), and the air's
    loads act on each drop until that drop has landed, whatever the others do. The draws
    depend on ``seed`` alone, not on the strengths, the tilt range or ``n``: two calls
    that differ in a strength differ only by the effect (common random numbers, which
    make the fit of a strength smooth).
    """
    strengths = dict(strengths or {})
    preset = PRESETS.get(scenario.physics.preset, key="physics.preset")
    streams = [np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(n)]
    fractions = np.array([r.uniform(-1.0, 1.0, size=2) for r in streams]).reshape(n, 2)
    spin_draws = np.array([r.normal(size=3) for r in streams]).reshape(n, 3)
    (shape,) = draw_shapes(scenario, 1, np.random.default_rng(scenario.seed))
    shape = shaped(shape, strengths)
    setup = setup_effects(preset, scenario.physics, strengths)
    physics, per_step = setup.physics, list(setup.per_step)
    spin = release_spin(strengths, spin_draws)
    tilt = np.radians(protocol.tilt_deg) * fractions
    yaw = np.radians(protocol.yaw_deg)
    rotations = Rotation.from_euler("xyz", np.column_stack([tilt, np.full(n, yaw)])).as_quat()
    s = scenario.settling
    check_steps = max(1, round(CHECK_INTERVAL_S / physics.time_step_s))
    hold_checks = max(1, int(np.ceil(s.hold_time_s / (check_steps * physics.time_step_s))))
    # Each drop falls at its own place: drops released at one point overlap in Bullet's
    # broad phase, which then tests every pair before the collision filter discards it
    # (a cost growing as n^2: 60 drops from 1 m took 0.47 s together, 0.35 s spread out,
    # 120 drops 1.39 s against 0.60 s). Positions are reported from each drop's own
    # release point.
    places = release_places(n, RELEASE_SPACING * shape.circumradius_mm)
    with ChipWorld(preset, physics, isolated=True) as world:
        chips = [
            world.add_chip(shape, np.array([*places[k], protocol.height_mm]), rotations[k])
            for k in range(n)
        ]
        floor = setup.contact
        world.set_floor_compliance(
            floor.floor_compliance_mm_n, floor.floor_damping_ratio, world.mass_g(chips[0])
        )
        for k in range(n):
            if spin[k].any():
                world.set_velocity(chips[k], np.zeros(3), spin[k])
        tracker = RestTracker(world, s.speed_mm_s * s.hold_time_s, hold_checks)
        tracker.add(chips)
        start = world.time_s
        in_flight = list(chips) if per_step else []
        while tracker.awake and world.time_s - start < s.max_time_s:
            in_flight = [c for c in in_flight if c in tracker.awake]
            if in_flight:
                for _ in range(check_steps):
                    apply_effect_loads(world, in_flight, per_step)
                    world.step()
                # Each drop on its own: under the air's loads while still in the air (above
                # the height where it could touch the floor) or fast.
                pos, _, vel, _ = world.kinematics(in_flight)
                airborne = pos[:, 2] > shape.circumradius_mm + 1.0
                fast = np.linalg.norm(vel, axis=1) > _FLIGHT_SPEED_MM_S
                in_flight = [c for c, keep in zip(in_flight, airborne | fast, strict=True) if keep]
            else:
                world.step(check_steps)
            tracker.update(np.inf)
        settled = np.ones(n, dtype=bool)
        settled[sorted(tracker.awake)] = False
        positions, quaternions = world.poses()
    if not np.isfinite(positions).all():
        raise SimulationError("a drop ended with a NaN position")
    yaw_deg, tilt_deg = final_angles(quaternions)
    return DropSample(
        positions=positions[:, :2] - places,
        yaw_deg=yaw_deg,
        tilt_deg=tilt_deg,
        settled=settled,
    )
