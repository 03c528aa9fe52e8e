"""Image route: tetrahedra of the labelled voxel image, by CGAL's Mesh_3 (``pygalmesh``).

The exact route (:mod:`meshing.conformal`) needs a mesh-ready arrangement and curved or
many-sided chips it cannot take; this route needs only a labelled image (chip id per
voxel), so it takes any stack the geometry stage can voxelize, and later a CT scan. The
chips' faces are Mesh_3's approximation of the label boundaries (a staircase between
voxel centres: nodes within about a voxel of the exact faces, volumes within ~1 %),
and touching chips share their interface faces by construction.

How, and why so:

* The stack's image is cut into its face-connected pieces, each meshed on its own (chips
  are first grouped by bounding boxes within two voxels, so that no image spans the
  empty conveyor between groups). Mesh_3 finds a subdomain only from points its
  refinement reaches: chips lying alone on the conveyor, up to 170 mm from the pile, were
  left out of a whole-stack image (10 of 270 chips of the reference stack, seed 0), and
  so was a chip 2 voxels from the pile's image.
* With ``pore_space = "box"``, the pore space of the box over the chips (as for the voxel
  mesh) is given a label of its own, so the whole box is one cluster: Mesh_3 meshes only
  non-zero labels.
* Mesh_3 renumbers the labels; each subdomain is mapped back to a chip by the label of the
  voxel under most of its elements' centroids.
* Mesh_3 runs in a child process: it writes its progress to stderr (millions of lines on a
  stack) whatever ``verbose`` says, and a crash of the C++ mesher (or the kernel killing
  it for memory) must become a one-line error, not the end of the pipeline.

Element quality is the signed inverse condition number (SICN) of each tetrahedron, the
measure gmsh reports for the conformal mesh (1 for a regular tetrahedron, negative when
inverted).
"""

from __future__ import annotations

import importlib.util
import logging
import math
import os
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from chipstack.core.arrangement import Arrangement
from chipstack.core.errors import InputError
from chipstack.geometry.contacts import candidate_pairs
from chipstack.geometry.voxels import voxelize
from chipstack.meshing.boundaries import side_node_sets
from chipstack.meshing.checks import face_neighbours
from chipstack.meshing.mesh import (
    PORE,
    MeshingError,
    VolumeMesh,
    check_voxel_below_thinnest,
    element_attributes,
)
from chipstack.meshing.slivers import improve_tetrahedra, tetra_sicn
from chipstack.meshing.voxel import _crop

__all__ = ["image_mesh", "image_voxel_mm", "tetra_sicn", "cgal_available", "require_cgal"]

log = logging.getLogger(__name__)

_PAD = 2  # empty voxels around a cluster's image: its chips' outer faces are boundaries
# A regular tetrahedron's circumradius over its edge: ``size_mm`` is an edge length.
_CIRCUMRADIUS_PER_EDGE = math.sqrt(6) / 4
# The largest label Mesh_3 reads from a 16-bit image, the pore space's among them.
MAX_LABELS = 65_534


def cgal_available() -> bool:
    """True when ``pygalmesh`` (CGAL's Mesh_3) can be imported."""
    return importlib.util.find_spec("pygalmesh") is not None


def require_cgal() -> None:
    """Refuse the image route where ``pygalmesh`` is missing, naming the make target that
    installs it (``make run`` does not: it compiles nothing)."""
    if not cgal_available():
        raise InputError(
            "mesh.kind: 'image' needs pygalmesh (CGAL's Mesh_3), which is not installed: "
            "run `make image` (it installs Debian's libcgal-dev and libeigen3-dev with "
            "apt-get, then compiles pygalmesh, about 5 minutes)"
        )


def image_voxel_mm(arrangement: Arrangement, voxel_mm: float = 0.0) -> float:
    """The image route's voxel (mm): ``voxel_mm``, or for 0 an eighth of the thinnest chip
    dimension; raises naming ``mesh.image_voxel_mm`` when it is not below that dimension.

    Why an eighth: the reference stack's chips (2 mm thick) come within 1.1 % of their
    exact volumes at 0.25 mm; at a twelfth (0.167 mm) its main cluster of 256 touching
    chips, spread over 280 x 273 mm, is a 415-million-voxel image, over the voxelizer's
    cap and, measured at 0.25 mm (3 GB), well over 4 GB in Mesh_3."""
    if voxel_mm == 0:
        return arrangement.thinnest_mm / 8
    check_voxel_below_thinnest("mesh.image_voxel_mm", voxel_mm, arrangement, 4)
    return voxel_mm


