"""PNG figures of the paper's descriptors (section 3) and a 3-D picture of a stack.

Figure 6: :func:`render_stack`; Figure 7: :func:`plot_contact_types`; Figure 9:
:func:`plot_neh_map`; Figure 10: :func:`plot_layer_filling`; Figure 12:
:func:`plot_layer_comparison`; porosity through the thickness: :func:`plot_profile`.

Every function writes exactly the file at ``path`` (PNG, 150 dpi for the charts, whatever
its suffix) and never modifies its inputs. Lengths are in mm. The charts are drawn on a
``matplotlib.figure.Figure`` with its own Agg canvas, so neither pyplot nor the global
matplotlib backend is touched. Bad arguments raise :class:`core.errors.InputError`, a
``ValueError`` whose one-line message starts with the argument's name.
"""

from __future__ import annotations

import functools
import math
import os
import signal
import subprocess
import sys
from collections.abc import Mapping, Sequence
from numbers import Real
from pathlib import Path

import numpy as np
from matplotlib import colormaps
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import BoundaryNorm, ListedColormap
from matplotlib.figure import Figure
from matplotlib.patches import Circle, Patch, Rectangle
from matplotlib.ticker import MaxNLocator
from PIL import Image  # matplotlib's own dependency: imported with it

from chipstack.core.errors import InputError

__all__ = [
    "neh_colormap",
    "plot_contact_types",
    "plot_layer_comparison",
    "plot_layer_filling",
    "plot_mat",
    "plot_neh_map",
    "plot_profile",
    "plot_sweep",
    "render_stack",
]

DPI = 150
CONTACT_KINDS = ("point", "line", "surface")
_CONTACT_COLOURS = {"point": "tab:blue", "line": "tab:red", "surface": "tab:green"}
_NEH_LEVELS = 9  # 0, 1, ..., 7 and 8+
_RENDER_PROBE_TIMEOUT_S = 120


# --------------------------------------------------------------------------- checks


def _path(path: object) -> Path:
    if not isinstance(path, str | os.PathLike) or not str(path):
        raise InputError(f"path: must be a non-empty str or pathlib.Path, got {path!r}")
    return Path(path)


def _vector(
    values: object,
    name: str,
    *,
    length: int | None = None,
    like: str = "",
    integer: bool = False,
    allow_nan: bool = False,
) -> np.ndarray:
    """A float copy of a 1-D array, checked; ``like`` names the argument ``length`` is from."""
    try:
        array = np.array(values, dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"{name}: must be a 1-D array of numbers") from None
    if array.ndim != 1:
        raise InputError(f"{name}: must be 1-D, got shape {array.shape}")
    if length is not None and len(array) != length:
        raise InputError(f"{name}: has length {len(array)}, {like} has {length}")
    bad = np.isinf(array) if allow_nan else ~np.isfinite(array)
    if bad.any():
        raise InputError(f"{name}: must be finite, got {array[bad][0]} at index {_first(bad)}")
    if integer and np.any(array != np.round(array)):
        raise InputError(f"{name}: must hold whole numbers")
    return array


def _first(mask: np.ndarray) -> int:
    return int(np.flatnonzero(mask)[0])


def _increasing(array: np.ndarray, name: str) -> None:
    if np.any(np.diff(array) <= 0):
        raise InputError(f"{name}: must be strictly increasing")


def _positive(value: object, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, Real):
        raise InputError(f"{name}: must be a number, got {value!r}")
    if not (math.isfinite(value) and value > 0):
        raise InputError(f"{name}: must be positive and finite, got {value!r}")
    return float(value)


def _text(value: object, name: str) -> str:
    if not isinstance(value, str):
        raise InputError(f"{name}: must be a str, got {type(value).__name__}")
    return value


