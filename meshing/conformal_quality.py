"""The quality of a conformal mesh: slivers' nodes moved, gmsh's optimisers, and a sliver's
volume meshed again by Delaunay; the check that every element passes the bar."""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from chipstack.meshing.mesh import MeshingError, VolumeMesh
from chipstack.meshing.slivers import improve_tetrahedra

log = logging.getLogger(__name__)

_HOPELESS_FRACTION = 0.01  # elements below the quality bar beyond which no polish is tried
_DELAUNAY_MAX_ELEMENTS = 100_000  # the largest volume meshed again by Delaunay for a sliver
_LEFT_TO_MOVES = 10  # at most this many slivers of a larger volume are left to the node moves


SLIVER_FLOOR = 0.2


def _move_sliver_nodes(mesh: VolumeMesh) -> VolumeMesh:
    """The slivers gmsh's polish leaves (a few, in the pore space's thin gaps between
    chips: 8 of 170,000 elements under 0.1 on a 24-chip stack; 19 of 3.96 million under
    0.2 on the reference stack) have their nodes moved: inside a region freely, on a
    face of a chip or an interface within its plane, on an edge along it, corners kept
    (:func:`meshing.slivers.improve_tetrahedra` without its gmsh step: the volumes were
    optimised already). No element is added or reconnected; every chip's faces stay in
    their planes, so the volumes and the shared faces are kept. A move is kept only when
    it raises the worst of the node's elements, so the worst element never gets worse."""
    quality = np.asarray(mesh.quality)
    if not (quality < SLIVER_FLOOR).any():
        return mesh

    improved = improve_tetrahedra(
        mesh.points, mesh.cells, mesh.chip, floor=SLIVER_FLOOR, rounds=1, optimise=False
    )
    # The node sets stand: a node on a side of the box moves within that side.
    info = dict(mesh.info, slivers=improved.info)
    return dataclasses.replace(mesh, points=improved.points, quality=improved.quality, info=info)


def _check_quality(mesh: VolumeMesh, min_quality: float) -> None:
    """Refuse a mesh with elements below ``min_quality``, naming the chips that hold them."""
    bad = mesh.quality < min_quality
    if bad.any():
        chips = sorted({int(c) for c in mesh.chip[bad]})
        shown = ", ".join(map(str, chips[:12])) + (" ..." if len(chips) > 12 else "")
        raise MeshingError(
            f"conformal mesh: {int(bad.sum())} elements below quality {min_quality:g} "
            f"(worst {mesh.quality.min():.2g}) in chips {shown}, where chips nearly touch; "
            "use the voxel mesh (mesh.kind = 'voxel')"
        )


