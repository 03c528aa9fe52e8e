"""The figure writers: real PNGs read back, what is drawn, bad inputs, inputs left alone."""

from __future__ import annotations

import copy
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import pyvista  # a dependency (pyproject.toml): imported, never skipped
from matplotlib.figure import Figure
from matplotlib.image import imread
from parts import needs

import chipstack.export.render as render
from chipstack.export.figures import (
    neh_colormap,
    plot_contact_types,
    plot_layer_comparison,
    plot_layer_filling,
    plot_neh_map,
    plot_profile,
)
from chipstack.export.render import render_stack

ROOT = Path(__file__).resolve().parents[1]
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
DPI = 150

BATCHES = np.arange(1, 6)
MEAN = {
    "point": np.array([0.6, 0.8, 0.9, 1.0, 1.0]),
    "line": np.array([0.2, 0.35, 0.45, 0.5, 0.5]),
    "surface": np.array([0.1, 0.3, 0.4, 0.5, 0.5]),
}
LOW = {kind: values - 0.1 for kind, values in MEAN.items()}
HIGH = {kind: values + 0.1 for kind, values in MEAN.items()}
LAYER_MEAN = np.array([45.0, 40, 35, 28, 20, 12, 6, 2, 1, 0])


@pytest.fixture
def saved(monkeypatch) -> list[Figure]:
    """Every matplotlib Figure saved during the test, to look at what was drawn."""
    figures_saved: list[Figure] = []
    original = Figure.savefig

    def spy(self, *args, **kwargs):
        figures_saved.append(self)
        return original(self, *args, **kwargs)

    monkeypatch.setattr(Figure, "savefig", spy)
    return figures_saved


def read_png(path: Path) -> np.ndarray:
    """(height, width, 3) floats in 0..1; the file must be a PNG whatever its suffix."""
    assert path.read_bytes()[:8] == PNG_SIGNATURE
    with path.open("rb") as handle:
        image = imread(handle, format="png")
    return image[..., :3]


def assert_picture(path: Path, size_in: tuple[float, float]) -> np.ndarray:
    image = read_png(path)
    assert image.shape[:2] == (round(size_in[1] * DPI), round(size_in[0] * DPI))
    colours = np.unique((image * 255).round().astype(np.uint8).reshape(-1, 3), axis=0)
    assert len(colours) > 20, "a near-blank picture"
    return image


def near(image: np.ndarray, colour, tolerance: float = 0.06) -> int:
    """Pixels within ``tolerance`` of an RGB colour (0..1) on every channel."""
    return int(np.all(np.abs(image - np.asarray(colour)[:3]) < tolerance, axis=-1).sum())


# --- NEH colours -------------------------------------------------------------------------


def test_neh_colormap_levels():
    cmap, norm = neh_colormap()
    zero, eight, twenty = (np.asarray(cmap(norm(v))) for v in (0, 8, 20))
    assert np.all(zero[:3] > [0.95, 0.95, 0.7])  # light yellow
    assert eight[0] > 0.45 and eight[1] < 0.1 and eight[2] < 0.2  # dark red
    np.testing.assert_array_equal(eight, twenty)
    levels = np.array([cmap(norm(k)) for k in range(9)])
    assert len(np.unique(levels, axis=0)) == 9
    assert np.all(np.diff(levels[:, 1]) <= 0)  # darker (less green) with every chip


# --- Figure 7 ----------------------------------------------------------------------------


@pytest.mark.parametrize("bands", [True, False])
def test_contact_types_png(tmp_path, saved, bands):
    path = tmp_path / "contacts.png"
    if bands:
        plot_contact_types(path, BATCHES, MEAN, LOW, HIGH)
    else:
        plot_contact_types(path, BATCHES, MEAN)
    image = assert_picture(path, (6.4, 4.8))
    for colour in ("#1f77b4", "#d62728", "#2ca02c"):  # point blue, line red, surface green
        rgb = [int(colour[i : i + 2], 16) / 255 for i in (1, 3, 5)]
        assert near(image, rgb) > 50
    (ax,) = [a for a in saved[0].axes]
    assert ax.get_xlabel() == "number of batches deposited (NBD)"
    assert ax.get_ylabel() == "contacts per chip"
    assert ax.get_title()
    lines = {line.get_label(): line for line in ax.get_lines()}
    np.testing.assert_allclose(lines["line contacts"].get_ydata(), MEAN["line"])
    assert len(ax.collections) == (3 if bands else 0)


