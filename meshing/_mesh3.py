"""Child process of the image route: CGAL's Mesh_3 (pygalmesh) on one labelled image.

``python meshing/_mesh3.py IMAGE.npy OUT.npz VOXEL CIRCUMRADIUS FACET_DISTANCE OPTIMISE SEED``
reads a uint16 label image, meshes it and writes the tetrahedra (``points`` mm in the
image's frame, ``cells``, ``refs``: Mesh_3's subdomain of each). A process of its own:
Mesh_3 writes its progress to stderr whatever ``verbose`` says, and a crash of the C++
mesher must not take the pipeline with it. Run by path, it imports only numpy and
pygalmesh.
"""

from __future__ import annotations

import sys

import numpy as np


def mesh_image(labels, voxel, circumradius, facet_distance, optimise, seed):
    """(points, cells, refs) of Mesh_3's tetrahedra of ``labels`` (vertices of no
    tetrahedron dropped)."""
    import pygalmesh

    mesh = pygalmesh.generate_from_array(
        labels,
        (voxel, voxel, voxel),
        max_cell_circumradius=circumradius,
        max_facet_distance=facet_distance,
        perturb=optimise,
        exude=optimise,
        verbose=False,
        seed=seed,
    )
    blocks = [k for k, c in enumerate(mesh.cells) if c.type == "tetra"]
    if not blocks:
        return np.empty((0, 3)), np.empty((0, 4), dtype=np.int64), np.empty(0, dtype=np.int64)
    cells = np.asarray(mesh.cells[blocks[0]].data, dtype=np.int64)
    refs = np.asarray(mesh.cell_data["medit:ref"][blocks[0]], dtype=np.int64)
    used, cells = np.unique(cells, return_inverse=True)
    return np.asarray(mesh.points, dtype=float)[used], cells.reshape(-1, 4), refs


def main(argv: list[str]) -> None:
    image, out, voxel, circumradius, facet_distance, optimise, seed = argv
    labels = np.load(image)
    points, cells, refs = mesh_image(
        labels, float(voxel), float(circumradius), float(facet_distance), optimise == "1", int(seed)
    )
    np.savez(out, points=points, cells=cells, refs=refs)


if __name__ == "__main__":
    main(sys.argv[1:])
