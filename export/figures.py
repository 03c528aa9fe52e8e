"""PNG figures of the paper's descriptors (section 3), and the checks and canvas every
chart of the package is drawn with (the 3-D picture of a stack is :mod:`export.render`,
the process's figures :mod:`export.process_figures`).

Figure 7: :func:`plot_contact_types`; Figure 9:
:func:`plot_neh_map`; Figure 10: :func:`plot_layer_filling`; Figure 12:
:func:`plot_layer_comparison`; porosity through the thickness: :func:`plot_profile`.

Every function writes exactly the file at ``path`` (PNG, 150 dpi for the charts, whatever
its suffix) and never modifies its inputs. Lengths are in mm. The charts are drawn on a
``matplotlib.figure.Figure`` with its own Agg canvas, so neither pyplot nor the global
matplotlib backend is touched. Bad arguments raise :class:`core.errors.InputError`, a
``ValueError`` whose one-line message starts with the argument's name.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from numbers import Real
from pathlib import Path

import numpy as np
from matplotlib import colormaps
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import BoundaryNorm, ListedColormap
from matplotlib.figure import Figure
from matplotlib.patches import Patch, Rectangle
from matplotlib.ticker import MaxNLocator

from chipstack.core.errors import InputError

__all__ = [
    "neh_colormap",
    "plot_contact_types",
    "plot_layer_comparison",
    "plot_layer_filling",
    "plot_neh_map",
    "plot_profile",
]

DPI = 150
CONTACT_KINDS = ("point", "line", "surface")
_CONTACT_COLOURS = {"point": "tab:blue", "line": "tab:red", "surface": "tab:green"}
_NEH_LEVELS = 9  # 0, 1, ..., 7 and 8+


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