def _interval(
    mean: np.ndarray,
    low: object,
    high: object,
    names: tuple[str, str],
    like: str,
) -> tuple[np.ndarray, np.ndarray] | None:
    """Checked (low, high) around ``mean`` or None; NaN in either means 'undefined there'."""
    low_name, high_name = names
    if low is None and high is None:
        return None
    if low is None or high is None:
        missing, given = (low_name, high_name) if low is None else (high_name, low_name)
        raise InputError(f"{missing}: must be given together with {given}")
    lo = _vector(low, low_name, length=len(mean), like=like, allow_nan=True)
    hi = _vector(high, high_name, length=len(mean), like=like, allow_nan=True)
    undefined = np.isnan(lo) | np.isnan(hi)
    lo[undefined] = np.nan
    hi[undefined] = np.nan
    defined = ~undefined
    above = defined & (lo > mean)
    if above.any():
        i = _first(above)
        raise InputError(f"{low_name}: {lo[i]:g} is above the mean {mean[i]:g} at index {i}")
    below = defined & (hi < mean)
    if below.any():
        i = _first(below)
        raise InputError(f"{high_name}: {hi[i]:g} is below the mean {mean[i]:g} at index {i}")
    return lo, hi


def _by_kind(values: object, name: str, length: int) -> dict[str, np.ndarray] | None:
    if values is None:
        return None
    if not isinstance(values, Mapping):
        raise InputError(f"{name}: must be a dict with keys 'point', 'line', 'surface'")
    if set(values) != set(CONTACT_KINDS):
        got = ", ".join(sorted(map(repr, values)))
        raise InputError(
            f"{name}: must have exactly the keys 'point', 'line', 'surface', got {got}"
        )
    return {
        kind: _vector(
            values[kind], f"{name}[{kind!r}]", length=length, like="batches", allow_nan=True
        )
        for kind in CONTACT_KINDS
    }


# --------------------------------------------------------------------------- helpers


def _new_figure(size_in: tuple[float, float]) -> tuple[Figure, object]:
    figure = Figure(figsize=size_in, dpi=DPI, layout="constrained")
    FigureCanvasAgg(figure)
    return figure, figure.add_subplot()


def _save(figure: Figure, path: Path) -> None:
    figure.savefig(path, format="png", dpi=DPI)


def _full_layer_line(ax, full_layer: float) -> None:
    ax.axhline(
        full_layer, color="black", linestyle="--", linewidth=1.2, label=_full_label(full_layer)
    )


def _full_label(full_layer: float) -> str:
    return f"full layer ({full_layer:g} chips)"


def _error_bars(ax, x: np.ndarray, mean: np.ndarray, bounds, label: str | None) -> None:
    """Error bars from (low, high) where both are defined."""
    low, high = bounds
    ok = ~np.isnan(low)
    if not ok.any():
        return
    yerr = np.vstack([mean[ok] - low[ok], high[ok] - mean[ok]])
    ax.errorbar(
        x[ok], mean[ok], yerr=yerr, fmt="none", ecolor="black", elinewidth=1, capsize=3, label=label
    )


def _layer_axes(ax, layers: np.ndarray, top: float) -> None:
    ax.set_xlabel("layer index (from the conveyor up)")
    ax.set_ylabel("chips per layer")
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_xlim(layers.min() - 0.7, layers.max() + 0.7)
    ax.set_ylim(0, 1.12 * top if top > 0 else 1.0)
    ax.grid(axis="y", alpha=0.3)


# --------------------------------------------------------------------------- Figure 7


