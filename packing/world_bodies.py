"""The chips of a :class:`packing.world.ChipWorld` as engine bodies: their collision
shapes (made once per chip shape) and the register of chip index, body id, mass and
shape that the other parts of the world read."""

from __future__ import annotations

import os
import tempfile

import numpy as np
from scipy.spatial import ConvexHull

from chipstack.core.chipshape import ChipShape
from chipstack.core.errors import SimulationError
from chipstack.packing.bullet import pybullet
from chipstack.packing.world_engine import MM_PER_UNIT, EngineSession

__all__ = ["CollisionShapes", "ChipBodies", "RETIRED"]

RETIRED = -2  # the body id of a chip removed from the engine (no body has a negative id)


class CollisionShapes:
    """PyBullet collision shapes of chip shapes, each made once and reused."""

    def __init__(self, session: EngineSession) -> None:
        self._session = session
        self._ids: dict[int, tuple[int, ChipShape]] = {}
        self._scratch: tempfile.TemporaryDirectory | None = None

    def of(self, shape: ChipShape) -> int:
        """The collision shape id of ``shape`` (made on first use)."""
        key = id(shape)
        if key in self._ids:
            return self._ids[key][0]
        c = self._session.client
        if shape.collision == "box":
            sid = _box(shape, c)
        elif shape.collision == "cylinder":
            sid = _cylinder(shape, c)
        elif len(shape.convex_pieces) == 1:
            sid = pybullet.createCollisionShape(
                pybullet.GEOM_MESH,
                vertices=(shape.convex_pieces[0] / MM_PER_UNIT).tolist(),
                physicsClientId=c,
            )
        else:
            sid = self._compound(shape, c)
        if sid < 0:
            raise SimulationError(f"shape {shape.name!r}: PyBullet refused its collision shape")
        self._ids[key] = (sid, shape)  # the shape is kept alive, so its id stays unique
        return sid

    def _compound(self, shape: ChipShape, client: int) -> int:
        # PyBullet builds one hull per object of an OBJ file (its API takes no vertex lists
        # for compounds), so the pieces go through a scratch file.
        if self._scratch is None:
            self._scratch = tempfile.TemporaryDirectory(prefix="chipstack-shapes-")
        path = os.path.join(self._scratch.name, f"shape{len(self._ids)}.obj")
        lines = _obj_lines(shape.convex_pieces)
        with open(path, "w") as f:
            f.write("\n".join(lines) + "\n")
        return pybullet.createCollisionShape(
            pybullet.GEOM_MESH, fileName=path, physicsClientId=client
        )

    def close(self) -> None:
        """Remove the scratch files (the engine has read them)."""
        if self._scratch is not None:
            self._scratch.cleanup()
            self._scratch = None


def _box(shape: ChipShape, client: int) -> int:
    return pybullet.createCollisionShape(
        pybullet.GEOM_BOX,
        halfExtents=(shape.half_extents / MM_PER_UNIT).tolist(),
        collisionFramePosition=(shape.box_centre / MM_PER_UNIT).tolist(),
        physicsClientId=client,
    )


def _cylinder(shape: ChipShape, client: int) -> int:
    # PyBullet's cylinder runs along z; the fibre's axis is local x.
    return pybullet.createCollisionShape(
        pybullet.GEOM_CYLINDER,
        radius=shape.radius_mm / MM_PER_UNIT,
        height=2 * float(shape.half_extents[0]) / MM_PER_UNIT,
        collisionFrameOrientation=[0.0, np.sqrt(0.5), 0.0, np.sqrt(0.5)],
        physicsClientId=client,
    )


def _obj_lines(pieces: tuple[np.ndarray, ...]) -> list[str]:
    """An OBJ file, in engine units, with one object per convex piece."""
    lines, offset = [], 0
    for k, piece in enumerate(pieces):
        # Faces matter: PyBullet hulls only the vertices that faces use.
        hull = ConvexHull(piece)
        lines.append(f"o piece{k}")
        lines += [f"v {x:.17g} {y:.17g} {z:.17g}" for x, y, z in piece / MM_PER_UNIT]
        lines += [
            f"f {a + offset + 1} {b + offset + 1} {c + offset + 1}" for a, b, c in hull.simplices
        ]
        offset += len(piece)
    return lines


class ChipBodies:
    """The register of chips: chip index (0, 1, ... in order of addition) to body id and
    back, and each chip's mass, shape and reach, in engine units where the engine needs
    them."""

    def __init__(self) -> None:
        self.body_ids: list[int] = []  # chip index -> body id (RETIRED once removed)
        # Chips taken out of the engine for good: their last pose, position mm and
        # quaternion (see :meth:`retire`).
        self.retired: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._index_of: dict[int, int] = {}
        self.masses: list[float] = []
        self.shapes: list[ChipShape] = []
        self.radius_units: list[float] = []
        # Per chip: the largest distance of a vertex from each local axis.
        self.axis_reach_units: list[np.ndarray] = []

    def __len__(self) -> int:
        return len(self.body_ids)

    def register(self, body: int, mass: float, shape: ChipShape) -> int:
        """Record a new chip's body; returns its chip index."""
        index = len(self.body_ids)
        self.body_ids.append(body)
        self._index_of[body] = index
        self.masses.append(mass)
        self.shapes.append(shape)
        self.radius_units.append(shape.circumradius_mm / MM_PER_UNIT)
        v = shape.vertices
        self.axis_reach_units.append(
            np.array([np.hypot(v[:, (a + 1) % 3], v[:, (a + 2) % 3]).max() for a in range(3)])
            / MM_PER_UNIT
        )
        return index

    def retire(self, chip: int, position_mm: np.ndarray, quaternion: np.ndarray) -> int:
        """Unregister a chip's body (the caller removes it from the engine), keeping its
        final pose; returns the body id it had."""
        body = self.body_ids[chip]
        del self._index_of[body]
        self.body_ids[chip] = RETIRED
        self.retired[chip] = (np.asarray(position_mm, float), np.asarray(quaternion, float))
        return body

    def is_chip(self, body: int) -> bool:
        return body in self._index_of

    def chip_of(self, body: int, default: int) -> int:
        """The chip index of ``body``, or ``default`` for a body that is no chip."""
        return self._index_of.get(body, default)

    @property
    def index_of(self) -> dict[int, int]:
        """Body id -> chip index (read only)."""
        return self._index_of

    def inertia(self, chip: int) -> list[float]:
        """The exact principal inertia of a chip, engine units."""
        shape = self.shapes[chip]
        return (self.masses[chip] * shape.inertia_mm2 / MM_PER_UNIT**2).tolist()

    def circumradius_mm(self, chips: list[int]) -> np.ndarray:
        return np.array([self.radius_units[i] for i in chips]) * MM_PER_UNIT
