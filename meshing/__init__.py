"""Meshing stage (gmsh, always inside a context manager): not implemented yet (issue 3)."""