def plot_contact_types(
    path: str | os.PathLike,
    batches: Sequence[int] | np.ndarray,
    mean: Mapping[str, object],
    low: Mapping[str, object] | None = None,
    high: Mapping[str, object] | None = None,
) -> None:
    """Contacts per chip by contact type against the number of batches deposited (Fig. 7).

    batches: (B,) whole numbers, strictly increasing (NBD, 1..5 in the paper).
    mean: {"point": (B,), "line": (B,), "surface": (B,)}, mean contacts per chip.
    low, high: the same dicts, bounds of the shaded band (e.g. a 95 % confidence interval
    over repeats); both or neither; NaN where a bound is undefined (no band there).
    Lines: point contacts blue, line contacts red, surface contacts green, as in the paper.
    """
    path = _path(path)
    nbd = _vector(batches, "batches", integer=True)
    if len(nbd) == 0:
        raise InputError("batches: must not be empty")
    if np.any(nbd < 0):
        raise InputError("batches: must not be negative")
    _increasing(nbd, "batches")
    means = _by_kind(mean, "mean", len(nbd))
    if means is None:
        raise InputError("mean: must be a dict with keys 'point', 'line', 'surface'")
    for kind, values in means.items():
        if np.isnan(values).any():
            raise InputError(f"mean[{kind!r}]: must be finite")
    if (low is None) != (high is None):
        missing, given = ("low", "high") if low is None else ("high", "low")
        raise InputError(f"{missing}: must be given together with {given}")
    lows = _by_kind(low, "low", len(nbd))
    highs = _by_kind(high, "high", len(nbd))
    bands = {
        kind: _interval(
            means[kind],
            None if lows is None else lows[kind],
            None if highs is None else highs[kind],
            (f"low[{kind!r}]", f"high[{kind!r}]"),
            "batches",
        )
        for kind in CONTACT_KINDS
    }

    figure, ax = _new_figure((6.4, 4.8))
    handles = []
    for kind in CONTACT_KINDS:
        colour = _CONTACT_COLOURS[kind]
        if bands[kind] is not None:
            ax.fill_between(nbd, *bands[kind], color=colour, alpha=0.2, linewidth=0)
        (line,) = ax.plot(
            nbd, means[kind], color=colour, marker="o", linewidth=2, label=f"{kind} contacts"
        )
        handles.append(line)
    if any(band is not None for band in bands.values()):
        handles.append(Patch(color="grey", alpha=0.3, label="shaded: low to high (e.g. 95 % CI)"))
    ax.legend(handles=handles, loc="best")
    ax.set_xlabel("number of batches deposited (NBD)")
    ax.set_ylabel("contacts per chip")
    ax.set_title("Contact types per chip during deposition")
    ax.set_xticks(nbd)
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    _save(figure, path)


# --------------------------------------------------------------------------- Figure 9


def neh_colormap() -> tuple[ListedColormap, BoundaryNorm]:
    """(cmap, norm) of the NEH map: 0 light yellow, 1 ... 7, then 8 and above dark red.

    Nine colours sampled from matplotlib's "YlOrRd"; ``cmap(norm(k))`` is the colour of k
    chips; values above 8 take the colour of 8.
    """
    colours = colormaps["YlOrRd"](np.linspace(0.0, 1.0, _NEH_LEVELS))
    cmap = ListedColormap(colours, name="neh").with_extremes(over=colours[-1], under=colours[0])
    norm = BoundaryNorm(np.arange(_NEH_LEVELS + 1) - 0.5, _NEH_LEVELS, clip=True)
    return cmap, norm


def plot_neh_map(
    path: str | os.PathLike,
    x_edges: Sequence[float] | np.ndarray,
    y_edges: Sequence[float] | np.ndarray,
    neh: np.ndarray,
    target_size_mm: float,
) -> None:
    """Local stack thickness: chips crossed by a vertical ray in each pixel (Fig. 9).

    x_edges: (nx + 1,) mm and y_edges: (ny + 1,) mm, strictly increasing pixel edges.
    neh: (nx, ny) whole numbers >= 0; pixel (i, j) spans x_edges[i]..x_edges[i + 1] and
    y_edges[j]..y_edges[j + 1]. Colours: :func:`neh_colormap` (8 and above share one).
    target_size_mm: side of the target square centred on (0, 0), drawn dashed in black.
    """
    path = _path(path)
    xe = _vector(x_edges, "x_edges")
    ye = _vector(y_edges, "y_edges")
    for edges, name in ((xe, "x_edges"), (ye, "y_edges")):
        if len(edges) < 2:
            raise InputError(f"{name}: needs at least 2 edges, got {len(edges)}")
        _increasing(edges, name)
    try:
        counts = np.array(neh, dtype=float)
    except (TypeError, ValueError):
        raise InputError("neh: must be a 2-D array of numbers") from None
    expected = (len(xe) - 1, len(ye) - 1)
    if counts.shape != expected:
        raise InputError(
            f"neh: has shape {counts.shape}, the edges give {expected} (len(x_edges) - 1, "
            "len(y_edges) - 1)"
        )
    if not np.isfinite(counts).all():
        raise InputError("neh: must be finite")
    if np.any(counts < 0):
        raise InputError(f"neh: must not be negative, got {counts.min():g}")
    if np.any(counts != np.round(counts)):
        raise InputError("neh: must hold whole numbers")
    side = _positive(target_size_mm, "target_size_mm")

    cmap, norm = neh_colormap()
    figure, ax = _new_figure((7.0, 6.0))
    mesh = ax.pcolormesh(
        xe, ye, np.minimum(counts, _NEH_LEVELS - 1).T, cmap=cmap, norm=norm, shading="flat"
    )
    half = side / 2
    ax.add_patch(
        Rectangle(
            (-half, -half), side, side, fill=False, edgecolor="black", linestyle="--", linewidth=1.5
        )
    )
    margin = 0.03 * max(xe[-1] - xe[0], ye[-1] - ye[0], side)
    ax.set_xlim(min(xe[0], -half) - margin, max(xe[-1], half) + margin)
    ax.set_ylim(min(ye[0], -half) - margin, max(ye[-1], half) + margin)
    ax.set_aspect("equal")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_title(f"Local stack thickness (NEH); dashed: {side:g} mm target")
    colourbar = figure.colorbar(mesh, ax=ax, ticks=np.arange(_NEH_LEVELS), shrink=0.85)
    colourbar.set_ticklabels([str(k) for k in range(_NEH_LEVELS - 1)] + [f"{_NEH_LEVELS - 1}+"])
    colourbar.set_label("NEH: chips crossed by a vertical ray")
    _save(figure, path)


