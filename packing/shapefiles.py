"""Chips read from geometry files (STL, OBJ, PLY).

The file is read with trimesh, in the units the scenario states, and checked: it must hold
one closed (watertight), consistently oriented surface with a positive volume. The chip
is then centred on its centre of mass and turned to its principal axes of inertia, the
axis of the largest moment (a plate's normal) becoming local z and the smallest (its
length) local x, so a chip from a file lies like every other chip.

A convex chip is its own single convex piece, exactly. A non-convex flat chip (a plate of
uniform thickness, what a shredder cuts from a sheet) is split exactly through its
outline. Any other non-convex chip is split by V-HACD (PyBullet's built-in copy) into
convex pieces for the physics and the geometry stage; the pieces approximate the chip,
and a split whose volume is more than ``MAX_DECOMPOSITION_ERROR`` away from the exact
volume is refused.
"""

from __future__ import annotations

import logging
import os
import tempfile
from functools import lru_cache
from pathlib import Path

import numpy as np

from chipstack.core.chipshape import WOVEN_DEG, ChipShape, frozen_array, spec_fibre_directions
from chipstack.core.errors import InputError, brief, printable
from chipstack.core.files import check_geometry_file
from chipstack.core.keys import LENGTH_UNITS_MM
from chipstack.core.schema import ChipSpec
from chipstack.packing.polygons import convex_partition, counter_clockwise

__all__ = ["shape_from_file", "file_extent", "FILE_SUFFIXES", "MAX_DECOMPOSITION_ERROR"]

log = logging.getLogger(__name__)

FILE_SUFFIXES = (".stl", ".obj", ".ply")
MAX_DECOMPOSITION_ERROR = 0.10
MAX_FACES = 200_000
MAX_VERTEX_MM = 1e6  # 1 km: surely a wrong unit or a broken file (a chip is far smaller)


@lru_cache(maxsize=32)
def _read(path: str, mtime: float, units: str):
    """(vertices mm, faces, convex pieces) of the file, centred and on principal axes."""
    import trimesh

    shown = printable(path)
    suffix = Path(path).suffix.lower()
    if suffix not in FILE_SUFFIXES:
        raise InputError(
            f"{shown}: unsupported geometry file type {suffix or '(none)'!r}; "
            f"use {', '.join(FILE_SUFFIXES)}"
        )
    check_geometry_file(path, MAX_FACES)  # its size, before a byte of it is parsed
    try:
        # Not processed yet: merging vertices is arithmetic, and the numbers are unchecked.
        loaded = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for malformed files
        message = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise InputError(f"{shown}: unreadable geometry file ({brief(message)})") from None
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise InputError(f"{shown}: the geometry file holds no surface")
    mesh = loaded
    if len(mesh.faces) > MAX_FACES:
        raise InputError(f"{shown}: {len(mesh.faces)} faces; at most {MAX_FACES} are accepted")
    vertices = np.asarray(mesh.vertices)
    if not np.isfinite(vertices).all():
        raise InputError(f"{shown}: vertices hold NaN or infinite values")
    reach = float(np.abs(vertices).max(initial=0.0)) * LENGTH_UNITS_MM[units]
    if reach > MAX_VERTEX_MM:  # before any arithmetic on them: 1e150 would overflow
        raise InputError(
            f"{shown}: a vertex lies {reach:.3g} mm from the origin; at most {MAX_VERTEX_MM:g}"
        )
    mesh.process(validate=False)
    if mesh.body_count != 1:
        raise InputError(f"{shown}: holds {mesh.body_count} separate bodies; give one chip")
    if not mesh.is_watertight:
        raise InputError(f"{shown}: the surface is not watertight (it has holes or open edges)")
    if not mesh.is_winding_consistent:
        raise InputError(f"{shown}: the faces are not consistently oriented")
    mesh.apply_scale(LENGTH_UNITS_MM[units])
    if mesh.volume < 0:
        mesh.invert()
    if not mesh.volume > 0:
        raise InputError(f"{shown}: the surface encloses no volume")
    # Centre of mass at the origin, principal axes along x (smallest moment) to z (largest).
    mesh.apply_translation(-mesh.center_mass)
    moments, axes = np.linalg.eigh(mesh.moment_inertia)
    if np.linalg.det(axes) < 0:
        axes[:, 0] *= -1
    vertices = np.asarray(mesh.vertices) @ axes
    mesh = trimesh.Trimesh(vertices, mesh.faces, process=False)
    hull = mesh.convex_hull
    outline = None
    if abs(hull.volume - mesh.volume) <= 1e-6 * hull.volume:
        pieces = [np.asarray(hull.vertices)]
    elif (outline := _prism_outline(mesh)) is not None:
        # A flat chip cut from a sheet: its outline, partitioned exactly.

        low, high = float(mesh.vertices[:, 2].min()), float(mesh.vertices[:, 2].max())
        pieces = [
            np.vstack([np.column_stack([q, np.full(len(q), z)]) for z in (low, high)])
            for q in convex_partition(outline)
        ]
    else:
        pieces = _decompose(mesh, shown)
    inertia = moments / mesh.volume  # per unit mass for a uniform chip (mm^2)
    return np.asarray(mesh.vertices), np.asarray(mesh.faces), pieces, float(mesh.volume), inertia


