"""Meshing stage: volume meshes of the stack for a consolidation solver.

``voxel_mesh`` (hexahedra from the exact voxel image; always succeeds) and
``conformal_mesh`` (gmsh tetrahedra, one volume per chip, shared interfaces), both
returning a :class:`VolumeMesh`; ``check_mesh`` reports their validity.
"""

from typing import TYPE_CHECKING

from chipstack.core.lazy import lazy_package

if TYPE_CHECKING:
    from chipstack.meshing.checks import assert_valid, check_mesh
    from chipstack.meshing.conformal import conformal_mesh
    from chipstack.meshing.gmsh_session import GmshSession
    from chipstack.meshing.mesh import PORE, MeshingError, VolumeMesh
    from chipstack.meshing.voxel import voxel_mesh

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
        "GmshSession": "chipstack.meshing.gmsh_session",
        "MeshingError": "chipstack.meshing.mesh",
        "PORE": "chipstack.meshing.mesh",
        "VolumeMesh": "chipstack.meshing.mesh",
        "assert_valid": "chipstack.meshing.checks",
        "check_mesh": "chipstack.meshing.checks",
        "conformal_mesh": "chipstack.meshing.conformal",
        "voxel_mesh": "chipstack.meshing.voxel",
    },
)