@dataclass(frozen=True)
class _Cluster:
    """One image to mesh: labels (uint16: 1 + index into ``chips``; ``pore`` for the pore
    space), the centre of its first voxel (mm) and the chips (global ids) its labels
    stand for."""

    labels: np.ndarray
    origin_mm: np.ndarray
    chips: np.ndarray
    pore: int  # the pore space's label, 0 when there is none


def image_mesh(
    arrangement: Arrangement,
    voxel_mm: float = 0.0,
    size_mm: float = 1.5,
    pore_space: str = "none",
    layer_mm: float = 2.0,
    optimise: bool = False,
    seed: int = 0,
    region_mm: tuple[float, float, float, float] | None = None,
    improve: bool = True,
) -> VolumeMesh:
    """Tetrahedral mesh of the stack's labelled image (see the module docstring).

    region_mm: (x_min, x_max, y_min, y_max) of a crop (the voxels whose centres lie in
    it, chips cut at its sides; with the pore space the box spans the whole region), or
    None for the whole stack.

    voxel_mm: the image's voxel (0: an eighth of the thinnest chip dimension). size_mm:
    the largest element edge. seed: Mesh_3's random seed: without ``optimise`` the same
    seed and image give the same mesh. optimise: perturb and exude slivers after the
    refinement (reference stack, 0.25 mm voxels: 288 s instead of 60 s, the worst SICN
    0.036 instead of 0.0006), but CGAL's optimisers then give a different mesh each run
    (measured: the same seed, nodes up to 20 mm apart in their order). improve: remove
    the slivers Mesh_3 leaves (:func:`meshing.slivers.improve_tetrahedra`: gmsh's
    optimiser, then boundary nodes moved within their boundary; regions, shared faces and
    volumes kept, reproducible)."""
    if pore_space not in ("none", "box"):
        raise InputError(f"mesh.pore_space: must be 'none' or 'box', got {pore_space!r}")
    require_cgal()
    start = time.perf_counter()
    voxel = image_voxel_mm(arrangement, voxel_mm)
    clusters, meshed_region = _clusters(arrangement, voxel, pore_space, region_mm)
    expected = np.unique(np.concatenate([c.chips[_labels_in(c) - 1] for c in clusters]))
    parts = _mesh_clusters(clusters, voxel, size_mm, optimise, seed)
    points, cells, chip = [], [], []
    offset = 0
    for cluster, (cluster_points, cluster_cells, refs) in zip(clusters, parts, strict=True):
        cluster_chip = _chips_of_subdomains(cluster, cluster_points, cluster_cells, refs, voxel)
        points.append(cluster_points + cluster.origin_mm)
        cells.append(cluster_cells + offset)
        chip.append(cluster_chip)
        offset += len(cluster_points)
    points = np.concatenate(points)
    cells = np.concatenate(cells).astype(np.int64)
    if not len(cells):
        raise MeshingError(
            f"image mesh: Mesh_3 made no element at {voxel:g} mm voxels; use a smaller "
            "mesh.image_voxel_mm"
        )
    chip, keep = _absorb_strays(points, cells, np.concatenate(chip))
    used, cells = np.unique(cells[keep], return_inverse=True)
    points, cells, chip = points[used], cells.reshape(-1, 4), chip[keep]
    missing = np.setdiff1d(expected, chip)
    if len(missing):
        shown = ", ".join(map(str, missing[:10])) + (", ..." if len(missing) > 10 else "")
        raise MeshingError(
            f"image mesh: Mesh_3 left out chips {shown} at {voxel:g} mm voxels; use a "
            "smaller mesh.image_voxel_mm"
        )
    slivers, quality = None, None
    if improve:
        improved = improve_tetrahedra(points, cells, chip, seed=seed)
        points, cells, chip = improved.points, improved.cells, improved.labels
        slivers, quality = improved.info, improved.quality
    return VolumeMesh(
        points=points,
        cell_type="tetra",
        cells=cells,
        chip=chip,
        **element_attributes(arrangement, chip, layer_mm),
        quality=tetra_sicn(points, cells) if quality is None else quality,
        # Mesh_3 finds flat sides (the conveyor, a crop's sides, the box's top) by
        # bisection, to ~0.01 mm: moving the nodes onto the planes flattened elements at
        # the bevelled edges (tried), so the sets take the nodes within a quarter voxel.
        node_sets=side_node_sets(points, tolerance_mm=voxel / 4),
        n_chips=arrangement.n_chips,
        kind="image",
        info={
            "voxel_mm": round(voxel, 6),
            "size_mm": size_mm,
            "pore_space": pore_space,
            "optimise": optimise,
            "improve": improve,
            "slivers": slivers,
            "seed": seed,
            "clusters": len(clusters),
            "region_mm": meshed_region,
            "mesh_time_s": round(time.perf_counter() - start, 3),
        },
    )