def _prism_outline(mesh) -> np.ndarray | None:
    """The outline (n, 2) of a mesh that is a plate extruded along z, else None."""
    z = mesh.vertices[:, 2]
    low, high = z.min(), z.max()
    tol = 1e-6 * float(np.ptp(mesh.vertices, axis=0).max())
    if not np.all((np.abs(z - low) <= tol) | (np.abs(z - high) <= tol)):
        return None
    top = mesh.faces[np.all(np.abs(z[mesh.faces] - high) <= tol, axis=1)]
    edges = np.sort(np.vstack([top[:, [0, 1]], top[:, [1, 2]], top[:, [2, 0]]]), axis=1)
    unique, counts = np.unique(edges, axis=0, return_counts=True)
    boundary = unique[counts == 1]
    neighbours: dict[int, list[int]] = {}
    for a, b in boundary.tolist():
        neighbours.setdefault(a, []).append(b)
        neighbours.setdefault(b, []).append(a)
    if not neighbours or any(len(v) != 2 for v in neighbours.values()):
        return None  # holes or several outlines: not a simple plate
    start = next(iter(neighbours))
    loop, previous, current = [start], None, start
    while True:
        a, b = neighbours[current]
        following = b if a == previous else a
        if following == start:
            break
        loop.append(following)
        previous, current = current, following
    if len(loop) != len(neighbours):
        return None
    return counter_clockwise(mesh.vertices[loop, :2])


def _decompose(mesh, shown: str) -> list[np.ndarray]:
    import trimesh

    # pybullet (~0.1 s) only for a concave file: every scenario check imports this module
    from chipstack.packing.bullet import vhacd

    with tempfile.TemporaryDirectory(prefix="chipstack-vhacd-") as tmp:
        source, target = os.path.join(tmp, "in.obj"), os.path.join(tmp, "out.obj")
        mesh.export(source)
        vhacd(source, target, os.path.join(tmp, "log.txt"))
        pieces = _obj_objects(target)
    pieces = [p for p in pieces if len(p) >= 4]
    if not pieces:
        raise InputError(f"{shown}: convex decomposition failed (no pieces)")
    total = sum(trimesh.convex.convex_hull(p).volume for p in pieces)
    error = abs(total - mesh.volume) / mesh.volume
    if error > MAX_DECOMPOSITION_ERROR:
        raise InputError(
            f"{shown}: its convex decomposition differs from the chip by {100 * error:.1f} % "
            f"of its volume (at most {100 * MAX_DECOMPOSITION_ERROR:g} % accepted)"
        )
    log.info("%s: %d convex pieces, volume within %.2f %%", shown, len(pieces), 100 * error)
    return pieces


def _obj_objects(path: str) -> list[np.ndarray]:
    """The vertices of each object (``o`` line) of an OBJ file, as V-HACD writes it (a
    generic OBJ reader would merge the objects into one mesh)."""
    objects: list[list[list[float]]] = []
    with open(path, encoding="utf-8") as f:
        for line in f:
            if line.startswith("o ") or not objects:
                objects.append([])
            if line.startswith("v "):
                objects[-1].append([float(v) for v in line.split()[1:4]])
    return [np.array(o) for o in objects if o]


def shape_from_file(spec: ChipSpec, size: float = 1.0):
    """The chip in ``spec.file`` (units ``spec.units``), scaled by ``size`` in its plane."""

    path = spec.file
    try:
        mtime = os.path.getmtime(path)
    except OSError:
        raise InputError(f"chip.file: {printable(path)}: geometry file not found") from None
    vertices, faces, pieces, volume, inertia = _read(path, mtime, spec.units)
    scale = np.array([size, size, 1.0])
    vertices = vertices * scale
    pieces = tuple(frozen_array(p * scale) for p in pieces)
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    name = f"file {Path(path).name}" + (f" x{size:.4g}" if size != 1.0 else "")
    inertia = inertia * np.array([size**2, size**2, size**2])  # in-plane scaling, roughly
    return ChipShape(
        name=name,
        kind="file",
        vertices=frozen_array(vertices),
        faces=tuple(tuple(int(v) for v in f) for f in faces),
        convex_pieces=pieces,
        fibre_directions=frozen_array(spec_fibre_directions(spec, WOVEN_DEG)),
        volume_mm3=volume * size * size,
        inertia_mm2=frozen_array(inertia),
        half_extents=frozen_array((hi - lo) / 2),
        box_centre=frozen_array((hi + lo) / 2),
        collision="hull",
    )


def file_extent(spec: ChipSpec) -> tuple[float, float]:
    """(largest in-plane extent, circumradius) in mm of the chip in ``spec.file``, at its
    nominal size (the ``file`` shape's ``extent``)."""
    shape = shape_from_file(spec)
    across = 2 * float(np.linalg.norm(shape.vertices[:, :2], axis=1).max())
    return across, shape.circumradius_mm
