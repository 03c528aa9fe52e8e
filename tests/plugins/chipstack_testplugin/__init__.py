"""A plugin package outside the project: a chip shape and a mesh kind with keys of their
own, a descriptor, an effect, a scenario kind (with its table and deposition site), a
stack writer and a figure, declared only in its own entry points
(``chipstack_testplugin-0.1.dist-info``). ``tests/test_plugins.py`` puts this folder on
the path of a CLI run and checks that each works end to end."""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from chipstack.core.errors import InputError
from chipstack.core.keys import between, key, length
from chipstack.core.schema import Parameters, Section
from chipstack.export.figure_kinds import FigureKind
from chipstack.geometry.descriptors.base import Descriptor
from chipstack.meshing.checks import check_volume
from chipstack.meshing.kinds import Built, MeshKind
from chipstack.packing.effects import Effect
from chipstack.packing.files import StackWriter
from chipstack.packing.kinds import StackKind
from chipstack.packing.shapes import ShapeKind, prism_shape
from chipstack.packing.sites import SquareTarget


@dataclass(frozen=True)
class TriangleKeys(Parameters):
    """The triangle's keys: two of the built-in shapes' names and one of its own."""

    length_mm: float = key(20.0, "mm", "base (local x)", length)
    thickness_mm: float = key(2.0, "mm", "thickness (local z)", length)
    apex_angle_deg: float = key(
        60.0, "deg", "angle between the two equal sides (60: equilateral)", between(20.0, 150.0)
    )


def _corners(spec, size=1.0):
    """(3, 2) mm: the base along x, the apex on +y."""
    base = spec.length_mm * size
    height = base / 2 / np.tan(np.radians(spec.apex_angle_deg) / 2)
    return np.array([[-base / 2, 0.0], [base / 2, 0.0], [0.0, height]])


def _triangle(spec, rng=None, size=1.0):
    """An isosceles triangle: base ``length_mm``, ``apex_angle_deg`` between its equal
    sides, extruded through the thickness."""
    outline = _corners(spec, size)
    outline -= outline.mean(axis=0)
    name = f"triangle {spec.length_mm * size:g}x{spec.apex_angle_deg:g}x{spec.thickness_mm:g}"
    return prism_shape(name, "triangle", outline, spec.thickness_mm, spec)


def _triangle_check(spec, key):
    corners = _corners(spec)
    if spec.thickness_mm >= np.ptp(corners[:, 1]):
        raise InputError(f"{key}.thickness_mm: a triangle must be thinner than it is tall")


def _triangle_extent(spec):
    corners = _corners(spec)
    sides = np.linalg.norm(corners - np.roll(corners, 1, axis=0), axis=1)
    radius = np.linalg.norm(corners - corners.mean(axis=0), axis=1).max()
    return float(sides.max()), float(np.hypot(radius, spec.thickness_mm / 2))


TRIANGLE = ShapeKind(_triangle, _triangle_check, _triangle_extent, parameters=TriangleKeys)


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


@dataclass(frozen=True)
class KuhnKeys(Parameters):
    """The Kuhn mesher's own keys."""

    cube_mm: float = key(
        1.0,
        "mm",
        "edge of the cubes of the labelled image, six tetrahedra each",
        between(0.1, 20.0),
    )
    min_quality: float = key(0.3, "", "smallest accepted element quality (SICN)", between(0.0, 1.0))


# A cube's corners in VTK hexahedron order split along its diagonal 0-6 into six
# tetrahedra, one per order of the three axes (Kuhn's split): every cube cut alike, so
# the faces of neighbouring cubes are cut alike and the tetrahedra conform.
_KUHN = np.array(
    [[0, 1, 2, 6], [0, 5, 1, 6], [0, 3, 7, 6], [0, 2, 3, 6], [0, 4, 5, 6], [0, 7, 4, 6]]
)


def _face_connected(labels: np.ndarray) -> np.ndarray:
    """The labelled image with each chip's cubes cut to its largest face-connected part:
    a sharp corner can leave a cube joined to its chip by an edge only, and tetrahedra
    meeting at an edge do not hold a chip together."""
    from scipy import ndimage

    kept = labels.copy()
    for index, box in enumerate(ndimage.find_objects(labels), start=1):
        if box is None:
            continue
        parts, count = ndimage.label(labels[box] == index)
        if count > 1:
            largest = 1 + int(np.argmax(np.bincount(parts.ravel())[1:]))
            kept[box][(parts > 0) & (parts != largest)] = 0
    return kept


class KuhnTetrahedra(MeshKind):
    """The chips' cubes of the labelled image, each split into six tetrahedra (a mesh kind
    the project does not have: tetrahedra on a grid, no pore space)."""

    name = "kuhn"
    doc = "six tetrahedra to each cube of the chips' voxel image, from a plugin"
    parameters = KuhnKeys
    version = 1

    def build(self, arrangement, scenario, scratch):
        from chipstack.geometry.voxels import voxelize
        from chipstack.meshing.boundaries import side_node_sets
        from chipstack.meshing.image import tetra_sicn
        from chipstack.meshing.mesh import VolumeMesh, element_attributes

        spec = scenario.mesh
        start = time.perf_counter()
        image = voxelize(arrangement, spec.cube_mm)
        labels = _face_connected(image.labels)
        i, j, k = np.nonzero(labels)
        corners = np.array([(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)] * 2)
        corners[4:, 2] = 1  # the top face's corners in the bottom's order
        nx, ny, nz = (n + 1 for n in image.labels.shape)
        ids = ((i[:, None] + corners[:, 0]) * ny + j[:, None] + corners[:, 1]) * nz
        ids += k[:, None] + corners[:, 2]
        used, hexes = np.unique(ids, return_inverse=True)
        hexes = hexes.reshape(-1, 8)
        ui, rest = np.divmod(used, ny * nz)
        points = np.column_stack([ui, *np.divmod(rest, nz)]) * spec.cube_mm + image.origin_mm
        cells = hexes[:, _KUHN].reshape(-1, 4)
        chip = np.repeat(labels[i, j, k].astype(np.int64) - 1, len(_KUHN))
        mesh = VolumeMesh(
            points=points,
            cell_type="tetra",
            cells=cells,
            chip=chip,
            **element_attributes(arrangement, chip, scenario.geometry.layer_mm),
            quality=tetra_sicn(points, cells),
            node_sets=side_node_sets(points),
            n_chips=arrangement.n_chips,
            kind=self.name,
            info={"cube_mm": spec.cube_mm, "mesh_time_s": round(time.perf_counter() - start, 3)},
        )
        return Built(mesh)

    def check(self, built, arrangement, scenario, surface_pairs):
        thinnest = min(s.thickness_mm for s in arrangement.shapes)
        tolerance = max(0.02, 0.25 * scenario.mesh.cube_mm / thinnest)
        spec = scenario.mesh
        return check_volume(
            built.mesh, arrangement, surface_pairs(), spec.min_quality, tolerance, self.name
        )


KUHN = KuhnTetrahedra()


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