def _labels_in(cluster: _Cluster) -> np.ndarray:
    """The chip labels (1-based, the pore's left out) in a cluster's image."""
    labels = np.unique(cluster.labels)
    return labels[(labels > 0) & (labels != cluster.pore)].astype(np.int64)


def _clusters(
    arrangement: Arrangement, voxel: float, pore_space: str, region_mm=None
) -> tuple[list[_Cluster], list[float] | None]:
    """The images to mesh (one per face-connected piece of each group of chips; the whole
    box with the pore space) and the crop as meshed (voxel boundaries), if any."""

    n = arrangement.n_chips
    near = np.ones(n, dtype=bool)
    if region_mm is not None:  # chips whose boxes reach into the crop
        x0, x1, y0, y1 = region_mm
        low, high = arrangement.bounds[:, 0], arrangement.bounds[:, 1]
        near = (high[:, 0] >= x0) & (low[:, 0] <= x1) & (high[:, 1] >= y0) & (low[:, 1] <= y1)
    empty = InputError(
        "mesh.region_mm: the crop x {:g} to {:g}, y {:g} to {:g} mm holds no chip of the "
        "stack".format(*region_mm)
        if region_mm is not None
        else "mesh.kind: the image route has no chip to mesh"
    )
    if not near.any():
        raise empty
    if pore_space == "box":
        groups = [np.flatnonzero(near)]
    else:
        pairs = candidate_pairs(arrangement.bounds, 2 * voxel)
        graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
        _, label = connected_components(graph, directed=False)
        groups = [np.flatnonzero((label == k) & near) for k in range(label.max() + 1)]
        groups = [g for g in groups if len(g)]
    clusters, meshed_region = [], None
    for chips in groups:
        if len(chips) + 1 > MAX_LABELS:
            raise InputError(
                f"mesh.kind: the image route takes at most {MAX_LABELS - 1:,} chips in a "
                f"cluster, got {len(chips):,}"
            )
        part = Arrangement(
            arrangement.shapes,
            arrangement.shape_index[chips],
            arrangement.positions[chips],
            arrangement.quaternions[chips],
            arrangement.batch[chips],
            arrangement.target_size_mm,
        )
        try:
            image = voxelize(part, voxel)
        except InputError as error:  # too many voxels: name the key the user sets
            raise InputError(f"mesh.image_voxel_mm: {str(error).partition(': ')[2]}") from None
        labels = image.labels
        origin = np.asarray(image.origin_mm, dtype=float)
        if region_mm is not None:
            try:
                labels, origin = _crop(labels, origin, voxel, region_mm)
            except InputError:  # this group's chips only come near the crop
                continue
            # Groups' images differ in extent (each covers the target and its chips), so
            # the crop as meshed is the union of theirs.
            top = origin[:2] + np.array(labels.shape[:2]) * voxel
            here = [float(origin[0]), float(top[0]), float(origin[1]), float(top[1])]
            meshed_region = (
                here
                if meshed_region is None
                else [
                    min(meshed_region[0], here[0]),
                    max(meshed_region[1], here[1]),
                    min(meshed_region[2], here[2]),
                    max(meshed_region[3], here[3]),
                ]
            )
        solid = labels > 0
        pore = 0
        if pore_space == "box":  # the box over the chips' footprint, as the voxel mesh's
            pore = len(chips) + 1
            ii, jj, kk = (np.flatnonzero(solid.any(axis=axes)) for axes in ((1, 2), (0, 2), (0, 1)))
            box = np.zeros_like(solid)
            if region_mm is not None:  # the whole region: its sides are full faces
                box[:, :, : kk.max() + 1] = True
            else:
                box[ii.min() : ii.max() + 1, jj.min() : jj.max() + 1, : kk.max() + 1] = True
            labels = np.where(box & ~solid, pore, labels)
            solid = labels > 0
        # Each face-connected piece of the image on its own: chips whose boxes come near
        # but whose voxels do not meet are separate pieces (a chip 0.3 mm from the pile
        # was left out of the pile's image), and chips meeting only at a voxel's edge
        # or corner could be too.
        pieces, count = ndimage.label(solid)
        for k, box_slices in enumerate(ndimage.find_objects(pieces), start=1):
            low = np.array([s.start for s in box_slices])
            piece = np.where(pieces[box_slices] == k, labels[box_slices], 0)
            padded = np.pad(piece, _PAD).astype(np.uint16)
            # Mesh_3 puts voxel (i, j, k) of an image at (i, j, k) x voxel: its centre.
            centre_of_first = origin + (low - _PAD + 0.5) * voxel
            clusters.append(_Cluster(padded, centre_of_first, np.asarray(chips), pore))
    if not clusters:
        raise empty
    return clusters, meshed_region