# --------------------------------------------------------------------------- Figures 10, 12


def plot_layer_filling(
    path: str | os.PathLike,
    layers: Sequence[int] | np.ndarray,
    mean: Sequence[float] | np.ndarray,
    full_layer: float,
    low: Sequence[float] | np.ndarray | None = None,
    high: Sequence[float] | np.ndarray | None = None,
    label: str | None = None,
) -> None:
    """Chips per layer against the layer index, with the full-layer level (Fig. 10).

    layers: (L,) strictly increasing whole numbers (layer k spans k h .. (k + 1) h above
    the conveyor, h = 2 mm in the paper). mean: (L,) chips per layer (>= 0).
    full_layer: chips in a full layer (target area / chip area, 56.25 for 20 mm squares
    on 150 mm), drawn as a dashed line. low, high: (L,) error-bar bounds, both or neither,
    low <= mean <= high, NaN where undefined. label: legend entry of the bars.
    """
    path = _path(path)
    index = _layer_index(layers)
    counts = _vector(mean, "mean", length=len(index), like="layers")
    if np.any(counts < 0):
        raise InputError("mean: must not be negative")
    bounds = _interval(counts, low, high, ("low", "high"), "layers")
    full = _positive(full_layer, "full_layer")
    label = "chips per layer" if label is None else _text(label, "label")

    figure, ax = _new_figure((6.4, 4.8))
    ax.bar(index, counts, width=0.8, color="tab:blue", label=label)
    if bounds is not None:
        _error_bars(ax, index, counts, bounds, "low to high")
    _full_layer_line(ax, full)
    top = max(full, np.nanmax(bounds[1], initial=0.0) if bounds else 0.0, counts.max())
    _layer_axes(ax, index, top)
    ax.set_title("Layer filling: chips per layer (by centre of mass)")
    ax.legend(loc="upper right")
    _save(figure, path)


def _layer_index(layers: object, name: str = "layers") -> np.ndarray:
    index = _vector(layers, name, integer=True)
    if len(index) == 0:
        raise InputError(f"{name}: must not be empty")
    _increasing(index, name)
    return index


