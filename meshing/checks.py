"""Validity of a volume mesh of the stack: the figures a reviewer of an FE model asks for.

``check_mesh`` returns a plain report (JSON-ready); ``assert_valid`` raises
:class:`MeshingError` with the first failed criterion. Criteria (documented in the README):

* every element has positive volume;
* element quality (SICN; 1 for a regular tetrahedron or a cube): minimum and 1st
  percentile, the minimum above ``min_quality``;
* the meshed volume of every chip within ``chip_tolerance`` (2 %) of its exact solid after
  the overlap rule, and of the whole within ``total_tolerance`` (1 %) of the union;
* no two nodes at the same place;
* every face shared by at most two elements (one on the boundary, two inside);
* every chip one piece: its elements connected through shared faces (a chip whose pieces
  meet only at edges or nodes is a mechanism in a solver, not a chip);
* chips in surface contact share interface faces.
"""

from __future__ import annotations

import logging

import manifold3d as m3
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from chipstack.core.arrangement import Arrangement
from chipstack.geometry.contacts import candidate_pairs
from chipstack.geometry.solids import chip_solids, union_solid
from chipstack.meshing.boundaries import ELEMENT_FACES
from chipstack.meshing.mesh import MeshingError, VolumeMesh

__all__ = [
    "check_mesh",
    "check_volume",
    "assert_valid",
    "exact_chip_volumes",
    "element_faces",
    "chip_pieces",
    "split_warning",
    "surface_report",
]

# Chips in pieces are the mesh stage's warning (it names the kind).
log = logging.getLogger(__name__)


def element_faces(mesh: VolumeMesh) -> tuple[np.ndarray, np.ndarray]:
    """Every face of every element: (F, k) sorted node ids and (F,) owning element."""
    return _faces(mesh.cells, mesh.cell_type)


def _faces(cells: np.ndarray, cell_type: str) -> tuple[np.ndarray, np.ndarray]:
    local = ELEMENT_FACES[cell_type]
    faces = np.concatenate([cells[:, list(f)] for f in local])
    owner = np.tile(np.arange(len(cells)), len(local))
    return np.sort(faces, axis=1), owner


def face_neighbours(cells: np.ndarray, cell_type: str) -> tuple[np.ndarray, np.ndarray]:
    """(a, b): the two elements on either side of every face that two elements share
    (``cells``: node ids per element, before a :class:`VolumeMesh` exists)."""
    faces, owner = _faces(cells, cell_type)
    order = np.lexsort(faces.T[::-1])
    faces, owner = faces[order], owner[order]
    twin = np.flatnonzero(np.all(faces[1:] == faces[:-1], axis=1))
    return owner[twin], owner[twin + 1]


def _sorted_faces(mesh: VolumeMesh) -> tuple[np.ndarray, np.ndarray]:
    """``element_faces`` sorted so that the copies of a face are neighbours."""
    faces, owner = element_faces(mesh)
    order = np.lexsort(faces.T[::-1])
    return faces[order], owner[order]


def chip_pieces(mesh: VolumeMesh, sorted_faces=None) -> np.ndarray:
    """(n_chips,) int: into how many face-connected pieces each chip's elements fall (1 for
    a sound chip, 0 for a chip with no element; pore elements are not counted)."""
    faces, owner = sorted_faces if sorted_faces is not None else _sorted_faces(mesh)
    same = np.flatnonzero(np.all(faces[1:] == faces[:-1], axis=1))
    a, b = owner[same], owner[same + 1]
    own_chip = (mesh.chip[a] == mesh.chip[b]) & (mesh.chip[a] >= 0)
    n = mesh.n_elements
    graph = coo_matrix((np.ones(int(own_chip.sum())), (a[own_chip], b[own_chip])), shape=(n, n))
    _, component = connected_components(graph, directed=False)
    counted = mesh.chip >= 0
    pairs = np.unique(np.column_stack([mesh.chip[counted], component[counted]]), axis=0)
    return np.bincount(pairs[:, 0], minlength=mesh.n_chips)


def exact_chip_volumes(arrangement: Arrangement, region_mm=None) -> np.ndarray:
    """(n,) mm3: each chip's solid minus the lower chips it overlaps (the meshing rule),
    within the crop ``region_mm`` ([x_min, x_max, y_min, y_max]) when one is given."""
    return _volumes_by_rule(arrangement, _cut(arrangement, chip_solids(arrangement), region_mm))