def _mesh_clusters(clusters, voxel, size_mm, optimise, seed):
    """Mesh_3 on every cluster's image, each in a child process (:mod:`meshing._mesh3`):
    [(points, tetrahedra, subdomain of each tetrahedron)], points in the cluster's frame
    (mm)."""

    # Mesh_3 takes a C int as its seed.
    settings = [voxel, size_mm * _CIRCUMRADIUS_PER_EDGE, voxel / 2, int(optimise), seed % 2**31]
    results: list = [None] * len(clusters)
    with tempfile.TemporaryDirectory(prefix="chipstack-mesh3-") as scratch:
        for k in range(len(clusters)):
            log.info(
                "Mesh_3: cluster %d of %d (%d chips, %s voxels)",
                k + 1,
                len(clusters),
                len(clusters[k].chips),
                f"{clusters[k].labels.size:,}",
            )
            image, out = Path(scratch) / f"{k}.npy", Path(scratch) / f"{k}.npz"
            errors = Path(scratch) / f"{k}.err"
            np.save(image, clusters[k].labels)
            # Run by path: the child needs only numpy and pygalmesh. Mesh_3's progress
            # goes to stderr (millions of lines on a stack): to a file, not to memory.
            # TMPDIR: pygalmesh's own temporary files (the image again, the mesh) are
            # then removed with the scratch folder even when the child is killed.
            command = [sys.executable, str(Path(__file__).with_name("_mesh3.py"))]
            with open(errors, "wb") as stderr:
                done = subprocess.run(
                    command + [str(image), str(out)] + [repr(v) for v in settings],
                    stdout=subprocess.DEVNULL,
                    stderr=stderr,
                    env={**os.environ, "TMPDIR": scratch},
                )
            if done.returncode != 0 or not out.is_file():
                chips = clusters[k].chips
                shown = ", ".join(map(str, chips[:5])) + (", ..." if len(chips) > 5 else "")
                raise MeshingError(
                    f"image mesh: CGAL's Mesh_3 failed on the piece with chips {shown} "
                    f"({_failure(done.returncode, errors)})"
                )
            with np.load(out) as data:
                results[k] = (data["points"], data["cells"], data["refs"])
    return results


def _failure(status: int, errors) -> str:
    """What ended a Mesh_3 child, in a few words: the signal, or its last error line."""

    if status < 0:
        name = signal.Signals(-status).name
        hint = ", out of memory?" if name == "SIGKILL" else ""
        return f"killed by {name}{hint}"
    lines = errors.read_bytes()[-4000:].decode(errors="replace").strip().splitlines()
    found = [line for line in lines if "Error" in line or "error" in line]
    return f"exit status {status}: {(found or lines or ['?'])[-1][:200]}"


