"""The packing stage's result: a settled stack and its history batch by batch."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from chipstack.core.chipshape import ChipShape

__all__ = ["BatchResult", "Stack"]


@dataclass(frozen=True)
class ContactRecord:
    """Closest-point contacts between chips (and the ground, index ``GROUND``).

    Arrays of length m: chip_a, chip_b (chip indices; chip_b is GROUND for the floor),
    point_a, point_b (m, 3) mm on each surface, normal (m, 3) unit vector on b pointing
    towards a, distance (m,) mm (negative: interpenetration).
    """

    chip_a: np.ndarray
    chip_b: np.ndarray
    point_a: np.ndarray
    point_b: np.ndarray
    normal: np.ndarray
    distance: np.ndarray

    def __len__(self) -> int:
        return len(self.chip_a)


@dataclass(frozen=True)
class BatchResult:
    """The state after one batch has settled (or hit its time cap).

    positions (n, 3) mm and quaternions (n, 4) x, y, z, w cover every chip deposited so far
    (n grows batch by batch). Times: ``sim_time_s`` simulated, ``wall_time_s`` spent.
    """

    batch: int  # 1-based, the paper's NBD
    positions: np.ndarray
    quaternions: np.ndarray
    contacts: ContactRecord
    sim_time_s: float
    wall_time_s: float
    steps: int
    settled: bool
    wakes: int
    max_floor_penetration_mm: float
    max_chip_penetration_mm: float
    outside_target: int


@dataclass(frozen=True)
class Stack:
    """A deposited stack: every chip's shape, batch and final pose, plus each batch's state."""

    shapes: tuple[ChipShape, ...]  # distinct shapes
    shape_index: np.ndarray  # (n,) index into ``shapes``
    batch: np.ndarray  # (n,) 1-based batch of each chip
    batches: tuple[BatchResult, ...]
    target_size_mm: float
    warnings: tuple[str, ...] = field(default=())

    @property
    def n_chips(self) -> int:
        return len(self.batch)

    @property
    def positions(self) -> np.ndarray:
        return self.batches[-1].positions

    @property
    def quaternions(self) -> np.ndarray:
        return self.batches[-1].quaternions

    def inside_target(self) -> np.ndarray:
        """Boolean (n,): the chip's centre of mass lies over the square target."""
        half = self.target_size_mm / 2
        return (np.abs(self.positions[:, :2]) <= half).all(axis=1)
