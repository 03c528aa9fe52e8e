"""The interfaces of a volume mesh: the faces two chips share, pair by pair.

A consolidation model reads them as the input of intimate contact and healing (the
contact area that grows under pressure and heat, and where the polymer bonds across it):
each pair of touching chips is one named interface, with its faces (each seen from both
chips: element and local face number on either side), its area and its mean normal. The
mesh files carry them (``meshing.files``: ``*SURFACE`` pairs in the ``.inp``, physical
surfaces in the ``.msh``, facet tags in the ``.xdmf``, a surface mesh beside the ``.vtu``)
and a table beside the mesh lists them with the contact class the stack's contact
detection gave the pair.
"""

from __future__ import annotations

import csv
import weakref
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from chipstack.meshing.boundaries import ELEMENT_FACES
from chipstack.meshing.mesh import VolumeMesh

__all__ = ["INTERFACE_TAG_START", "Interfaces", "find_interfaces", "write_interface_table"]

# Interface k's tag in the .msh physical surfaces and the .xdmf facet tags (the domain's
# sides take 1 to 6).
INTERFACE_TAG_START = 101


@dataclass(frozen=True)
class Interfaces:
    """The faces shared by two chips of a mesh, by pair.

    pairs: (k, 2) chip indices, the lower first. faces: (F, n) node ids of each shared
    face, ordered as the face of the element on the pair's first chip (so their normal
    points from the first chip into the second). pair: (F,) which pair each face belongs
    to. element_a, face_a, element_b, face_b: (F,) the element and its local face number
    (0-based; the Abaqus face label is S + 1) on either side. area_mm2: (k,) summed face
    area. normal: (k, 3) area-weighted mean unit normal from the first chip to the second.
    """

    pairs: np.ndarray
    faces: np.ndarray
    pair: np.ndarray
    element_a: np.ndarray
    face_a: np.ndarray
    element_b: np.ndarray
    face_b: np.ndarray
    area_mm2: np.ndarray
    normal: np.ndarray

    @property
    def tags(self) -> np.ndarray:
        """(k,) each interface's tag in the mesh files."""
        return INTERFACE_TAG_START + np.arange(len(self.pairs))

    def parts(self) -> list[slice]:
        """Interface k's faces are ``faces[parts()[k]]`` (faces are grouped by pair)."""
        starts = np.searchsorted(self.pair, np.arange(len(self.pairs) + 1))
        return [slice(int(a), int(b)) for a, b in zip(starts[:-1], starts[1:], strict=True)]

    def name(self, k: int) -> str:
        """Interface k's name in the mesh files: ``interface_A_B`` (the two chips' region
        ids, chip index + 1)."""
        a, b = self.pairs[k] + 1
        return f"interface_{a}_{b}"


def _face_vectors(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F, 3) each face's normal scaled by its area (mm2): half the sum of the cross
    products of a fan of triangles (exact for flat faces)."""
    p = points[faces]
    total = np.zeros((len(faces), 3))
    for i in range(1, faces.shape[1] - 1):
        total += np.cross(p[:, i] - p[:, 0], p[:, i + 1] - p[:, 0])
    return 0.5 * total


# A mesh is immutable (frozen, its arrays read-only): every file writer asks for its
# interfaces, which are found once.
_FOUND: weakref.WeakKeyDictionary[VolumeMesh, Interfaces] = weakref.WeakKeyDictionary()


def find_interfaces(mesh: VolumeMesh) -> Interfaces:
    """The faces shared by elements of two different chips (the pore space is not a
    chip: its faces with a chip are not interfaces), grouped by pair of chips."""
    if (found := _FOUND.get(mesh)) is None:
        found = _FOUND[mesh] = _find(mesh)
    return found


def _find(mesh: VolumeMesh) -> Interfaces:
    local = ELEMENT_FACES[mesh.cell_type]
    m = mesh.n_elements
    raw = np.concatenate([mesh.cells[:, list(f)] for f in local])
    owner = np.tile(np.arange(m), len(local))
    which = np.repeat(np.arange(len(local)), m)
    key = np.sort(raw, axis=1)
    order = np.lexsort(key.T[::-1])
    same = np.all(key[order][1:] == key[order][:-1], axis=1)
    i, j = order[:-1][same], order[1:][same]
    chip_i, chip_j = mesh.chip[owner[i]], mesh.chip[owner[j]]
    keep = (chip_i >= 0) & (chip_j >= 0) & (chip_i != chip_j)
    i, j, chip_i, chip_j = i[keep], j[keep], chip_i[keep], chip_j[keep]
    swap = chip_i > chip_j
    i, j = np.where(swap, j, i), np.where(swap, i, j)
    lower, upper = np.minimum(chip_i, chip_j), np.maximum(chip_i, chip_j)
    pairs, pair = np.unique(np.column_stack([lower, upper]), axis=0, return_inverse=True)
    pair = pair.ravel()
    sort = np.lexsort((owner[i], pair))
    i, j, pair = i[sort], j[sort], pair[sort]
    faces = raw[i]
    vectors = _face_vectors(np.asarray(mesh.points, dtype=float), faces)
    summed = np.zeros((len(pairs), 3))
    np.add.at(summed, pair, vectors)
    area = np.bincount(pair, weights=np.linalg.norm(vectors, axis=1), minlength=len(pairs))
    length = np.linalg.norm(summed, axis=1, keepdims=True)
    normal = np.divide(summed, length, out=np.zeros_like(summed), where=length > 0)
    return Interfaces(
        pairs=pairs.reshape(-1, 2).astype(np.int64),
        faces=faces,
        pair=pair,
        element_a=owner[i],
        face_a=which[i],
        element_b=owner[j],
        face_b=which[j],
        area_mm2=area,
        normal=normal,
    )


def write_interface_table(
    path: Path, interfaces: Interfaces, contacts: dict[tuple[int, int], str] | None = None
) -> Path:
    """The interfaces as CSV: tag, region_a, region_b (the two chips' region ids, chip
    index + 1, as in the mesh files), faces, area_mm2, normal_x/y/z (from region_a into
    region_b) and contact, the class the stack's contact detection gave the pair
    (point, line, surface; ``none`` when it found no contact there). Pairs in contact
    whose mesh shares no face (point and line contacts) follow with tag -1 and no faces.
    """
    contacts = contacts or {}
    counts = np.bincount(interfaces.pair, minlength=len(interfaces.pairs))
    meshed = set()
    with open(path, "w", newline="") as f:
        out = csv.writer(f)
        out.writerow(
            ["tag", "region_a", "region_b", "faces", "area_mm2"]
            + ["normal_x", "normal_y", "normal_z"]
            + ["contact"]
        )
        for k, (a, b) in enumerate(interfaces.pairs.tolist()):
            meshed.add((a, b))
            n = interfaces.normal[k]
            out.writerow(
                [int(interfaces.tags[k]), a + 1, b + 1, int(counts[k])]
                + [f"{interfaces.area_mm2[k]:.6g}"]
                + [f"{v:.6f}" for v in n]
                + [contacts.get((a, b), "none")]
            )
        for (a, b), kind in sorted(contacts.items()):
            if (a, b) not in meshed:
                out.writerow([-1, a + 1, b + 1, 0, "0", "", "", "", kind])
    return Path(path)