# --- Figure 9 ----------------------------------------------------------------------------


def test_neh_map_png(tmp_path, saved):
    x_edges = np.arange(-90.0, 91.0, 3.0)
    y_edges = np.arange(-90.0, 91.0, 3.0)
    neh = np.zeros((60, 60), dtype=int)
    neh[30:, :] = 20  # right half: well beyond 8
    neh[5, 50] = 3
    path = tmp_path / "neh.png"
    plot_neh_map(path, x_edges, y_edges, neh, 150.0)
    image = assert_picture(path, (7.0, 6.0))
    cmap, norm = neh_colormap()
    assert near(image, cmap(norm(0)), 0.02) > 5000
    assert near(image, cmap(norm(8)), 0.02) > 5000
    ax = saved[0].axes[0]
    drawn = np.asarray(ax.collections[0].get_array()).reshape(60, 60)
    np.testing.assert_array_equal(drawn, np.minimum(neh, 8).T)  # rows are y
    assert drawn[50, 5] == 3
    assert ax.get_xlabel() == "x (mm)" and ax.get_ylabel() == "y (mm)"
    (target,) = ax.patches
    assert target.get_xy() == (-75.0, -75.0) and target.get_width() == 150.0
    assert target.get_linestyle() == "--"
    colourbar_axes = saved[0].axes[1]
    labels = [t.get_text() for t in colourbar_axes.get_yticklabels()]
    assert labels == ["0", "1", "2", "3", "4", "5", "6", "7", "8+"]


# --- Figures 10 and 12 -------------------------------------------------------------------


def test_layer_filling_png(tmp_path, saved):
    layers = np.arange(len(LAYER_MEAN))
    path = tmp_path / "filling.png"
    plot_layer_filling(
        path, layers, LAYER_MEAN, 56, LAYER_MEAN * 0.9, LAYER_MEAN * 1.1, label="squares"
    )
    assert_picture(path, (6.4, 4.8))
    ax = saved[0].axes[0]
    heights = [bar.get_height() for bar in ax.patches]
    np.testing.assert_allclose(heights, LAYER_MEAN)
    labels = ax.get_legend_handles_labels()[1]
    assert "full layer (56 chips)" in labels and "squares" in labels
    (full,) = [line for line in ax.get_lines() if line.get_label().startswith("full layer")]
    assert full.get_linestyle() == "--" and set(full.get_ydata()) == {56}
    assert ax.get_ylim()[1] > 56
    assert ax.get_ylabel() == "chips per layer" and "layer" in ax.get_xlabel()


def test_layer_filling_without_bounds_and_with_undefined_ones(tmp_path):
    layers = np.arange(3)
    plot_layer_filling(tmp_path / "a.png", layers, [3, 2, 1], 56.25)
    low, high = np.array([2.0, np.nan, 0.5]), np.array([4.0, np.nan, 1.5])
    plot_layer_filling(tmp_path / "b.png", layers, [3, 2, 1], 56.25, low, high)
    assert_picture(tmp_path / "b.png", (6.4, 4.8))


