"""The 3-D picture of a stack (the paper's Figure 6): pyvista off screen, after a probe
in a child process that OpenGL can render there at all."""

from __future__ import annotations

import functools
import os
import signal
import subprocess
import sys
from collections.abc import Sequence

import numpy as np
from matplotlib import colormaps
from matplotlib.colors import ListedColormap
from PIL import Image  # matplotlib's own dependency: imported with it

from chipstack.core.errors import InputError
from chipstack.export.figures import _path, _text

__all__ = ["render_stack"]

_RENDER_PROBE_TIMEOUT_S = 120


_PROBE = """
import vtkmodules.vtkRenderingOpenGL2
from vtkmodules.vtkRenderingCore import vtkRenderWindow, vtkRenderer
window = vtkRenderWindow()
window.SetOffScreenRendering(1)
window.SetSize(8, 8)
window.AddRenderer(vtkRenderer())
window.Render()
window.Finalize()
"""


@functools.cache
def _rendering_problem() -> str | None:
    """Why VTK cannot render off screen here, or None; tried once per process.

    Without any OpenGL, VTK crashes the process on the first render (a segmentation fault,
    no Python exception), so the attempt runs in a child interpreter.
    """
    try:
        result = subprocess.run(
            [sys.executable, "-c", _PROBE],
            capture_output=True,
            timeout=_RENDER_PROBE_TIMEOUT_S,
            check=False,
        )
    except (OSError, subprocess.TimeoutExpired) as error:
        return f"the off-screen render test could not run ({type(error).__name__})"
    if result.returncode < 0:
        return f"a test render in a child process was killed by {_signal_name(-result.returncode)}"
    if result.returncode != 0:
        return f"a test render in a child process failed (exit code {result.returncode})"
    return None


def _signal_name(number: int) -> str:
    try:
        return signal.Signals(number).name
    except ValueError:
        return f"signal {number}"


def _tab20_categorical() -> ListedColormap:
    """tab20 with its 10 strong colours first, so neighbouring values differ in hue."""
    colours = colormaps["tab20"].colors
    return ListedColormap([colours[i] for i in [*range(0, 20, 2), *range(1, 20, 2)]], "tab20")


def render_stack(
    path: str | os.PathLike,
    polydata,
    scalars: str = "region",
    window_size: tuple[int, int] = (1200, 900),
    show_edges: bool = True,
) -> None:
    """A 3-D picture of the stack on the conveyor (Fig. 6), rendered off screen.

    polydata: ``pyvista.PolyData`` of the chips (mm, polygons), with cell arrays such as
    "region" and "batch" (see :func:`export.vtk.stack_polydata`). scalars: the cell array
    that colours the chips; whole numbers get categorical tab20 colours (value mod 20),
    other values a continuous tab20 scale. window_size: (width, height) pixels of the PNG.
    The conveyor is a light grey plane at z = 0 slightly larger than the stack.

    Raises RuntimeError when this machine cannot render with OpenGL at all.
    """
    import pyvista  # heavy: imported when a picture is asked for

    path = _path(path)
    if not isinstance(polydata, pyvista.PolyData):
        raise InputError(f"polydata: must be a pyvista.PolyData, got {type(polydata).__name__}")
    if polydata.n_cells == 0:
        raise InputError("polydata: has no cells")
    scalars = _text(scalars, "scalars")
    if scalars not in polydata.cell_data:
        known = ", ".join(polydata.cell_data.keys()) or "none"
        raise InputError(f"scalars: {scalars!r} is not a cell array of polydata (has: {known})")
    values = np.asarray(polydata.cell_data[scalars])
    if values.ndim != 1 or not np.issubdtype(values.dtype, np.number):
        raise InputError(f"scalars: cell array {scalars!r} must hold one number per cell")
    if not np.isfinite(values).all():
        raise InputError(f"scalars: cell array {scalars!r} must be finite")
    if (
        isinstance(window_size, str)
        or not isinstance(window_size, Sequence)
        or len(window_size) != 2
        or not all(isinstance(v, int | np.integer) and 16 <= v <= 16384 for v in window_size)
    ):
        raise InputError(f"window_size: must be (width, height) in pixels, got {window_size!r}")
    problem = _rendering_problem()
    if problem is not None:
        raise RuntimeError(f"render_stack: cannot render off screen: {problem}")

    mesh = polydata.copy(deep=True)  # the plotter sets active scalars on what it is given
    if np.array_equal(values, np.round(values)):
        mesh.cell_data["colour_index"] = np.mod(values, 20).astype(np.int32)
        colour_by = "colour_index"
        style = {"cmap": _tab20_categorical(), "clim": (-0.5, 19.5), "n_colors": 20}
    else:
        colour_by = scalars
        style = {"cmap": "tab20"}
    (x0, x1, y0, y1, _, z1) = mesh.bounds
    margin = 0.12 * max(x1 - x0, y1 - y0, 1.0)
    conveyor = pyvista.Plane(
        center=((x0 + x1) / 2, (y0 + y1) / 2, 0.0),
        direction=(0.0, 0.0, 1.0),
        i_size=x1 - x0 + 2 * margin,
        j_size=y1 - y0 + 2 * margin,
        i_resolution=1,
        j_resolution=1,
    )
    if "region" in mesh.cell_data:
        what = f"Stack of {len(np.unique(mesh.cell_data['region']))} chips"
    else:
        what = "Stack"

    # VTK logs "bad X server connection" before falling back to an off-screen context: noise
    # on a terminal that should show only the run's own lines.
    with pyvista.vtk_verbosity("off"):
        image = _render(
            pyvista, mesh, conveyor, colour_by, style, what, scalars, window_size, show_edges
        )
    Image.fromarray(np.asarray(image)).save(path, format="PNG")


def _render(pyvista, mesh, conveyor, colour_by, style, what, scalars, window_size, show_edges):
    (x0, x1, y0, y1, _, z1) = mesh.bounds
    plotter = pyvista.Plotter(off_screen=True, window_size=list(map(int, window_size)))
    try:
        plotter.set_background("white")
        plotter.add_mesh(conveyor, color="#e4e4e4", show_edges=False)
        plotter.add_mesh(
            mesh,
            scalars=colour_by,
            preference="cell",
            show_edges=show_edges,
            edge_color="#303030",
            line_width=1,
            show_scalar_bar=False,
            **style,
        )
        plotter.add_text(
            f"{what} on the conveyor, coloured by {scalars}",
            position="upper_edge",
            font_size=12,
            color="black",
        )
        plotter.add_text(
            f"chips: {x1 - x0:.0f} x {y1 - y0:.0f} mm in plan, {z1:.1f} mm high",
            position="lower_left",
            font_size=10,
            color="black",
        )
        plotter.camera_position = "iso"
        plotter.reset_camera(bounds=mesh.bounds)  # frame the chips, the conveyor runs on
        plotter.camera.zoom(1.3)
        return plotter.screenshot(return_img=True)
    finally:
        plotter.close()