def _absorb_strays(
    points: np.ndarray, cells: np.ndarray, chip: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``chip`` with stray elements given to their neighbours, and which elements to keep.

    Mesh_3 labels a tetrahedron by the image under its circumcentre, so where three chips
    meet a lone tetrahedron can take the label of a chip it touches only at an edge (the
    24-chip test stack: one, making its chip two pieces for a solver). A face-connected
    piece of a chip (never of the pore space) that is not its largest and holds under 1 %
    of its volume goes to the region it shares most faces with; one that shares no face with
    anything (a sliver hanging by an edge: the reference stack, seed 0, three pieces of
    0.001 to 0.006 mm3) is dropped."""

    a, b = face_neighbours(cells, "tetra")
    n = len(cells)
    same = chip[a] == chip[b]
    graph = coo_matrix((np.ones(int(same.sum())), (a[same], b[same])), shape=(n, n))
    _, piece = connected_components(graph, directed=False)
    p = points[cells]
    edges = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    volume = np.abs(np.einsum("ij,ij->i", edges, p[:, 3] - p[:, 0])) / 6
    piece_volume = np.bincount(piece, weights=volume)
    region = np.zeros(len(piece_volume), dtype=np.int64)
    region[piece] = chip - chip.min()
    by_region = np.lexsort((piece_volume, region))  # by region, then volume
    largest = np.zeros(len(region), dtype=bool)
    largest[by_region[np.r_[region[by_region][1:] != region[by_region][:-1], True]]] = True
    region_volume = np.bincount(region, weights=piece_volume)
    # The pore space's pieces stay what they are: a pocket the chips close off is pore
    # (the voxel mesh keeps it so), whatever its size.
    stray = ~largest & (piece_volume < 0.01 * region_volume[region]) & (region != PORE - chip.min())
    if not stray.any():
        return chip, np.ones(len(chip), dtype=bool)
    # Each stray piece goes to the region across most of its faces.
    forward, backward = ~same & stray[piece[a]], ~same & stray[piece[b]]
    sources = np.concatenate([piece[a[forward]], piece[b[backward]]])
    targets = np.concatenate([chip[b[forward]], chip[a[backward]]])
    if not len(sources):
        return chip, ~stray[piece]
    pairs, counts = np.unique(np.column_stack([sources, targets]), axis=0, return_counts=True)
    best = np.lexsort((counts, pairs[:, 0]))
    last = best[np.r_[pairs[best][1:, 0] != pairs[best][:-1, 0], True]]
    unset = np.iinfo(np.int64).min
    new_chip = np.full(len(region), unset, dtype=np.int64)
    new_chip[pairs[last, 0]] = pairs[last, 1]
    moved = stray[piece] & (new_chip[piece] != unset)
    chip = np.where(moved, new_chip[piece], chip)
    keep = ~stray[piece] | moved
    log.debug(
        "image mesh: %d stray pieces, %d elements given to their neighbours, %d dropped",
        int(stray.sum()),
        int(moved.sum()),
        int((~keep).sum()),
    )
    return chip, keep


def _chips_of_subdomains(cluster: _Cluster, points, cells, refs, voxel) -> np.ndarray:
    """(M,) chip id (global; ``PORE`` for the pore space) of every tetrahedron: each Mesh_3
    subdomain takes the label under most of its tetrahedra's centroids."""
    if not len(cells):
        return np.empty(0, dtype=np.int64)
    index = np.rint(points[cells].mean(axis=1) / voxel).astype(np.int64)
    index = np.clip(index, 0, np.array(cluster.labels.shape) - 1)
    under = cluster.labels[index[:, 0], index[:, 1], index[:, 2]].astype(np.int64)
    # Centroids over the void (a tetrahedron across a label boundary) do not vote.
    votes = under > 0
    pairs, counts = np.unique(
        np.column_stack([refs[votes], under[votes]]), axis=0, return_counts=True
    )
    label_of = np.zeros(int(refs.max()) + 1, dtype=np.int64)
    for ref in np.unique(refs):
        mine = pairs[:, 0] == ref
        if not mine.any():
            raise MeshingError(
                f"image mesh: a Mesh_3 subdomain ({int((refs == ref).sum())} elements) lies "
                "over no chip; use a smaller mesh.image_voxel_mm"
            )
        label_of[ref] = pairs[mine][np.argmax(counts[mine]), 1]
    label = label_of[refs]
    lookup = np.full(len(cluster.chips) + 2, PORE, dtype=np.int64)  # the pore last
    lookup[1 : len(cluster.chips) + 1] = cluster.chips
    return lookup[label]