def test_layer_comparison_pads_shorter_series(tmp_path, saved):
    square = LAYER_MEAN[:8]
    rectangle = np.array([30.0, 28, 25, 22, 18, 15, 12, 9, 6, 3, 2, 1])
    path = tmp_path / "comparison.png"
    series = [
        ("square 20 x 20 mm", square, square - 1, square + 1),
        ("rectangle 40 x 10 mm", rectangle, None, None),
    ]
    plot_layer_comparison(path, np.arange(12), series, 56.25)
    assert_picture(path, (7.2, 4.8))
    ax = saved[0].axes[0]
    heights = np.array([bar.get_height() for bar in ax.patches])
    assert len(heights) == 24
    np.testing.assert_allclose(heights[:12], np.concatenate([square, np.zeros(4)]))
    np.testing.assert_allclose(heights[12:], rectangle)
    x = np.array([bar.get_x() + bar.get_width() / 2 for bar in ax.patches])
    assert np.all(x[:12] < x[12:])  # side by side, square on the left of each layer
    labels = ax.get_legend_handles_labels()[1]
    assert {"square 20 x 20 mm", "rectangle 40 x 10 mm", "full layer (56.25 chips)"} <= set(labels)
    # layers=None: 0 .. longest - 1
    plot_layer_comparison(tmp_path / "none.png", None, series, 56.25)
    assert len(saved[1].axes[0].patches) == 24


# --- porosity profile --------------------------------------------------------------------


@pytest.mark.parametrize("as_centres", [False, True])
def test_profile_png(tmp_path, saved, as_centres):
    porosity = np.array([0.3, 0.35, 0.45, 0.6, 0.8])
    edges = np.arange(0.0, 11.0, 2.0)
    z = (edges[:-1] + edges[1:]) / 2 if as_centres else edges
    path = tmp_path / "profile.png"
    plot_profile(path, z, porosity, "porosity (-)", "Porosity profile", label="stack 1")
    assert_picture(path, (5.0, 6.0))
    ax = saved[0].axes[0]
    (steps,) = ax.patches
    np.testing.assert_allclose(steps.get_data().edges, edges)
    np.testing.assert_allclose(steps.get_data().values, porosity)
    assert ax.get_ylabel() == "height z (mm)" and ax.get_xlabel() == "porosity (-)"
    assert ax.get_title() == "Porosity profile"


def test_profile_of_a_single_layer(tmp_path, saved):
    plot_profile(tmp_path / "one.png", [1.0], [0.4], "porosity (-)", "one layer")
    np.testing.assert_allclose(saved[0].axes[0].patches[0].get_data().edges, [0.0, 2.0])


# --- paths, global state -----------------------------------------------------------------


def test_writes_exactly_the_path_given(tmp_path):
    target = tmp_path / "sub" / "figure.out"
    target.parent.mkdir()
    plot_profile(str(target), [0.0, 2.0, 4.0], [0.5, 0.7], "porosity (-)", "t")
    assert sorted(p.name for p in target.parent.iterdir()) == ["figure.out"]
    read_png(target)


