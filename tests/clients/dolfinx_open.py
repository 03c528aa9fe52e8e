"""DOLFINx opens a run's mesh files as its user does; prints what it found as JSON.

Run by the DOLFINx environment's Python (``make dolfinx``)::

    .venv-dolfinx/bin/python tests/clients/dolfinx_open.py STEM

where ``STEM`` is a mesh's path without its suffix (``runs/x/mesh/stack_voxel``). Reads

- ``STEM.msh`` with ``dolfinx.io.gmsh.read_from_msh``: the cell tags (the physical
  volumes) and the facet tags (the physical surfaces);
- ``STEM.xdmf`` with ``XDMFFile.read_mesh(name="mesh")`` and ``read_meshtags(mesh,
  name="mesh", attribute_name="region")``, then ``STEM_facets.xdmf`` with
  ``read_meshtags(mesh, name="facets", attribute_name="facets")`` on that mesh.

Prints one JSON object with, for ``msh`` and ``xdmf`` each: ``cells``, ``nodes``,
``cell_type``, ``regions`` (region id -> cells) and ``facets`` (tag -> facets); and the
physical group names gmsh passed on (``names``: "dim/tag" -> name).
"""

from __future__ import annotations

import contextlib
import ctypes
import json
import os
import sys

# First: dolfinx_solver loads the wheel's MPI, PETSc and HDF5 libraries that dolfinx needs.
import dolfinx_solver  # noqa: F401

# isort: split

import numpy as np
from dolfinx.io import XDMFFile
from dolfinx.io.gmsh import read_from_msh
from mpi4py import MPI


@contextlib.contextmanager
def stdout_to_stderr():
    """Send what C libraries print on stdout (gmsh's Info lines) to stderr, so that stdout
    holds the JSON only."""
    sys.stdout.flush()
    saved = os.dup(1)
    os.dup2(2, 1)
    try:
        yield
    finally:
        ctypes.CDLL(None).fflush(None)
        os.dup2(saved, 1)
        os.close(saved)


def counts(tags) -> dict[str, int]:
    """Tag value -> how many entities carry it."""
    values, number = np.unique(tags.values, return_counts=True)
    return {str(int(v)): int(n) for v, n in zip(values, number, strict=True)}


def summary(mesh, cell_tags, facet_tags) -> dict:
    tdim = mesh.topology.dim
    return {
        "cells": int(mesh.topology.index_map(tdim).size_global),
        "nodes": int(mesh.geometry.index_map().size_global),
        "cell_type": mesh.topology.cell_name(),
        "regions": counts(cell_tags),
        "facets": counts(facet_tags),
    }


def main(stem: str) -> dict:
    comm = MPI.COMM_WORLD
    with stdout_to_stderr():
        data = read_from_msh(f"{stem}.msh", comm, 0, gdim=3)
    found = {"msh": summary(data.mesh, data.cell_tags, data.facet_tags)}
    found["names"] = {
        f"{dim}/{tag}": name for name, (dim, tag) in sorted(data.physical_groups.items())
    }
    with XDMFFile(comm, f"{stem}.xdmf", "r") as file:
        mesh = file.read_mesh(name="mesh")
        regions = file.read_meshtags(mesh, name="mesh", attribute_name="region")
    mesh.topology.create_connectivity(mesh.topology.dim - 1, mesh.topology.dim)
    with XDMFFile(comm, f"{stem}_facets.xdmf", "r") as file:
        facets = file.read_meshtags(mesh, name="facets", attribute_name="facets")
    found["xdmf"] = summary(mesh, regions, facets)
    return found


if __name__ == "__main__":
    sys.stdout.write(json.dumps(main(sys.argv[1])) + "\n")
