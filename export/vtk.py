"""ParaView files: the stack as polydata (.vtp) and a time series of them (.pvd)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING
from xml.sax.saxutils import quoteattr

import numpy as np
from scipy.spatial.transform import Rotation

if TYPE_CHECKING:
    from chipstack.core.chipshape import ChipShape


def stack_polydata(
    shapes: tuple[ChipShape, ...],
    shape_index: np.ndarray,
    positions: np.ndarray,
    quaternions: np.ndarray,
    batch: np.ndarray,
):
    """The chips as one ``pyvista.PolyData``; cell data ``region`` (chip k of the packing
    tables is region k + 1, as in every mesh file) and ``batch``.

    positions (n, 3) mm, quaternions (n, 4) x, y, z, w; one polygon per chip face.
    """
    import pyvista  # heavy: imported when a picture or file is asked for

    rotations = Rotation.from_quat(quaternions).as_matrix()
    points, faces, chip_ids = [], [], []
    offset = 0
    for i in range(len(positions)):
        shape = shapes[shape_index[i]]
        points.append(shape.vertices @ rotations[i].T + positions[i])
        for face in shape.faces:
            faces.append([len(face), *(offset + v for v in face)])
            chip_ids.append(i)
        offset += len(shape.vertices)
    mesh = (
        pyvista.PolyData(np.vstack(points), np.concatenate(faces)) if points else pyvista.PolyData()
    )
    chip_ids = np.asarray(chip_ids, dtype=np.int32)
    mesh.cell_data["region"] = chip_ids + 1
    mesh.cell_data["batch"] = np.asarray(batch, dtype=np.int32)[chip_ids]
    return mesh


def write_stack_vtp(path: Path, mesh) -> None:
    mesh.save(str(path), binary=True)


def write_pvd(path: Path, entries: list[tuple[float, str]]) -> None:
    """A ParaView collection: (time value, file name relative to the .pvd) per step."""
    lines = [
        '<?xml version="1.0"?>',
        '<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">',
        "  <Collection>",
    ]
    lines += [
        f'    <DataSet timestep="{t:g}" group="" part="0" file={quoteattr(name)}/>'
        for t, name in entries
    ]
    lines += ["  </Collection>", "</VTKFile>", ""]
    Path(path).write_text("\n".join(lines))


def write_voxel_image(path: Path, image) -> None:
    """The voxel image as VTK ImageData (.vti): cell array ``region``, the region id of
    every mesh file (chip k of the packing tables is k + 1; a void voxel is the pore
    space's id, n_chips + 1); field data ``voxel_mm``, ``origin_mm`` and ``shape`` (voxel
    (i, j, k) spans origin + (i, j, k) * voxel_mm to one voxel further)."""
    import pyvista

    grid = pyvista.ImageData(
        dimensions=np.array(image.labels.shape) + 1,
        spacing=(image.voxel_mm,) * 3,
        origin=image.origin_mm,
    )
    labels = np.ascontiguousarray(image.labels).ravel(order="F")
    grid.cell_data["region"] = np.where(labels > 0, labels, image.n_chips + 1).astype(np.int32)
    grid.field_data["voxel_mm"] = [float(image.voxel_mm)]
    grid.field_data["origin_mm"] = np.asarray(image.origin_mm, dtype=float)
    grid.field_data["shape"] = np.asarray(image.labels.shape, dtype=np.int64)
    grid.save(str(path))
