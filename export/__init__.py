"""Writers of files and pictures. Every function takes the path to write; the run directory
manager in :mod:`pipeline` decides where that is."""

from export.tables import write_contacts_csv, write_poses_csv
from export.vtk import stack_polydata, write_pvd, write_stack_vtp

__all__ = [
    "stack_polydata",
    "write_contacts_csv",
    "write_poses_csv",
    "write_pvd",
    "write_stack_vtp",
]
