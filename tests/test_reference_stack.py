"""The reference stack's files (``make run``: ``paper-squares``, 270 chips, 1 mm voxels)
as a consolidation modeller reads them: the platen's surface covers the stack's
footprint, and every format gives each region the same elements."""

from __future__ import annotations

import json

import meshio
import numpy as np
import pytest
import pyvista


def _region_counts(blocks, data) -> dict[int, int]:
    values = np.concatenate(
        [np.asarray(d) for c, d in zip(blocks, data, strict=True) if c.dim == 3]
    )
    ids, counts = np.unique(values, return_counts=True)
    return dict(zip(ids.tolist(), counts.tolist(), strict=True))


def test_top_covers_the_reference_stack_footprint(reference_run):
    """``top`` (the upper envelope a platen meets) projects onto the area covered by any
    chip in the geometry's voxel image, within 5 % (the issue's bound; on voxels of the
    same size as the image's it is the same columns, so equal), and ``bottom`` onto the
    chips resting on the conveyor, less than the footprint."""
    checks = json.loads((reference_run / "mesh/stack_voxel_checks.json").read_text())
    surfaces = checks["surfaces"]
    assert set(surfaces) == {"top", "bottom"}  # no pore box, no crop: no sides
    image = pyvista.read(reference_run / "geometry/voxels.vti")
    shape = np.array(image.dimensions) - 1
    region = np.asarray(image.cell_data["region"]).reshape(shape, order="F")
    chips = int(json.loads((reference_run / "manifest.json").read_text())["packing"]["chips"])
    covered = (region <= chips).any(axis=2).sum() * image.spacing[0] * image.spacing[1]
    assert surfaces["top"]["projected_area_mm2"] == pytest.approx(covered, rel=0.05)
    assert 0 < surfaces["bottom"]["projected_area_mm2"] < covered


def test_every_format_gives_each_region_the_same_elements(reference_run):
    """The per-region element counts that meshio reads from the .msh (physical tags),
    the .vtu and the .xdmf (``region``) are one mapping, every chip in it once."""
    mesh = reference_run / "mesh"
    msh = meshio.read(mesh / "stack_voxel.msh")
    counts = {"msh": _region_counts(msh.cells, msh.cell_data["gmsh:physical"])}
    for name in ("vtu", "xdmf"):
        back = meshio.read(mesh / f"stack_voxel.{name}")
        counts[name] = _region_counts(back.cells, back.cell_data["region"])
    assert counts["msh"] == counts["vtu"] == counts["xdmf"]
    assert sorted(counts["msh"]) == list(range(1, 271))
