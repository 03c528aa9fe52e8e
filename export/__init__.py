"""Writers of files and pictures. Every function takes the path to write; the run directory
manager in :mod:`pipeline` decides where that is."""

from typing import TYPE_CHECKING

from chipstack.core.lazy import lazy_package

if TYPE_CHECKING:
    from chipstack.export.tables import write_contacts_csv, write_poses_csv
    from chipstack.export.vtk import stack_polydata, write_pvd, write_stack_vtp

__all__ = [
    "stack_polydata",
    "write_contacts_csv",
    "write_poses_csv",
    "write_pvd",
    "write_stack_vtp",
]

# Imported on first use: checking a scenario's mesh formats (meshing.files) imports
# this package at every run, and these writers bring scipy and the packing world (~0.6 s).
lazy_package(
    __name__,
    {
        "stack_polydata": "chipstack.export.vtk",
        "write_contacts_csv": "chipstack.export.tables",
        "write_poses_csv": "chipstack.export.tables",
        "write_pvd": "chipstack.export.vtk",
        "write_stack_vtp": "chipstack.export.vtk",
    },
)
