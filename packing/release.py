"""Releasing a batch: the chips' shapes drawn for a scenario (one, a mix, or sizes that
vary per chip), their rotations, and release poses that overlap neither one another nor
the pile; the table of distinct shapes a stack records."""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial.transform import Rotation

from chipstack.core.errors import InputError
from chipstack.core.overlap import box_penetration_depth
from chipstack.core.schema import Scenario
from chipstack.packing.shapes import ChipShape, make_shape, varies_per_chip

__all__ = ["draw_shapes", "release_poses", "shape_table"]

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
