"""The Python API: scenarios in, a :class:`Run` out, its results as numpy arrays, pandas
DataFrames, ``meshio.Mesh`` and pyvista datasets.

Units are the project's everywhere: millimetres, seconds, grams, newtons; quaternions
are (x, y, z, w). Bad input raises :class:`core.errors.InputError` (a
:class:`core.errors.ChipstackError`) with a one-line message naming the key or file.
Nothing here prints; warnings go through :mod:`logging`.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING, Any

from chipstack.core.errors import InputError, brief, printable
from chipstack.core.files import read_json
from chipstack.core.keys import MAX_SEED
from chipstack.core.schema import Scenario
from chipstack.packing.stage import STAGE as _PACKING
from chipstack.pipeline.run import run_pipeline
from chipstack.pipeline.scenario_files import builtin_names, load_resolved, with_overrides
from chipstack.pipeline.scenario_files import load_scenario as _load_file

if TYPE_CHECKING:
    import meshio
    import numpy as np
    import pandas as pd
    import pyvista as pv

    from chipstack.core.stack import Stack

__all__ = ["Run", "load_scenario", "open_run", "run", "scenarios"]


def scenarios() -> list[str]:
    """The names of the built-in scenarios.

    Returns
    -------
    list of str
        Sorted names, each usable wherever a scenario is asked for.

    Examples
    --------
    >>> import chipstack
    >>> chipstack.scenarios()[:3]
    ['container-ar10', 'container-ar25', 'conveyor-line']
    """
    return builtin_names()


def load_scenario(
    source: str | Path | Scenario | None = None,
    overrides: Mapping[str, Any] | None = None,
    seed: int | None = None,
) -> Scenario:
    """A validated scenario from a built-in name, a TOML file or a scenario.

    Parameters
    ----------
    source : str, Path, Scenario or None
        A built-in name (see :func:`scenarios`), the path of a scenario TOML file, or a
        scenario to change. None: ``paper-squares``, the paper's reference stack.
    overrides : mapping of str to value, optional
        Scenario keys to change, dotted as in the TOML file and ``docs/scenarios.md``:
        ``{"deposition.chips": 60, "mesh.voxel_mm": 1.0}``. Each value is checked as if
        it had been written in the file.
    seed : int, optional
        The seed of every random draw (replaces the scenario's ``seed``).

    Returns
    -------
    Scenario
        Frozen; its tables read as attributes (``scenario.deposition.chips``).

    Raises
    ------
    InputError
        An unknown name, a missing or malformed file, an unknown key or a bad value.

    Examples
    --------
    >>> import chipstack
    >>> s = chipstack.load_scenario("paper-squares", {"mesh.voxel_mm": 2.0}, seed=7)
    >>> s.name, s.seed, s.mesh.voxel_mm
    ('paper-squares', 7, 2.0)
    >>> chipstack.load_scenario("paper-squares", {"deposition.chipz": 3})
    Traceback (most recent call last):
    ...
    chipstack.core.errors.InputError: deposition.chipz: no such scenario key (see docs/scenarios.md)
    """
    scenario = source if isinstance(source, Scenario) else _load_file(source)
    if overrides:
        scenario = with_overrides(scenario, overrides)
    if seed is not None:
        if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed <= MAX_SEED:
            raise InputError(f"seed: must be a whole number, 0 to 2**63 - 1, got {brief(seed)}")
        scenario = scenario.with_seed(seed)
    return scenario


def run(
    scenario: str | Path | Scenario | None = None,
    to: str = "mesh",
    out: str | Path | None = None,
    *,
    seed: int | None = None,
    overrides: Mapping[str, Any] | None = None,
    overwrite: bool = False,
    descriptors: Sequence[str] | None = None,
    figures: bool = True,
    progress: Callable[[str, int, int, dict], None] | None = None,
) -> Run:
    """Run a scenario through the stages up to ``to`` into a run directory.

    The same run as ``pipeline run SCENARIO --to TO --out OUT``: crash-safe, cached and
    resumable. Called again on the same ``out`` it resumes an interrupted run or redoes
    only the stages whose inputs changed (``overwrite``: all of them).

    Parameters
    ----------
    scenario : str, Path, Scenario or None
        As for :func:`load_scenario` (None: ``paper-squares``).
    to : str
        The last stage: ``"packing"``, ``"geometry"``, ``"mesh"`` or ``"solve"`` (the
        last needs CalculiX, ``ccx``, on the PATH).
    out : str or Path, optional
        The run directory (default: ``runs/<name>-seed<N>``).
    seed, overrides
        As for :func:`load_scenario`.
    overwrite : bool
        Recompute every stage instead of reusing the cached ones.
    descriptors : sequence of str, optional
        The geometry stage's descriptors (default: all; ``docs/geometry.md``).
    figures : bool
        Draw the PNG figures of the geometry and mesh stages (a few seconds).
    progress : callable, optional
        ``progress(stage, done, total, detail)``, called as the stages advance.

    Returns
    -------
    Run
        The finished run directory, read lazily.

    Raises
    ------
    InputError
        Bad input of any kind (scenario, stage name, run directory), before any work.

    Examples
    --------
    >>> import tempfile, chipstack
    >>> folder = tempfile.mkdtemp()
    >>> small = {"deposition.chips": 24, "deposition.batch_size": 12,
    ...          "deposition.target_size_mm": 80.0, "mesh.voxel_mm": 1.0}
    >>> result = chipstack.run("paper-squares", to="mesh", out=f"{folder}/run",
    ...                        overrides=small, figures=False)
    >>> result.stages
    ['packing', 'geometry', 'mesh']
    >>> result.positions.shape, len(result.chips)
    ((24, 3), 24)
    >>> sorted(result.mesh().cell_data)[:3]
    ['batch', 'fibre_1', 'fibre_2']
    """
    resolved = load_scenario(scenario, overrides, seed)
    path = Path(out) if out is not None else Path(f"runs/{resolved.name}-seed{resolved.seed}")
    folder, first, manifest = run_pipeline(
        resolved,
        path,
        to=to,
        overwrite=overwrite,
        progress=progress,
        command=["chipstack.run"],
        descriptors=descriptors,
        figures=figures,
    )
    return Run(folder, _scenario=resolved, _manifest=manifest, _stack=first)


def open_run(path: str | Path) -> Run:
    """A finished run directory, written by :func:`run` or ``pipeline run``.

    Parameters
    ----------
    path : str or Path
        The run directory (it holds ``manifest.json`` and ``scenario.toml``).

    Returns
    -------
    Run

    Raises
    ------
    InputError
        No such directory, or not a finished run.

    Examples
    --------
    >>> import chipstack
    >>> chipstack.open_run("no/such/run")
    Traceback (most recent call last):
    ...
    chipstack.core.errors.InputError: no/such/run: not a finished run directory (no manifest.json)
    """
    return Run(Path(path))


class Run:
    """A finished run directory and its results.

    Every result is read from the files when first asked for: ``Run`` works on a run made
    by the command line too. A stage that did not run raises :class:`InputError` naming
    it.

    Attributes
    ----------
    path : Path
        The run directory.
    """

    def __init__(
        self,
        path: Path,
        *,
        _scenario: Scenario | None = None,
        _manifest: dict | None = None,
        _stack: Stack | None = None,
    ) -> None:
        self.path = Path(path)
        if _manifest is None:
            manifest = self.path / "manifest.json"
            if not manifest.is_file():
                raise InputError(
                    f"{printable(path)}: not a finished run directory (no manifest.json)"
                )
            _manifest = read_json(manifest, "manifest")
        self._manifest = _manifest
        self._given_scenario = _scenario
        self._given_stack = _stack

    def __repr__(self) -> str:
        return f"Run({str(self.path)!r}, stages={self.stages})"

    # -- the run ---------------------------------------------------------------------

    @property
    def manifest(self) -> dict[str, Any]:
        """``manifest.json``: versions, seed, command, times, warnings, stage summaries."""
        return self._manifest

    @property
    def stages(self) -> list[str]:
        """The stages completed, in pipeline order."""
        return list(self._manifest.get("stages_completed", []))

    @cached_property
    def scenario(self) -> Scenario:
        """The resolved scenario the run used (``scenario.toml``)."""
        if self._given_scenario is not None:
            return self._given_scenario
        return load_resolved(self.path / "scenario.toml")

    @property
    def warnings(self) -> list[str]:
        """What the stages warned about (an unsettled batch, ...)."""
        return list(self._manifest.get("warnings", []))

    def files(self, stage: str | None = None) -> list[Path]:
        """The files of the run (or of one stage's folder), sorted.

        Examples
        --------
        >>> # run.files("mesh") -> [.../mesh/stack_voxel.inp, .../mesh/stack_voxel.msh, ...]
        """
        root = self.path if stage is None else self._folder(stage)
        return sorted(p for p in root.rglob("*") if p.is_file())

    def _folder(self, stage: str) -> Path:
        if stage not in self.stages:
            raise InputError(
                f"{printable(self.path)}: has no {stage} result (run it with to={stage!r}); "
                f"completed: {', '.join(self.stages) or 'none'}"
            )
        return self.path / stage

    # -- packing ---------------------------------------------------------------------

    @cached_property
    def stack(self) -> Stack:
        """The settled stack as the packing stage recorded it (:class:`core.stack.Stack`:
        shapes, batches, poses and contacts after every batch)."""
        if self._given_stack is not None:
            return self._given_stack
        stack = _PACKING.load(self._folder("packing"), self.scenario)
        if stack is None:
            raise InputError(f"{printable(self.path)}: a {self.scenario.kind} run has no stack")
        return stack

    @property
    def positions(self) -> np.ndarray:
        """(n, 3) centre of mass of every chip, mm."""
        return self.stack.positions

    @property
    def quaternions(self) -> np.ndarray:
        """(n, 4) orientation of every chip, (x, y, z, w)."""
        return self.stack.quaternions

    @cached_property
    def poses(self) -> pd.DataFrame:
        """One row per chip after the last batch: chip, batch, shape, x_mm, y_mm, z_mm,
        qx, qy, qz, qw, inside_target."""
        files = sorted(self._folder("packing").glob("poses_after_batch_*.csv"))
        if not files:
            raise InputError(f"{printable(self.path)}: its packing stage wrote no poses")
        return _csv(files[-1])

    def stack_grid(self, batch: int | None = None) -> pv.PolyData:
        """The chips' surfaces after ``batch`` (default: the last) as a pyvista dataset,
        with cell arrays ``region`` (chip + 1, as in the mesh files) and ``batch``.

        Examples
        --------
        >>> # run.stack_grid().plot(scalars="batch")
        """
        import pyvista as pv  # here: only this method and mesh_grid need VTK

        files = sorted(self._folder("packing").glob("stack_after_batch_*.vtp"))
        if not files:
            raise InputError(f"{printable(self.path)}: its packing stage wrote no VTK stack")
        if batch is None:
            return pv.read(files[-1])
        path = self.path / "packing" / f"stack_after_batch_{batch:02d}.vtp"
        if not path.is_file():
            raise InputError(f"batch: {printable(batch)} is not a batch of this run")
        return pv.read(path)

    # -- geometry --------------------------------------------------------------------

    @cached_property
    def description(self) -> dict[str, Any]:
        """``geometry/descriptors.json`` as written: every descriptor's scalars (value,
        unit, doc) and profiles."""
        return read_json(self._folder("geometry") / "descriptors.json", "descriptors")

    @property
    def descriptors(self) -> dict[str, float]:
        """Every scalar descriptor by ``"descriptor.name"``, e.g.
        ``run.descriptors["stack.volume_fraction"]`` (units: :attr:`descriptor_table`)."""
        return {
            f"{name}.{key}": entry["value"]
            for name, section in self.description["descriptors"].items()
            for key, entry in section.get("scalars", {}).items()
        }

    @property
    def descriptor_table(self) -> pd.DataFrame:
        """The scalar descriptors as a table: descriptor, name, value, unit, doc."""
        rows = [
            (name, key, entry["value"], entry.get("unit", ""), entry.get("doc", ""))
            for name, section in self.description["descriptors"].items()
            for key, entry in section.get("scalars", {}).items()
        ]
        import pandas as pd  # here: listing and loading scenarios must not wait for pandas

        return pd.DataFrame(rows, columns=["descriptor", "name", "value", "unit", "doc"])

    @cached_property
    def chips(self) -> pd.DataFrame:
        """One row per chip: batch, layer, tilt, direction, contacts by kind, overlap."""
        return _csv(self._folder("geometry") / "chips.csv")

    @cached_property
    def contacts(self) -> pd.DataFrame:
        """One row per contact pair (chip_b -1: the conveyor): kind, extents, centre,
        area."""
        return _csv(self._folder("geometry") / "contacts.csv")

    @cached_property
    def layers(self) -> pd.DataFrame:
        """One row per layer of ``geometry.layer_mm``: chips, solid fraction, porosity."""
        return _csv(self._folder("geometry") / "layers.csv")

    # -- mesh ------------------------------------------------------------------------

    def _mesh_file(self, kind: str | None) -> Path:
        folder = self._folder("mesh")
        found = sorted(folder.glob("stack_*.vtu"))
        kinds = [p.stem.removeprefix("stack_") for p in found]
        if not found:
            raise InputError(f"{printable(self.path)}: its mesh stage wrote no .vtu mesh")
        if kind is None:
            return found[0]
        if kind not in kinds:
            raise InputError(f"kind: {printable(kind)!r} not in this run ({', '.join(kinds)})")
        return found[kinds.index(kind)]

    def mesh(self, kind: str | None = None) -> meshio.Mesh:
        """The volume mesh as a ``meshio.Mesh``, cell data ``chip`` (-1: pore space),
        ``batch``, ``layer``, fibre directions and ``quality``.

        Parameters
        ----------
        kind : str, optional
            ``"voxel"``, ``"conformal"`` or ``"image"`` when the run holds several.
        """
        import meshio  # here: as pandas, only for what reads a run's files

        return meshio.read(self._mesh_file(kind))

    def mesh_grid(self, kind: str | None = None) -> pv.UnstructuredGrid:
        """The volume mesh as a pyvista ``UnstructuredGrid`` (same arrays as :meth:`mesh`).

        Examples
        --------
        >>> # run.mesh_grid().plot(scalars="region", show_edges=True)
        """
        import pyvista as pv  # here: as in stack_grid

        return pv.read(self._mesh_file(kind))


def _csv(path: Path) -> pd.DataFrame:
    import pandas as pd  # here: as in descriptor_table

    if not path.is_file():
        raise InputError(f"{printable(path)}: missing from the run directory")
    return pd.read_csv(path)
