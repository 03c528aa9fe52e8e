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

from packing.config import Scenario
from packing.deposition import draw_shapes, settle
from packing.presets import PRESETS
from packing.shapes import ChipShape
from packing.world import ChipWorld

__all__ = ["DropResult", "drop_chips"]

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
