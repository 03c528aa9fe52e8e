"""The README's picture: the paper's reference stack, settled, beside its voxel mesh.

``python -m chipstack.pipeline.picture`` (part of ``make docs``) runs the reference scenario to its
mesh into ``runs/paper-squares`` as ``make run`` does (the stage cache makes that instant
after ``make run``) and draws ``docs/stack-and-mesh.png``: the chips coloured by
batch, and the hexahedra of the middle of the stack cut open, coloured by chip.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyvista
from PIL import Image  # a pyvista dependency

from chipstack.pipeline.run import run_pipeline
from chipstack.pipeline.scenario_files import load_scenario

__all__ = ["draw"]

ROOT = Path(__file__).resolve().parent.parent
PICTURE = ROOT / "docs" / "stack-and-mesh.png"
# The cut-away: the mesh's elements whose centres lie in this box (mm).
WINDOW_MM = (-35.0, 35.0, -35.0, 0.0)


def draw(run_dir: Path = ROOT / "runs" / "paper-squares", out: Path = PICTURE) -> Path:
    """Run (or reuse) the reference stack to its mesh in ``run_dir`` and draw ``out``."""
    scenario = load_scenario("paper-squares").with_seed(0)
    run_pipeline(scenario, run_dir, to="mesh")
    stack = pyvista.read(sorted((run_dir / "packing").glob("stack_after_batch_*.vtp"))[-1])
    grid = pyvista.read(run_dir / "mesh" / "stack_voxel.vtu")
    centres = grid.cell_centers().points
    x0, x1, y0, y1 = WINDOW_MM
    inside = (
        (centres[:, 0] > x0) & (centres[:, 0] < x1) & (centres[:, 1] > y0) & (centres[:, 1] < y1)
    )
    chips = grid.cell_data["region"] <= scenario.deposition.chips  # the pore is n + 1
    cut = grid.extract_cells(np.flatnonzero(inside & chips))
    with pyvista.vtk_verbosity("off"):
        plotter = pyvista.Plotter(off_screen=True, shape=(1, 2), window_size=[1600, 640])
        try:
            plotter.set_background("white")
            plotter.subplot(0, 0)
            plotter.add_mesh(
                stack, scalars="batch", cmap="viridis", show_scalar_bar=False, preference="cell"
            )
            plotter.add_text(
                f"{scenario.deposition.chips} chips settled in "
                f"{int(stack.cell_data['batch'].max())} batches (colour: batch)",
                font_size=11,
                color="black",
            )
            plotter.camera_position = "iso"
            plotter.camera.zoom(1.4)
            plotter.subplot(0, 1)
            plotter.add_mesh(
                cut,
                scalars="region",
                cmap="tab20",
                show_edges=True,
                edge_color="#303030",
                line_width=0.5,
                show_scalar_bar=False,
                preference="cell",
            )
            plotter.add_text(
                f"its voxel mesh, cut open ({scenario.mesh.voxel_mm:g} mm hexahedra, colour: chip)",
                font_size=11,
                color="black",
            )
            plotter.camera_position = "iso"
            plotter.camera.zoom(1.05)
            image = plotter.screenshot(return_img=True)
        finally:
            plotter.close()
    out.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.asarray(image)).save(out, format="PNG", optimize=True)
    return out


if __name__ == "__main__":
    import logging

    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    log = logging.getLogger(__name__)
    log.setLevel(logging.INFO)
    log.info("drew %s", draw().relative_to(ROOT))
