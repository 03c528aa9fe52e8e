"""A plugin package outside the project: a chip shape, a descriptor, a mesh kind and an
effect, declared only in its own entry points (``chipstack_testplugin-0.1.dist-info``).
``tests/test_plugins.py`` puts this folder on the path of a CLI run and checks that each
works end to end."""

from __future__ import annotations

import numpy as np

from geometry.describe import Descriptor
from meshing.kinds import VoxelKind
from packing.effects import Effect
from packing.shapes import ShapeKind, prism_shape


def _triangle(spec, rng=None, size=1.0):
    """An equilateral triangle of side ``length_mm``, extruded through the thickness."""
    side = spec.length_mm * size
    radius = side / np.sqrt(3)
    angles = np.radians([90.0, 210.0, 330.0])
    outline = np.column_stack([radius * np.cos(angles), radius * np.sin(angles)])
    return prism_shape(
        f"triangle {side:g}x{spec.thickness_mm:g}", "triangle", outline, spec.thickness_mm, spec
    )


def _triangle_check(spec, key):
    from core.errors import InputError

    if spec.thickness_mm >= spec.length_mm:
        raise InputError(f"{key}.thickness_mm: a triangle must be thinner than it is across")


TRIANGLE = ShapeKind(_triangle, _triangle_check, lambda s: (s.length_mm, s.length_mm / np.sqrt(3)))


def _centre_heights(ctx):
    z = np.asarray(ctx.final.positions)[:, 2]
    return z, {"mean_mm": round(float(z.mean()), 6), "max_mm": round(float(z.max()), 6)}


CENTRE_HEIGHT = Descriptor(
    "centre_height", "height of the chips' centres of mass above the conveyor (mm)", _centre_heights
)


class CoarseVoxel(VoxelKind):
    """The voxel mesh under another name (a mesh kind the project does not have)."""

    name = "coarse_voxel"
    doc = "hexahedra of the voxel image, from a plugin"


COARSE_VOXEL = CoarseVoxel()


class Crosswind(Effect):
    """A steady wind along +x acting on flying chips: a force of mass x strength."""

    name = "crosswind"
    parameter = "acceleration of the wind's push along x"
    unit = "mm/s^2"
    prior = (0.0, 2000.0)
    kinds = ("drop",)
    justification = "a draught in the lab (a plugin's effect)"

    def acts_per_step(self):
        return True

    def loads(self, state, strength):
        forces = np.zeros((len(state.masses_g), 3))
        forces[:, 0] = state.masses_g * strength
        return forces, np.zeros_like(forces)


CROSSWIND = Crosswind()
