"""The geometry stage's input: where every chip is (no physics, no files)."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy.spatial.transform import Rotation

from chipstack.core.chipshape import ChipShape
from chipstack.core.errors import InputError

__all__ = ["Arrangement", "arrangements_from_stack", "stack_history", "MAX_COORDINATE_MM"]

MAX_COORDINATE_MM = 1e6  # 1 km: beyond any conveyor, and well inside float arithmetic


@dataclass(frozen=True, eq=False)
class Arrangement:
    """Chips at rest: shapes and poses, in millimetres, target centred on (0, 0), z up.

    Attributes
    ----------
    shapes: the distinct chip shapes.
    shape_index: (n,) int, index into ``shapes`` of each chip.
    positions: (n, 3) mm, centres of mass.
    quaternions: (n, 4) unit quaternions x, y, z, w (chip frame to world frame).
    batch: (n,) int, 1-based batch in which each chip was deposited.
    target_size_mm: side of the square deposition target.

    The arrays are copied and made read-only on construction, so nothing downstream can
    change a caller's data.
    """

    shapes: tuple[ChipShape, ...]
    shape_index: np.ndarray
    positions: np.ndarray
    quaternions: np.ndarray
    batch: np.ndarray
    target_size_mm: float

    def __post_init__(self) -> None:
        n = len(self.positions)
        arrays = {
            "shape_index": np.array(self.shape_index, dtype=np.int64).reshape(-1),
            "positions": np.array(self.positions, dtype=float).reshape(-1, 3),
            "quaternions": np.array(self.quaternions, dtype=float).reshape(-1, 4),
            "batch": np.array(self.batch, dtype=np.int64).reshape(-1),
        }
        for name, array in arrays.items():
            if len(array) != n:
                raise InputError(f"{name}: {len(array)} rows for {n} chips")
            if not np.isfinite(array).all():
                raise InputError(f"{name}: holds NaN or infinite values")
            array.setflags(write=False)
            object.__setattr__(self, name, array)
        if n and not (
            0 <= arrays["shape_index"].min() and arrays["shape_index"].max() < len(self.shapes)
        ):
            raise InputError(f"shape_index: must index the {len(self.shapes)} shapes")
        if n and np.abs(arrays["positions"]).max() > MAX_COORDINATE_MM:
            raise InputError(f"positions: beyond {MAX_COORDINATE_MM:g} mm from the target centre")
        norms = np.linalg.norm(arrays["quaternions"], axis=1)
        if n and np.abs(norms - 1).max() > 1e-4:
            raise InputError("quaternions: must be unit quaternions (x, y, z, w)")
        if not (np.isfinite(self.target_size_mm) and self.target_size_mm > 0):
            raise InputError(f"target_size_mm: must be positive, got {self.target_size_mm!r}")

    @property
    def n_chips(self) -> int:
        return len(self.positions)

    @property
    def thinnest_mm(self) -> float:
        """The thinnest dimension of any chip shape (mm): twice its smallest half extent
        (1 mm for no shape at all)."""
        return min((2 * float(min(s.half_extents)) for s in self.shapes), default=1.0)

    @cached_property
    def rotations(self) -> np.ndarray:
        """(n, 3, 3) rotation matrices; column k is the chip's local axis k in the world."""
        if not self.n_chips:
            return np.empty((0, 3, 3))
        matrices = Rotation.from_quat(self.quaternions).as_matrix()
        matrices.setflags(write=False)
        return matrices

    @cached_property
    def bounds(self) -> np.ndarray:
        """(n, 2, 3) mm, axis-aligned bounding box (low, high corners) of every chip."""
        out = np.empty((self.n_chips, 2, 3))
        for k, shape in enumerate(self.shapes):
            mine = np.flatnonzero(self.shape_index == k)
            if not len(mine):
                continue
            corners = np.einsum("vj,nij->nvi", shape.vertices, self.rotations[mine])
            corners += self.positions[mine, None, :]
            out[mine, 0] = corners.min(axis=1)
            out[mine, 1] = corners.max(axis=1)
        out.setflags(write=False)
        return out

    def bottom_up_order(self) -> np.ndarray:
        """(n,) chip indices from the bottom up: by the height of the lowest point, then index.

        The rule for overlaps the physics left: the lower chip, the one that came to rest
        first, keeps the shared material (voxel image, voxel and conformal meshes).
        """
        return np.lexsort((np.arange(self.n_chips), self.bounds[:, 0, 2]))

    def bottom_up_rank(self) -> np.ndarray:
        """(n,) each chip's place in :meth:`bottom_up_order` (0: the lowest)."""
        rank = np.empty(self.n_chips, dtype=np.int64)
        rank[self.bottom_up_order()] = np.arange(self.n_chips)
        return rank

    def inside_target(self) -> np.ndarray:
        """(n,) bool: the chip's centre of mass lies over the target square."""
        return (np.abs(self.positions[:, :2]) <= self.target_size_mm / 2).all(axis=1)


def stack_history(stack) -> list[Arrangement]:
    """:func:`arrangements_from_stack`, built once per stack object and kept on it (every
    stage of a run that reads the stack shares it; it goes when the stack goes)."""
    history = stack.__dict__.get("_history")
    if history is None:
        history = arrangements_from_stack(stack)
        object.__setattr__(stack, "_history", history)  # a cache, not a field
    return history


def arrangements_from_stack(stack) -> list[Arrangement]:
    """One :class:`Arrangement` per deposited batch of a :class:`packing.Stack` (NBD 1, 2, ...)."""
    out = []
    for result in stack.batches:
        n = len(result.positions)
        out.append(
            Arrangement(
                stack.shapes,
                stack.shape_index[:n],
                result.positions,
                result.quaternions,
                stack.batch[:n],
                stack.target_size_mm,
            )
        )
    return out
