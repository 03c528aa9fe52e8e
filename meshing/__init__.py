"""Meshing stage: volume meshes of the stack for a consolidation solver.

``voxel_mesh`` (hexahedra from the exact voxel image; always succeeds) and
``conformal_mesh`` (gmsh tetrahedra, one volume per chip, shared interfaces), both
returning a :class:`VolumeMesh`; ``check_mesh`` reports their validity.
"""

from typing import TYPE_CHECKING

from core.lazy import lazy_package

if TYPE_CHECKING:
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

# Imported on first use: every command-line start imports meshing.stage, hence this
# package, and these modules bring numpy, scipy and gmsh.
lazy_package(
    __name__,
    {
        "GmshSession": "meshing.conformal",
        "MeshingError": "meshing.conformal",
        "PORE": "meshing.mesh",
        "VolumeMesh": "meshing.mesh",
        "assert_valid": "meshing.checks",
        "check_mesh": "meshing.checks",
        "conformal_mesh": "meshing.conformal",
        "voxel_mesh": "meshing.voxel",
    },
)
