"""A plugin package outside the project: a chip shape, a descriptor, a mesh kind, an
effect, a scenario kind (with its table and deposition site), a stack writer and a
figure, declared only in its own entry points (``chipstack_testplugin-0.1.dist-info``).
``tests/test_plugins.py`` puts this folder on the path of a CLI run and checks that each
works end to end."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from chipstack.core.schema import Section, between, key
from chipstack.export.figure_kinds import FigureKind
from chipstack.geometry.describe import Descriptor
from chipstack.meshing.kinds import VoxelKind
from chipstack.packing.effects import Effect
from chipstack.packing.files import StackWriter
from chipstack.packing.kinds import StackKind
from chipstack.packing.shapes import ShapeKind, prism_shape
from chipstack.packing.sites import SquareTarget


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
    from chipstack.core.errors import InputError

    if spec.thickness_mm >= spec.length_mm:
        raise InputError(f"{key}.thickness_mm: a triangle must be thinner than it is across")


TRIANGLE = ShapeKind(_triangle, _triangle_check, lambda s: (s.length_mm, s.length_mm / np.sqrt(3)))


def _centre_heights(ctx):
    z = np.asarray(ctx.final.positions)[:, 2]
    return z, {"mean_mm": round(float(z.mean()), 6), "max_mm": round(float(z.max()), 6)}


CENTRE_HEIGHT = Descriptor(
    "centre_height",
    "height of the chips' centres of mass above the conveyor (mm)",
    _centre_heights,
    chip_columns=lambda z: {"centre_height_mm": [f"{v:.6f}" for v in z]},
    headline=lambda section: f"centres up to {section['max_mm']:.1f} mm",
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


@dataclass(frozen=True)
class RingSpec(Section):
    """The round target of the plugin's ``ring`` kind."""

    table: ClassVar[str] = "ring"
    kinds: ClassVar[tuple[str, ...]] = ("ring",)

    radius_mm: float = key(
        30.0, "mm", "radius of the disc the chips are released over", between(1.0, 1000.0)
    )
    centre_x_mm: float = key(0.0, "mm", "where the disc's centre lies along x", between(-500, 500))


class Ring(StackKind):
    """Batch deposition over a disc (a scenario kind from a plugin)."""

    name = "ring"
    sections = (RingSpec,)


class RingSite(SquareTarget):
    """Chips released over the disc of ``[ring]`` (a deposition site from a plugin)."""

    def release_point(self, scenario, clearance_mm, rng, zone_x_mm):
        radius = scenario.ring.radius_mm * np.sqrt(rng.uniform())
        angle = rng.uniform(0, 2 * np.pi)
        height = max(rng.uniform(*scenario.deposition.release_height_mm), clearance_mm)
        centre = scenario.ring.centre_x_mm
        return np.array([centre + radius * np.cos(angle), radius * np.sin(angle), height])

    def no_room(self, scenario, n):
        from chipstack.core.errors import InputError

        return InputError(f"ring.radius_mm: cannot release {n} chips over the disc")


RING = Ring()
RING_SITE = RingSite()


def _write_centres(folder, stack):
    """The chips' centres after the last batch as an XYZ point cloud (mm)."""
    last = stack.batches[-1]
    rows = [f"{x:.6f} {y:.6f} {z:.6f}" for x, y, z in np.asarray(last.positions)]
    (folder / "centres.xyz").write_text("\n".join(rows) + "\n")
    return ["centres.xyz"]


CENTRES = StackWriter(
    "centres", "centres.xyz", "the chips' centres as a point cloud, from a plugin", _write_centres
)


def _draw_top_view(folder, arrangement):
    """The chips' centres seen from above, coloured by height (mm)."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot

    xyz = np.asarray(arrangement.positions)
    figure, ax = pyplot.subplots(figsize=(4, 4))
    ax.scatter(xyz[:, 0], xyz[:, 1], c=xyz[:, 2])
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    figure.savefig(folder / "centres_top.png", dpi=60)
    pyplot.close(figure)
    return ["centres_top.png"]


TOP_VIEW = FigureKind(
    "top_view",
    "stack",
    "centres_top.png",
    "the chips' centres from above, from a plugin",
    _draw_top_view,
)
