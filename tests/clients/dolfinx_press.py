"""DOLFINx presses a box-shaped mesh between platens; prints the platen force as JSON.

Run by the DOLFINx environment's Python (``make dolfinx``)::

    .venv-dolfinx/bin/python tests/clients/dolfinx_press.py MESH.msh E NU PRESS_MM

The mesh is read as a user reads it, with ``dolfinx.io.gmsh.read_from_msh``, and its
surfaces are taken from its facet tags (``bottom`` 1, ``top`` 2). Linear elasticity, one
isotropic material (``E`` in MPa, ``NU``) on every cell, on linear Lagrange elements
(P1 on tetrahedra, Q1 on hexahedra) integrated by Gauss points of degree 2 (2 x 2 x 2 on
a hexahedron: CalculiX's full-integration C3D8); ``bottom`` is fixed, ``top`` moved by
``-PRESS_MM`` along z with x and y held, the sides are free. The platen force is the
reaction on the top's z degrees of freedom, the residual of the solved field there
(the nodal forces CalculiX prints as RF), in N (negative: the platen pushes down).

Prints one JSON object: ``force_n``, ``dofs``, ``cells``, ``cell_type``, the facets of
each surface, the region ids found in the cell tags, and the wall times of reading and
solving (s).
"""

from __future__ import annotations

import contextlib
import ctypes
import json
import os
import sys
import time

# First: dolfinx_solver loads the wheel's MPI, PETSc and HDF5 libraries that dolfinx needs.
import dolfinx_solver  # noqa: F401

# isort: split

import dolfinx
import dolfinx.fem.petsc
import numpy as np
import ufl
from dolfinx.io.gmsh import read_from_msh
from mpi4py import MPI

BOTTOM, TOP = 1, 2  # the facet tags of meshing/boundaries.py


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


def main(path: str, young: float, poisson: float, press: float) -> dict:
    """Solve the press on the mesh at ``path``; the measured figures."""
    start = time.perf_counter()
    with stdout_to_stderr():
        data = read_from_msh(path, MPI.COMM_WORLD, 0, gdim=3)
    read_s = time.perf_counter() - start
    mesh, facets = data.mesh, data.facet_tags
    tdim = mesh.topology.dim
    start = time.perf_counter()
    space = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    mu = young / (2 * (1 + poisson))
    lam = young * poisson / ((1 + poisson) * (1 - 2 * poisson))

    def strain(w):
        return ufl.sym(ufl.grad(w))

    def stress(w):
        return 2 * mu * strain(w) + lam * ufl.tr(strain(w)) * ufl.Identity(3)

    u, v = ufl.TrialFunction(space), ufl.TestFunction(space)
    dx = ufl.Measure("dx", domain=mesh, metadata={"quadrature_degree": 2})
    a = ufl.inner(stress(u), strain(v)) * dx
    zero = dolfinx.fem.Constant(mesh, np.zeros(3))
    rhs = ufl.inner(zero, v) * dx
    bottom_dofs = dolfinx.fem.locate_dofs_topological(space, tdim - 1, facets.find(BOTTOM))
    top_dofs = dolfinx.fem.locate_dofs_topological(space, tdim - 1, facets.find(TOP))
    pressed = dolfinx.fem.Constant(mesh, np.array([0.0, 0.0, -press]))
    conditions = [
        dolfinx.fem.dirichletbc(np.zeros(3), bottom_dofs, space),
        dolfinx.fem.dirichletbc(pressed, top_dofs, space),
    ]
    problem = dolfinx.fem.petsc.LinearProblem(
        a,
        rhs,
        bcs=conditions,
        petsc_options_prefix="press_",
        petsc_options={
            "ksp_type": "preonly",
            "pc_type": "lu",
            "pc_factor_mat_solver_type": "mumps",
        },
    )
    solved = problem.solve()
    solve_s = time.perf_counter() - start
    # The reaction: the internal nodal forces of the solved field at the top's z dofs.
    residual = dolfinx.fem.assemble_vector(dolfinx.fem.form(ufl.action(a, solved)))
    residual.scatter_reverse(dolfinx.la.InsertMode.add)
    top_z = dolfinx.fem.locate_dofs_topological(space.sub(2), tdim - 1, facets.find(TOP))
    force = float(residual.array[top_z].sum())
    bottom_z = dolfinx.fem.locate_dofs_topological(space.sub(2), tdim - 1, facets.find(BOTTOM))
    return {
        "force_n": force,
        "bottom_force_n": float(residual.array[bottom_z].sum()),
        "dofs": int(space.dofmap.index_map.size_global * space.dofmap.index_map_bs),
        "cells": int(mesh.topology.index_map(tdim).size_global),
        "cell_type": mesh.topology.cell_name(),
        "facets": {
            "bottom": int(len(facets.find(BOTTOM))),
            "top": int(len(facets.find(TOP))),
        },
        "regions": sorted(int(r) for r in np.unique(data.cell_tags.values)),
        "read_s": read_s,
        "solve_s": solve_s,
    }


if __name__ == "__main__":
    path, young, poisson, press = sys.argv[1], *map(float, sys.argv[2:5])
    json.dump(main(path, young, poisson, press), sys.stdout)
    sys.stdout.write("\n")