def plot_layer_comparison(
    path: str | os.PathLike,
    layers: Sequence[int] | np.ndarray | None,
    series: Sequence[tuple],
    full_layer: float,
) -> None:
    """Chips per layer of several stacks side by side, with the full-layer level (Fig. 12).

    series: [(label, mean (n,), low (n,) or None, high (n,) or None), ...], e.g. square
    and rectangular chips; low/high as in :func:`plot_layer_filling`. A series shorter
    than ``layers`` is padded with zeros (layers above a stack's top are empty).
    layers: (L,) strictly increasing whole numbers, L at least the longest series; None
    for 0 .. L - 1 with L the longest series. full_layer: chips in a full layer.
    """
    path = _path(path)
    if isinstance(series, str | bytes | Mapping) or not isinstance(series, Sequence):
        raise InputError("series: must be a list of (label, mean, low, high) tuples")
    if len(series) == 0:
        raise InputError("series: must not be empty")
    checked = []
    for k, entry in enumerate(series):
        name = f"series[{k}]"
        if isinstance(entry, str) or not isinstance(entry, Sequence) or len(entry) != 4:
            raise InputError(f"{name}: must be a (label, mean, low, high) tuple")
        label, mean, low, high = entry
        label = _text(label, f"{name} label")
        counts = _vector(mean, f"{name} mean")
        if np.any(counts < 0):
            raise InputError(f"{name} mean: must not be negative")
        bounds = _interval(counts, low, high, (f"{name} low", f"{name} high"), f"{name} mean")
        checked.append((name, label, counts, bounds))
    longest = max(len(counts) for _, _, counts, _ in checked)
    if layers is None:
        if longest == 0:
            raise InputError("series: every mean is empty")
        index = np.arange(longest, dtype=float)
    else:
        index = _layer_index(layers)
    for name, _, counts, _ in checked:
        if len(counts) > len(index):
            raise InputError(f"{name}: has {len(counts)} layers, layers has only {len(index)}")
    full = _positive(full_layer, "full_layer")

    figure, ax = _new_figure((7.2, 4.8))
    width = 0.8 / len(checked)
    colours = colormaps["tab10"].colors
    top = full
    bar_label = "low to high"  # on the first error bars only
    for k, (_, label, counts, bounds) in enumerate(checked):
        padded = _pad(counts, len(index), 0.0)
        x = index + (k - (len(checked) - 1) / 2) * width
        ax.bar(x, padded, width=width, color=colours[k % len(colours)], label=label)
        if bounds is not None:
            lo, hi = (_pad(b, len(index), 0.0) for b in bounds)
            _error_bars(ax, x, padded, (lo, hi), bar_label)
            bar_label = None
            top = max(top, np.nanmax(hi, initial=0.0))
        top = max(top, padded.max())
    _full_layer_line(ax, full)
    _layer_axes(ax, index, top)
    ax.set_title("Layer filling compared: chips per layer")
    ax.legend(loc="upper right")
    _save(figure, path)


def _pad(values: np.ndarray, length: int, fill: float) -> np.ndarray:
    out = np.full(length, fill)
    out[: len(values)] = values
    return out


# --------------------------------------------------------------------------- profiles


def plot_profile(
    path: str | os.PathLike,
    z: Sequence[float] | np.ndarray,
    values: Sequence[float] | np.ndarray,
    xlabel: str,
    title: str,
    label: str | None = None,
) -> None:
    """A quantity through the stack's thickness (e.g. porosity): values across, z up.

    values: (n,) the quantity per slab (x axis, labelled ``xlabel`` with its unit).
    z: (n + 1,) mm slab edges, or (n,) mm slab centres (edges then halfway between centres,
    a lone centre c > 0 taken as the slab 0 .. 2 c); strictly increasing. Drawn as steps,
    constant over each slab.
    label: legend entry of the line (no legend when None).
    """
    path = _path(path)
    quantity = _vector(values, "values")
    if len(quantity) == 0:
        raise InputError("values: must not be empty")
    heights = _vector(z, "z")
    _increasing(heights, "z")
    if len(heights) == len(quantity) + 1:
        edges = heights
    elif len(heights) == len(quantity):
        if len(heights) >= 2:
            middle = (heights[:-1] + heights[1:]) / 2
            edges = np.concatenate(
                [[heights[0] - (middle[0] - heights[0])], middle, [2 * heights[-1] - middle[-1]]]
            )
        elif heights[0] > 0:  # one slab: taken to start on the conveyor
            edges = np.array([0.0, 2 * heights[0]])
        else:
            raise InputError("z: a single centre must be above 0 mm, or pass the 2 slab edges")
    else:
        raise InputError(
            f"z: has length {len(heights)}, values has {len(quantity)} (z: centres or edges)"
        )
    xlabel = _text(xlabel, "xlabel")
    title = _text(title, "title")
    label = None if label is None else _text(label, "label")

    figure, ax = _new_figure((5.0, 6.0))
    ax.stairs(quantity, edges, orientation="horizontal", baseline=None, linewidth=2, label=label)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("height z (mm)")
    ax.set_ylim(edges[0], edges[-1])
    ax.set_title(title)
    ax.grid(alpha=0.3)
    if label is not None:
        ax.legend(loc="best")
    _save(figure, path)