def _polish(gmsh, min_quality: float) -> None:
    """HXT leaves a flat tetrahedron (a sliver) here and there, often through a chip's
    thickness where nodes of its top and bottom faces lie one above the other. gmsh's own
    optimiser, run again on the volumes that hold one, removes most; a volume that still
    holds one is meshed again by gmsh's Delaunay mesher (slower, but it does not leave
    such slivers) inside its own surface mesh, which stays as it is, so the volume stays
    conformal with its neighbours."""
    model = gmsh.model
    counts = [0, 0]  # elements below the bar, all elements (at the last look)

    per_volume: dict[int, tuple[int, int]] = {}  # volume: (elements, below the bar)

    def poor() -> list[tuple[int, int]]:
        out = []
        counts[:] = [0, 0]
        for _, volume in model.getEntities(3):
            _, tags, _ = model.mesh.getElements(3, volume)
            if tags and len(tags[0]):
                quality = model.mesh.getElementQualities(np.concatenate(tags), "minSICN")
                per_volume[volume] = (len(quality), int(np.sum(quality < min_quality)))
                counts[0] += per_volume[volume][1]
                counts[1] += len(quality)
                if np.min(quality) < min_quality:
                    out.append((3, volume))
        return out

    # The polish removes slivers here and there (measured: at most a few hundred in
    # 200,000 elements); a mesh with more than 1 % of its elements below the bar asks for
    # a quality the mesher does not reach (and more than 200, for small meshes), and
    # polishing every volume would only delay the refusal (by 10 s on the 24-chip test
    # stack at a bar of 0.9).
    volumes = poor()
    if counts[0] > max(_HOPELESS_FRACTION * counts[1], 200):
        log.info(
            "conformal mesh: %d of %d elements below quality %g, not polished",
            *counts,
            min_quality,
        )
        return
    for attempt in range(2):
        if attempt:
            volumes = poor()
        if not volumes:
            return
        model.mesh.optimize("", force=True, dimTags=volumes)
    volumes = poor()
    # A volume of the size of a whole stack's pore space is left to the node moves that
    # follow (``_move_sliver_nodes``): Delaunay takes minutes on it for a sliver or two
    # (reference stack, seed 3: 390 s for one element of quality 0.084 in 951,650 of the
    # pore, which the node moves took to 0.20 in 13 s).
    # A cluster of slivers is beyond the node moves (reference stack, seed 4: 138 elements
    # under 0.1 near one chip, worst 0.0005, after them), so only a few are left to them.
    large = [
        (dim, volume)
        for dim, volume in volumes
        if per_volume[volume][0] > _DELAUNAY_MAX_ELEMENTS
        and per_volume[volume][1] <= _LEFT_TO_MOVES
    ]
    if large:
        log.info(
            "conformal mesh: %d volumes of more than %d elements left to the node moves "
            "(at most %d slivers each)",
            len(large),
            _DELAUNAY_MAX_ELEMENTS,
            _LEFT_TO_MOVES,
        )
    volumes = [dv for dv in volumes if dv not in large]
    if volumes:
        _remesh_delaunay(gmsh, volumes)
        volumes = poor()
        volumes = [dv for dv in volumes if dv not in large]
        if volumes:
            model.mesh.optimize("", force=True, dimTags=volumes)
    # Netgen's optimiser is not tried any more: on a mesh holding a flat tetrahedron
    # (quality ~1e-14) it crashed the process (reference stack, seeds 3 and 5), and a
    # crash cannot be turned into a one-line error. The quality check refuses the mesh.


def _shells(model, volume: int) -> list[list[int]]:
    """The surfaces bounding ``volume`` grouped into closed shells (surfaces that share a
    curve are in one shell)."""
    surfaces = [abs(t) for _, t in model.getBoundary([(3, volume)], oriented=False)]
    curves = [[abs(c) for _, c in model.getBoundary([(2, s)], oriented=False)] for s in surfaces]
    index = {c: [] for group in curves for c in group}
    for k, group in enumerate(curves):
        for c in group:
            index[c].append(k)
    links = [(ks[0], k) for ks in index.values() for k in ks[1:]]
    graph = coo_matrix(
        (np.ones(len(links)), ([a for a, _ in links], [b for _, b in links])),
        shape=(len(surfaces), len(surfaces)),
    )
    _, label = connected_components(graph, directed=False)
    return [[s for s, g in zip(surfaces, label, strict=True) if g == k] for k in np.unique(label)]