def test_matplotlib_global_state_untouched(tmp_path):
    script = textwrap.dedent(
        f"""
        import sys, matplotlib
        # the raw rcParams entry: matplotlib.get_backend() would resolve it through pyplot
        before = dict.__getitem__(matplotlib.rcParams, "backend")
        import chipstack.export.figures as f
        f.plot_profile({str(tmp_path / "p.png")!r}, [0, 1, 2], [0.1, 0.2], "x (-)", "t")
        f.plot_contact_types(
            {str(tmp_path / "c.png")!r}, [1, 2],
            {{"point": [1, 1], "line": [0, 1], "surface": [0, 0]}},
        )
        assert "matplotlib.pyplot" not in sys.modules, "pyplot imported"
        assert dict.__getitem__(matplotlib.rcParams, "backend") == before, "backend changed"
        """
    )
    result = subprocess.run(
        [sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=300
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout == ""


# --- bad inputs --------------------------------------------------------------------------

GOOD_EDGES = np.arange(0.0, 13.0, 3.0)  # 4 pixels
GOOD_NEH = np.zeros((4, 4), dtype=int)


def _contacts(**change):
    kwargs = {"batches": BATCHES, "mean": MEAN, "low": None, "high": None} | change
    return lambda path: plot_contact_types(path, **kwargs)


def _neh(**change):
    kwargs = {
        "x_edges": GOOD_EDGES,
        "y_edges": GOOD_EDGES,
        "neh": GOOD_NEH,
        "target_size_mm": 150.0,
    } | change
    return lambda path: plot_neh_map(path, **kwargs)


def _filling(**change):
    kwargs = {"layers": np.arange(3), "mean": [3, 2, 1], "full_layer": 56.0} | change
    return lambda path: plot_layer_filling(path, **kwargs)


def _comparison(**change):
    kwargs = {
        "layers": np.arange(3),
        "series": [("a", [3, 2, 1], None, None)],
        "full_layer": 56.0,
    } | change
    return lambda path: plot_layer_comparison(path, **kwargs)


def _profile(**change):
    kwargs = {"z": [0, 2, 4], "values": [0.3, 0.5], "xlabel": "porosity (-)", "title": "t"} | change
    return lambda path: plot_profile(path, **kwargs)


BAD = {
    "batches not 1-D": (_contacts(batches=[[1, 2, 3, 4, 5]]), "batches"),
    "batches not whole": (_contacts(batches=[1, 2, 3.5, 4, 5]), "batches"),
    "batches unsorted": (_contacts(batches=[1, 3, 2, 4, 5]), "batches"),
    "mean length": (_contacts(mean=MEAN | {"line": [0.2, 0.3]}), r"mean\['line'\]"),
    "mean key": (_contacts(mean={"points": [1] * 5, "line": [1] * 5, "surface": [1] * 5}), "mean"),
    "mean nan": (_contacts(mean=MEAN | {"point": [np.nan] * 5}), r"mean\['point'\]"),
    "low alone": (_contacts(low=LOW), "high"),
    "high below mean": (
        _contacts(low=LOW, high=HIGH | {"surface": MEAN["surface"] - 0.2}),
        r"high\['surface'\]",
    ),
    "x_edges length": (_neh(x_edges=GOOD_EDGES[:-1]), "neh"),
    "x_edges unsorted": (_neh(x_edges=GOOD_EDGES[::-1]), "x_edges"),
    "y_edges 2-D": (_neh(y_edges=np.ones((2, 5))), "y_edges"),
    "neh 1-D": (_neh(neh=np.zeros(16)), "neh"),
    "neh negative": (_neh(neh=np.full((4, 4), -1)), "neh"),
    "neh fractional": (_neh(neh=np.full((4, 4), 0.5)), "neh"),
    "target zero": (_neh(target_size_mm=0.0), "target_size_mm"),
    "target text": (_neh(target_size_mm="150"), "target_size_mm"),
    "layers mismatch": (_filling(mean=[3, 2]), "mean"),
    "layers empty": (_filling(layers=[], mean=[]), "layers"),
    "negative count": (_filling(mean=[3, -2, 1]), "mean"),
    "low above mean": (_filling(low=[4, 1, 0], high=[5, 3, 2]), "low"),
    "full layer negative": (_filling(full_layer=-1.0), "full_layer"),
    "label not text": (_filling(label=3), "label"),
    "series empty": (_comparison(series=[]), "series"),
    "series not tuples": (_comparison(series=[[3, 2, 1]]), r"series\[0\]"),
    "series too long": (
        _comparison(series=[("a", [1, 1, 1], None, None), ("b", [1, 1, 1, 1], None, None)]),
        r"series\[1\]",
    ),
    "series high alone": (_comparison(series=[("a", [3, 2, 1], None, [4, 3, 2])]), r"series\[0\]"),
    "z length": (_profile(z=[0, 2, 4, 6, 8]), "z"),
    "z unsorted": (_profile(z=[0, 4, 2]), "z"),
    "z single centre at 0": (_profile(z=[0.0], values=[0.3]), "z"),
    "values 2-D": (_profile(values=[[0.3, 0.5]]), "values"),
    "xlabel not text": (_profile(xlabel=None), "xlabel"),
    "path not a path": (lambda path: plot_profile(3, [0, 2, 4], [0.3, 0.5], "x", "t"), "path"),
}


@pytest.mark.parametrize("case", BAD.values(), ids=BAD.keys())
def test_bad_inputs_name_the_argument(tmp_path, case):
    call, name = case
    path = tmp_path / "bad.png"
    with pytest.raises(ValueError, match=rf"^{name}(?=[: ])") as error:
        call(path)
    assert "\n" not in str(error.value)
    assert not path.exists()


# --- inputs left alone -------------------------------------------------------------------


def _frozen(array) -> np.ndarray:
    array = np.array(array)
    array.setflags(write=False)
    return array


def test_inputs_not_modified(tmp_path):
    batches = _frozen(BATCHES)
    mean = {kind: _frozen(v) for kind, v in MEAN.items()}
    low = {kind: _frozen(v - 0.1) for kind, v in MEAN.items()}
    high = {kind: [float(x) + 0.1 for x in v] for kind, v in MEAN.items()}
    edges = _frozen(GOOD_EDGES)
    neh = _frozen(np.arange(16).reshape(4, 4))
    layers = _frozen(np.arange(10))
    layer_mean = _frozen(LAYER_MEAN)
    layer_low = [float("nan")] + list(LAYER_MEAN[1:] - 1)
    layer_high = _frozen(LAYER_MEAN + 1)
    series = [("a", layer_mean, layer_low, layer_high), ("b", [5.0, 4.0], None, None)]
    z = _frozen([0.0, 2.0, 4.0])
    values = [0.3, 0.5]
    arguments = [batches, mean, low, high, edges, neh, layers, layer_mean, series, z, values]
    before = copy.deepcopy(arguments)

    plot_contact_types(tmp_path / "1.png", batches, mean, low, high)
    plot_neh_map(tmp_path / "2.png", edges, edges, neh, 150.0)
    plot_layer_filling(tmp_path / "3.png", layers, layer_mean, 56.25, layer_low, layer_high)
    plot_layer_comparison(tmp_path / "4.png", layers, series, 56.25)
    plot_profile(tmp_path / "5.png", z, values, "porosity (-)", "t")

    for after, was in zip(arguments, before, strict=True):
        _assert_same(after, was)
    assert np.isnan(layer_low[0]) and len(layer_low) == 10


def _assert_same(after, was) -> None:
    if isinstance(was, dict):
        assert list(after) == list(was)
        for key in was:
            _assert_same(after[key], was[key])
    elif isinstance(was, tuple) or (
        isinstance(was, list) and not all(isinstance(v, int | float) for v in was)
    ):
        assert len(after) == len(was)
        for a, w in zip(after, was, strict=True):
            _assert_same(a, w)
    elif was is None or isinstance(was, str):
        assert after == was
    else:
        np.testing.assert_array_equal(np.asarray(after), np.asarray(was))


# --- Figure 6: a real off-screen render ----------------------------------------------------


def two_chips():
    lower = pyvista.Box(bounds=(-10.0, 10.0, -10.0, 10.0, 0.0, 2.0))
    upper = pyvista.Box(bounds=(0.0, 20.0, -5.0, 15.0, 2.0, 4.0))
    lower.cell_data["region"] = np.zeros(lower.n_cells, dtype=np.int32)
    upper.cell_data["region"] = np.ones(upper.n_cells, dtype=np.int32)
    mesh = lower.merge(upper)
    mesh.cell_data["batch"] = np.ones(mesh.n_cells, dtype=np.int32)
    assert isinstance(mesh, pyvista.PolyData)
    return mesh


@needs("offscreen")
def test_render_stack_png(tmp_path):
    mesh = two_chips()
    points = mesh.points.copy()
    arrays = {name: mesh.cell_data[name].copy() for name in mesh.cell_data.keys()}
    active = mesh.active_scalars_name
    path = tmp_path / "stack.png"
    render_stack(path, mesh, window_size=(480, 360))

    image = read_png(path)
    assert image.shape[:2] == (360, 480)
    rgb = (image * 255).round().astype(int)
    assert len(np.unique(rgb.reshape(-1, 3), axis=0)) > 10
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    assert np.sum((b > r + 60) & (b > g)) > 200, "chip 0 (tab20 blue) missing"
    assert np.sum((r > b + 100) & (r > g)) > 200, "chip 1 (tab20 orange) missing"
    assert np.mean(np.all(rgb > 245, axis=-1)) > 0.05, "white background missing"

    np.testing.assert_array_equal(mesh.points, points)
    assert list(mesh.cell_data.keys()) == list(arrays)
    for name, values in arrays.items():
        np.testing.assert_array_equal(mesh.cell_data[name], values)
    assert mesh.active_scalars_name == active


@pytest.mark.parametrize(
    ("change", "name"),
    [
        ({"polydata": "mesh"}, "polydata"),
        ({"scalars": "fibre"}, "scalars"),
        ({"window_size": (0, 300)}, "window_size"),
        ({"window_size": "big"}, "window_size"),
    ],
)
def test_render_stack_bad_inputs(tmp_path, change, name):
    kwargs = {"polydata": two_chips(), "scalars": "region", "window_size": (64, 48)} | change
    with pytest.raises(ValueError, match=rf"^{name}(?=[: ])"):
        render_stack(tmp_path / "bad.png", **kwargs)
    assert not (tmp_path / "bad.png").exists()


def test_render_stack_empty_polydata(tmp_path):
    with pytest.raises(ValueError, match="^polydata"):
        render_stack(tmp_path / "bad.png", pyvista.PolyData())


def test_render_stack_without_opengl_raises(tmp_path, monkeypatch):
    monkeypatch.setattr(render, "_rendering_problem", lambda: "no OpenGL (test)")
    with pytest.raises(RuntimeError, match="cannot render"):
        render_stack(tmp_path / "stack.png", two_chips(), window_size=(64, 48))
    assert not (tmp_path / "stack.png").exists()


def test_render_stack_with_a_broken_opengl_does_not_crash(tmp_path):
    """OSMesa chosen where it may be missing: VTK alone would kill the interpreter."""
    script = textwrap.dedent(
        f"""
        import pyvista
        from chipstack.export.render import render_stack
        box = pyvista.Box()
        box.cell_data["region"] = list(range(box.n_cells))
        try:
            render_stack({str(tmp_path / "s.png")!r}, box, window_size=(64, 48))
            print("rendered")
        except RuntimeError as error:
            print("RuntimeError", error)
        """
    )
    env = os.environ | {"VTK_DEFAULT_OPENGL_WINDOW": "vtkOSOpenGLRenderWindow"}
    result = subprocess.run(
        [sys.executable, "-c", script],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    # Which outcome is right is decided apart from the code under test: a bare VTK render
    # in a child process with the same window class. Where it renders, render_stack must
    # render too; where it crashes (no OSMesa: SIGSEGV), render_stack must say so.
    bare = subprocess.run(
        [sys.executable, "-c", BARE_VTK_RENDER], env=env, capture_output=True, timeout=300
    )
    if bare.returncode == 0:
        assert result.stdout.startswith("rendered"), result.stdout
        assert read_png(tmp_path / "s.png").shape[:2] == (48, 64)
    else:
        assert result.stdout.startswith(
            "RuntimeError render_stack: cannot render off screen: a test render in a child"
        ), (bare.returncode, result.stdout)
        assert not (tmp_path / "s.png").exists()


BARE_VTK_RENDER = """
import vtkmodules.vtkRenderingOpenGL2
from vtkmodules.vtkRenderingCore import vtkRenderWindow, vtkRenderer
window = vtkRenderWindow()
window.SetOffScreenRendering(1)
window.AddRenderer(vtkRenderer())
window.Render()
"""