# --------------------------------------------------------------------------- Figure 6

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


def plot_drops(path: object, xy: np.ndarray, statistics: Mapping, yaw_deg: float = 0.0) -> Path:
    """Fig. 15: final positions of dropped chips (mm) with the disc holding 95 % of them
    and the chip's corner directions at release (dashed), the 4-fold axis (solid)."""
    path = _path(path)
    xy = np.asarray(xy, dtype=float).reshape(-1, 2)
    if not np.isfinite(xy).all():
        raise InputError("xy: positions hold NaN or infinite values")
    figure, ax = _new_figure((5.2, 5.2))
    radius = float(statistics["disc95_mm"])
    ax.add_patch(
        Circle(
            (0, 0),
            radius,
            fill=False,
            color="tab:red",
            lw=1.5,
            label=f"95 % disc, r = {radius:.1f} mm",
        )
    )
    ax.scatter(xy[:, 0], xy[:, 1], s=14, color="tab:red", alpha=0.8, label="final positions")
    reach = max(radius, float(np.abs(xy).max(initial=1.0))) * 1.1
    for k in range(4):
        angle = math.radians(yaw_deg + 45 + 90 * k)
        ax.plot(
            [0, reach * math.cos(angle)],
            [0, reach * math.sin(angle)],
            ls="--",
            color="0.5",
            lw=0.8,
            label="corner directions" if k == 0 else None,
        )
        axis = math.radians(float(statistics["axis_deg"]) + 90 * k)
        ax.plot(
            [0, reach * math.cos(axis)],
            [0, reach * math.sin(axis)],
            color="tab:blue",
            lw=0.8,
            label="4-fold axis of the scatter" if k == 0 else None,
        )
    ax.set_xlim(-reach, reach)
    ax.set_ylim(-reach, reach)
    ax.set_aspect("equal")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_title(
        f"{statistics['drops']} drops: anisotropy {statistics['anisotropy']:.2f} "
        f"(p = {statistics['anisotropy_p']:.2g})",
        fontsize=9,
    )
    ax.legend(loc="upper right", fontsize=7)
    _save(figure, path)
    return path


def plot_force_displacement(path: str | os.PathLike, press_mm, force_n) -> None:
    """The platen force against the press of a compaction, from (0, 0)."""
    path = _path(path)
    press, force = _vector(press_mm, "press_mm"), _vector(force_n, "force_n")
    if len(press) != len(force) or not len(press):
        raise InputError("press_mm, force_n: need the same, non-zero number of values")
    figure, ax = _new_figure((6.0, 4.5))
    ax.plot(np.concatenate([[0.0], press]), np.concatenate([[0.0], force]), "o-", linewidth=2)
    ax.set_xlabel("press of the top platen (mm)")
    ax.set_ylabel("platen force (N)")
    ax.set_title("Compaction of the stack")
    ax.grid(alpha=0.3)
    _save(figure, path)