def _remesh_delaunay(gmsh, volumes: list[tuple[int, int]]) -> None:
    """Mesh ``volumes`` again with gmsh's Delaunay mesher inside their surface meshes,
    which are kept (so each stays conformal with its neighbours).

    Each volume is meshed in a model of its own, built from its surface triangles: in the
    stack's model, gmsh's Delaunay meshes the whole connected group of volumes again
    (measured: 77 s for one chip of the reference stack, against 1 s alone)."""
    model, option = gmsh.model, gmsh.option
    log.info("conformal mesh: %d volumes meshed again with Delaunay (slivers)", len(volumes))
    stack = model.getCurrent()
    node_tags, node_xyz, _ = model.mesh.getNodes()
    order = np.argsort(node_tags)
    node_tags, node_xyz = node_tags[order], node_xyz.reshape(-1, 3)[order]
    next_node = int(model.mesh.getMaxNodeTag()) + 1
    next_element = int(model.mesh.getMaxElementTag()) + 1
    surface_xyz = dict(zip(node_tags.tolist(), node_xyz, strict=True))  # once, not per volume
    saved = {
        name: option.getNumber(name)
        for name in ("Mesh.Algorithm3D", "Mesh.MeshSizeExtendFromBoundary", "Mesh.Renumber")
    }
    for _, volume in volumes:
        shells = []  # the triangles of each closed shell of the volume's boundary
        for group in _shells(model, volume):
            triangles = []
            for surface in group:
                types, _, nodes = model.mesh.getElements(2, surface)
                triangles += [n for t, n in zip(types, nodes, strict=True) if t == 2]
            shells.append(np.concatenate(triangles).astype(np.int64))
        # The outer shell first, the holes after it (the pore's box around its chips): as
        # one surface, the holes would be filled too (measured: mixed-shapes seed 4,
        # 2,372 faces shared by three elements after the pore was meshed again).
        extent = [
            np.ptp(node_xyz[np.searchsorted(node_tags, np.unique(t))], axis=0).sum() for t in shells
        ]
        shells = [shells[k] for k in np.argsort(extent)[::-1]]
        model.add("chipstack-remesh")
        try:
            option.setNumber("Mesh.Algorithm3D", 1)
            option.setNumber("Mesh.MeshSizeExtendFromBoundary", 1)  # no field here
            option.setNumber("Mesh.Renumber", 0)  # the surface's nodes keep their tags
            loops = []
            for triangles in shells:
                boundary = np.unique(triangles)
                xyz = node_xyz[np.searchsorted(node_tags, boundary)]
                surface = model.addDiscreteEntity(2)
                model.mesh.addNodes(2, surface, boundary, xyz.ravel())
                model.mesh.addElementsByType(surface, 2, [], triangles)
                loops.append(model.geo.addSurfaceLoop([surface]))
            # A volume of the geo kernel over the discrete surfaces: a discrete volume is
            # not meshed, and the surfaces' own triangles are kept as they are.
            alone = model.geo.addVolume(loops)
            model.geo.synchronize()
            model.mesh.generate(3)
            inner, inner_xyz, _ = model.mesh.getNodes(3, alone)
            _, _, tets = model.mesh.getElements(3, alone)
        finally:
            for name, value in saved.items():
                option.setNumber(name, value)
            model.remove()
            model.setCurrent(stack)
        if not len(tets) or not len(tets[0]):
            continue
        renumber = dict(zip(inner.tolist(), range(next_node, next_node + len(inner)), strict=True))
        tets = np.array([renumber.get(int(t), int(t)) for t in tets[0]], dtype=np.int64)
        new_inner = np.arange(next_node, next_node + len(inner))
        # A new mesh that does not fill the volume exactly once (a hole filled, a part
        # left empty) is not taken: the quality check then refuses the old one.
        added = dict(zip(new_inner.tolist(), np.asarray(inner_xyz).reshape(-1, 3), strict=True))
        corners = np.array([added.get(int(t), surface_xyz.get(int(t))) for t in tets])
        corners = corners.reshape(-1, 4, 3)
        filled = np.abs(np.linalg.det(corners[:, 1:] - corners[:, :1])).sum() / 6
        exact = model.occ.getMass(3, volume)
        if abs(filled - exact) > 1e-6 * exact:
            log.warning(
                "conformal mesh: volume %d meshed again fills %.6g mm3 of %.6g; kept as it was",
                volume,
                filled,
                exact,
            )
            continue
        elements = np.arange(next_element, next_element + len(tets) // 4)
        next_node += len(inner)
        next_element += len(elements)
        model.mesh.clear([(3, volume)])
        model.mesh.addNodes(3, volume, new_inner, np.asarray(inner_xyz).ravel())
        model.mesh.addElementsByType(volume, 4, elements, tets)