def _volumes_by_rule(arrangement: Arrangement, solids: list) -> np.ndarray:
    """(n,) mm3 of ``solids`` (one per chip), each minus the lower chips it overlaps."""
    volumes = np.array([s.volume() for s in solids])
    rank = arrangement.bottom_up_rank()
    below: dict[int, list[int]] = {}
    for i, j in candidate_pairs(arrangement.bounds, 0.0).tolist():  # any shape, exact below
        lower, upper = (i, j) if rank[i] < rank[j] else (j, i)
        below.setdefault(upper, []).append(lower)
    for upper, lowers in below.items():
        volumes[upper] = (solids[upper] - union_solid([solids[k] for k in lowers])).volume()
    return volumes


def _cut(arrangement: Arrangement, solids: list, region_mm=None) -> list:
    """The chips' exact solids cut to the crop when there is one."""
    if region_mm is None:
        return solids
    x0, x1, y0, y1 = region_mm
    top = float(arrangement.bounds[:, 1, 2].max()) + 1.0 if arrangement.n_chips else 1.0
    box = m3.Manifold.cube([x1 - x0, y1 - y0, top + 2.0]).translate([x0, y0, -1.0])
    return [solid ^ box for solid in solids]


def check_mesh(
    mesh: VolumeMesh,
    arrangement: Arrangement,
    surface_pairs: np.ndarray | None = None,
    min_quality: float = 0.1,
    chip_tolerance: float = 0.02,
    total_tolerance: float = 0.01,
    region_mm=None,
) -> dict:
    """The validity report of ``mesh`` (see the module docstring). ``region_mm``: the crop
    the mesh was cut to ([x_min, x_max, y_min, y_max]); a chip the crop cuts is compared
    with its part inside, the error taken relative to its whole volume (a sliver's own
    volume would make a voxel's aliasing look like 100 %)."""
    volumes = mesh.element_volumes()
    quality = np.asarray(mesh.quality)
    meshed = mesh.chip_volumes()
    solids = chip_solids(arrangement)
    cut = _cut(arrangement, solids, region_mm)
    exact = _volumes_by_rule(arrangement, cut)
    whole = exact if region_mm is None else _volumes_by_rule(arrangement, solids)
    relative = np.abs(meshed - exact) / np.maximum(whole, 1e-12)
    union = union_solid(cut).volume()
    total = float(meshed.sum())
    rounded = np.round(mesh.points / 1e-7).astype(np.int64)
    duplicates = len(mesh.points) - len(np.unique(rounded, axis=0))
    faces, owner = _sorted_faces(mesh)
    same = np.all(faces[1:] == faces[:-1], axis=1)
    starts = np.flatnonzero(np.concatenate([[True], ~same]))
    counts = np.diff(np.concatenate([starts, [len(faces)]]))
    shared_ok = bool((counts <= 2).all())
    # A crop can cut a concave chip into separate pieces (a star's two arms): those are
    # its exact part inside, not a chip falling apart.
    expected = np.ones(mesh.n_chips, dtype=int)
    if region_mm is not None:
        for k, solid in enumerate(cut[: mesh.n_chips]):
            if not solid.is_empty():
                expected[k] = max(1, len(solid.decompose()))
    split = np.flatnonzero(chip_pieces(mesh, (faces, owner)) > expected)
    interfaces = {}
    if surface_pairs is not None and len(surface_pairs):
        pair_faces = starts[counts == 2]
        a = mesh.chip[owner[pair_faces]]
        b = mesh.chip[owner[pair_faces + 1]]
        touching = {
            tuple(sorted(p)) for p in zip(a.tolist(), b.tolist(), strict=True) if p[0] != p[1]
        }
        wanted = {tuple(sorted(map(int, p))) for p in surface_pairs}
        missing = sorted(wanted - touching)
        interfaces = {
            "surface_contacts": len(wanted),
            "sharing_faces": len(wanted) - len(missing),
            "missing": [list(p) for p in missing[:20]],
        }
    report = {
        "elements": int(mesh.n_elements),
        "nodes": int(len(mesh.points)),
        "bounds_mm": [mesh.points.min(axis=0).tolist(), mesh.points.max(axis=0).tolist()],
        "min_element_volume_mm3": float(volumes.min()),
        "quality_min": float(quality.min()),
        "quality_p1": float(np.percentile(quality, 1)),
        "min_quality": min_quality,
        "chip_volume_error_max": float(relative.max()),
        "chip_tolerance": chip_tolerance,
        "chip_volume_worst": int(np.argmax(relative)),
        "total_volume_mm3": total,
        "union_volume_mm3": float(union),
        "total_volume_error": float(abs(total - union) / union),
        "duplicate_nodes": int(duplicates),
        "faces_shared_by_more_than_two": int((counts > 2).sum()),
        "chips_in_pieces": split.tolist()[:20],
        "chips_in_pieces_count": int(len(split)),
        "interfaces": interfaces,
    }
    if (below := int((quality < min_quality).sum())) > 0:
        # How many, and where the worst is: its centroid (mm) and its region (a chip's
        # index, or -1: the pore space).
        worst = int(np.argmin(quality))
        report["quality_below_min_count"] = below
        report["quality_worst_at_mm"] = (
            mesh.points[mesh.cells[worst]].mean(axis=0).round(3).tolist()
        )
        report["quality_worst_region"] = int(mesh.chip[worst])
    report["valid"] = bool(
        volumes.min() > 0
        and quality.min() >= min_quality
        and relative.max() <= chip_tolerance
        and report["total_volume_error"] <= total_tolerance
        and duplicates == 0
        and shared_ok
        and len(split) == 0
        and not interfaces.get("missing")
    )
    return report