def plot_mat(path: object, record: Mapping) -> Path:
    """A poured mat (``mat.json``'s record): areal-weight map over the belt (g/m^2), the
    thickness profiles along and across the belt (mm), and the chips' in-plane angles
    from the belt's direction of travel."""
    path = _path(path)
    weight, thickness = record["areal_weight"], record["thickness"]
    orientation = record["orientation"]
    figure = Figure(figsize=(11.0, 6.4), dpi=DPI, layout="constrained")
    FigureCanvasAgg(figure)
    grid = figure.add_gridspec(2, 3)
    ax = figure.add_subplot(grid[0, :])
    x_edges, y_edges = np.asarray(weight["x_edges_mm"]), np.asarray(weight["y_edges_mm"])
    mesh = ax.pcolormesh(
        x_edges, y_edges, np.asarray(weight["map_g_m2"]).T, cmap="viridis", shading="flat"
    )
    figure.colorbar(mesh, ax=ax, label="areal weight (g/m$^2$)")
    ax.set_aspect("equal")
    ax.set_xlabel("x along the belt (mm)")
    ax.set_ylabel("y across (mm)")
    ax.set_title(
        f"areal weight over {weight['cell_mm']:g} mm cells: mean {weight['mean_g_m2']:.0f} "
        f"g/m$^2$, CV {weight['cv']:.3f}"
    )
    ax = figure.add_subplot(grid[1, 0])
    ax.plot(thickness["along_x_mm"], thickness["along_mm"], color="tab:blue")
    ax.set_xlabel("x along the belt (mm)")
    ax.set_ylabel("mean top height (mm)")
    ax.set_title(f"along the belt, CV {thickness['cv_along']:.3f}")
    ax = figure.add_subplot(grid[1, 1])
    ax.plot(thickness["across_y_mm"], thickness["across_mm"], color="tab:red")
    ax.set_xlabel("y across the belt (mm)")
    ax.set_ylabel("mean top height (mm)")
    ax.set_title(f"across the belt, CV {thickness['cv_across']:.3f}")
    ax = figure.add_subplot(grid[1, 2])
    edges = np.asarray(orientation["angle_edges_deg"])
    ax.bar(
        edges[:-1],
        orientation["angle_fraction"],
        width=np.diff(edges),
        align="edge",
        color="tab:green",
        edgecolor="white",
    )
    ax.set_xlabel("chip x axis from the belt direction (deg)")
    ax.set_ylabel("fraction of chips")
    ax.set_title(f"<cos 2θ> = {orientation['order_cos2']:.3f}")
    _save(figure, path)
    return path


def plot_sweep(path: object, record: Mapping, key: str, columns: int = 5) -> Path:
    """Every scalar of a sweep (``sweep.json``'s record) against the swept ``key``: the
    mean over the repeats and its 95 % interval at each point, one line for each
    combination of the other swept keys."""
    path = _path(path)
    points = record["points"]
    others = [k for k in record["keys"] if k != key]
    names = sorted({n for p in points for n, s in p["scalars"].items() if s["mean"] is not None})
    if not names:
        raise InputError("record: the sweep has no scalar to draw")
    rows = math.ceil(len(names) / columns)
    figure = Figure(figsize=(3.2 * columns, 2.4 * rows), dpi=DPI, layout="constrained")
    FigureCanvasAgg(figure)
    values = [p["values"][key] for p in points]
    numeric = all(isinstance(v, int | float) and not isinstance(v, bool) for v in values)
    order = sorted(set(values), key=lambda v: v if numeric else str(v))
    groups: dict[tuple, list[Mapping]] = {}
    for p in points:
        groups.setdefault(tuple(p["values"][k] for k in others), []).append(p)
    for index, name in enumerate(names):
        ax = figure.add_subplot(rows, columns, index + 1)
        for label, members in groups.items():
            members = sorted(members, key=lambda p: order.index(p["values"][key]))
            x = [p["values"][key] if numeric else order.index(p["values"][key]) for p in members]
            stats = [p["scalars"].get(name, {}) for p in members]
            mean = np.array([np.nan if s.get("mean") is None else s["mean"] for s in stats])
            low = np.array([np.nan if s.get("ci_low") is None else s["ci_low"] for s in stats])
            high = np.array([np.nan if s.get("ci_high") is None else s["ci_high"] for s in stats])
            text = ", ".join(f"{k}={v}" for k, v in zip(others, label, strict=True))
            ax.errorbar(
                x,
                mean,
                yerr=[np.nan_to_num(mean - low), np.nan_to_num(high - mean)],
                marker="o",
                ms=3,
                capsize=2,
                label=text or None,
            )
        unit = next((p["scalars"][name].get("unit") for p in points if name in p["scalars"]), "")
        ax.set_title(name + (f" ({unit})" if unit else ""), fontsize=7)
        ax.tick_params(labelsize=6)
        if not numeric:
            ax.set_xticks(range(len(order)), [str(v) for v in order])
        if others and index == 0:
            ax.legend(fontsize=5)
    figure.suptitle(
        f"{record['scenario']}: every scalar against {key} (mean and 95 % interval over "
        f"{record['repeats']} repeats)",
        fontsize=9,
    )
    _save(figure, path)
    return path
