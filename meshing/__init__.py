"""Meshing stage: volume meshes of the stack for a consolidation solver.

``voxel_mesh`` (hexahedra from the exact voxel image; always succeeds) and
``conformal_mesh`` (gmsh tetrahedra, one volume per chip, shared interfaces), both
returning a :class:`VolumeMesh`; ``check_mesh`` reports their validity.
"""

from meshing.checks import assert_valid, check_mesh
from meshing.conformal import GmshSession, MeshingError, conformal_mesh
from meshing.mesh import PORE, VolumeMesh
from meshing.voxel import voxel_mesh

__all__ = [
    "GmshSession",
    "MeshingError",
    "PORE",
    "VolumeMesh",
    "assert_valid",
    "check_mesh",
    "conformal_mesh",
    "voxel_mesh",
]