def split_warning(report: dict, kind: str) -> str | None:
    """The warning for chips in pieces, or None when every chip is one piece."""
    count = report.get("chips_in_pieces_count", 0)
    if not count:
        return None
    return (
        f"{kind} mesh not valid for a solver: {count} chips fall apart into pieces joined "
        f"only at edges or nodes (chips {report['chips_in_pieces']}"
        f"{', ...' if count > len(report['chips_in_pieces']) else ''}); use a smaller element"
    )


def _region_name(region: int | None) -> str:
    if region is None:
        return "the mesh"
    return "the pore space" if region < 0 else f"chip {region}"


def assert_valid(report: dict) -> None:
    """Raise :class:`MeshingError` naming the first criterion ``report`` fails.

    Chips in pieces are not raised here: the mesh is still the best picture of the stack
    (the voxel mesh is the fallback that always exists), so the report says ``"valid":
    false``, names the chips, and the stage warns (:func:`split_warning`)."""
    checks = [
        (report["min_element_volume_mm3"] > 0, "an element has no positive volume"),
        (
            report["quality_min"] >= report["min_quality"],
            f"{report.get('quality_below_min_count', 1)} elements below quality "
            f"{report['min_quality']}, the worst {report['quality_min']:.3g} in "
            f"{_region_name(report.get('quality_worst_region'))} at "
            f"{report.get('quality_worst_at_mm')} mm",
        ),
        (
            report["chip_volume_error_max"] <= report.get("chip_tolerance", 0.02),
            f"chip {report['chip_volume_worst']} volume off by "
            f"{100 * report['chip_volume_error_max']:.2f} % "
            f"(over {100 * report.get('chip_tolerance', 0.02):.3g} %)",
        ),
        (
            report["total_volume_error"] <= 0.01,
            f"total volume off by {100 * report['total_volume_error']:.2f} % (over 1 %)",
        ),
        (report["duplicate_nodes"] == 0, f"{report['duplicate_nodes']} duplicate nodes"),
        (report["faces_shared_by_more_than_two"] == 0, "faces shared by more than two elements"),
        (
            not report["interfaces"].get("missing"),
            f"chips in surface contact without shared faces: {report['interfaces'].get('missing')}",
        ),
    ]
    for ok, problem in checks:
        if not ok:
            raise MeshingError(f"mesh check failed: {problem}")


def check_volume(mesh, arrangement, pairs, min_quality, tolerance, kind) -> dict:
    """The check report of a volume mesh of the stack (``meshing.checks.check_mesh``),
    raising when it is not valid: what a kind's ``check`` returns. ``pairs``: the chip
    pairs in surface contact, whose meshes must share faces; ``tolerance``: the largest
    accepted relative error of a chip's volume; ``kind``: the kind's name, for the log."""
    report = check_mesh(
        mesh,
        arrangement,
        pairs,
        min_quality,
        chip_tolerance=tolerance,
        region_mm=mesh.info.get("region_mm"),
    )
    assert_valid(report)
    if (warning := split_warning(report, kind)) is not None:
        log.warning("%s", warning)
    return report


def surface_report(mesh: VolumeMesh) -> dict[str, dict]:
    """The platen and support surfaces of the mesh's files (``VolumeMesh.surfaces``), by
    name: faces, nodes, area_mm2 and projected_area_mm2 (on the xy plane, what a platen
    presses); the check report's ``surfaces``."""
    return {
        name: {
            "faces": len(surface.element),
            "nodes": len(surface.node_ids),
            "area_mm2": round(surface.area_mm2, 4),
            "projected_area_mm2": round(surface.projected_area_mm2, 4),
        }
        for name, surface in mesh.surfaces.items()
    }
