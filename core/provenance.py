"""Versions of the code a result came from (in cache keys and manifests)."""

from __future__ import annotations

import platform
from importlib import metadata

__all__ = ["code_versions"]

PACKAGES = ("chipstack", "pybullet", "numpy", "scipy", "manifold3d", "pyvista", "vtk")


def code_versions() -> dict[str, str]:
    """Python's and the result-making packages' versions ("not installed" if absent)."""
    versions = {"python": platform.python_version()}
    for package in PACKAGES:
        try:
            versions[package] = metadata.version(package)
        except metadata.PackageNotFoundError:
            versions[package] = "not installed"
    return versions
