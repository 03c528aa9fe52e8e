"""The loose press's work: the steps of the press (checkpointed after every accepted
step, resumed after a kill), and what it measures at each: the platen force and nominal
pressure, the contact area of every pair of chips (and of chips on the platens), the
void fraction of the stack's box, the smallest gap between any two surfaces.

Its files (:func:`write_loose_press`) are what a process engineer reads: the force and
pressure against the travel (CSV and a figure), the contact areas, the thickness map at
the end, the deformed chips at every step as a ParaView series, and the pressed geometry
as ``.msh`` and ``.inp`` for a next solver.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from chipstack.core.errors import InputError, StoppedEarly
from chipstack.core.stages import StageInputs, StageOutput
from chipstack.meshing.calculix import SolverError
from chipstack.meshing.contact_model import load_contact_model
from chipstack.meshing.loose.bodies import press_bodies
from chipstack.meshing.loose.material import COLD_CHIP, HOT_CHIP, ChipMaterial

if TYPE_CHECKING:
    from chipstack.meshing.loose.ipc import IPCPress

__all__ = [
    "LooseCompaction",
    "require_ipctk",
    "press_loose_stack",
    "write_loose_press",
    "chip_material",
    "contact_areas",
    "void_fraction",
    "thickness_map",
    "MODEL_FILE",
]

log = logging.getLogger(__name__)

MODEL_FILE = "stack_loose_model.npz"  # the mesh stage's chips (the contact model's arrays)
HISTORY = (
    "travel_mm",
    "platen_force_n",
    "conveyor_force_n",
    "nominal_pressure_mpa",
    "contact_area_mm2",
    "void_fraction",
    "min_distance_mm",
    "newton_iterations",
    "barrier_stiffness",
    "seconds",
)
PLATEN_IDS = {"conveyor": -1, "press": -2}  # chip ids of the platens in contact tables
THICKNESS_CELL_MM = 1.0


def require_ipctk() -> None:
    """Refuse, in one line, a loose press without ipctk."""
    try:
        import ipctk  # noqa: F401
    except ImportError:
        raise InputError(
            "--to solve: the loose press needs ipctk (pip install ipctk; a wheel for "
            "Python 3.8 to 3.13 on Linux, macOS and Windows)"
        ) from None


def chip_material(params) -> ChipMaterial:
    """The chips' material from the loose press's keys (a 0 or -1 keeps the preset's)."""
    base = HOT_CHIP if params.material == "hot" else COLD_CHIP
    changes = {
        "in_plane_mpa": params.in_plane_modulus_mpa,
        "through_thickness_mpa": params.through_thickness_modulus_mpa,
        "transverse_shear_mpa": params.transverse_shear_mpa,
        "in_plane_shear_mpa": params.in_plane_shear_mpa,
        "viscosity_mpa_s": params.viscosity_mpa_s,
    }
    material = dataclasses.replace(base, **{k: v for k, v in changes.items() if v > 0})
    if params.poisson >= 0:
        material = dataclasses.replace(material, in_plane_poisson=params.poisson)
    try:
        material.stiffness()
    except ValueError:
        raise InputError(
            "solve: the chip material's moduli and Poisson ratios give no stable "
            "elasticity (lower solve.poisson)"
        ) from None
    return material


@dataclass
class _State:
    """What a checkpoint holds: the accepted steps' measures and displacements."""

    q: np.ndarray
    kappa: float
    q_previous: np.ndarray | None = None  # the step before: the next step's predictor
    history: list[list[float]] = field(default_factory=list)
    pairs: list[list[float]] = field(default_factory=list)
    displacements: list[np.ndarray] = field(default_factory=list)

    @property
    def batches_done(self) -> int:  # the checkpoint journal's count of steps
        return len(self.history)

    def arrays(self) -> dict[str, np.ndarray]:
        previous = self.q if self.q_previous is None else self.q_previous
        return {
            "q": self.q,
            "q_previous": previous,
            "kappa": np.array(self.kappa),
            "history": np.array(self.history, dtype=float).reshape(-1, len(HISTORY)),
            "pairs": np.array(self.pairs, dtype=float).reshape(-1, 5),
            "displacements": np.array(self.displacements, dtype=np.float32).reshape(
                len(self.displacements), -1, 3
            ),
        }

    @classmethod
    def from_arrays(cls, arrays: dict, where: str, n_dof: int) -> _State:
        if arrays["q"].shape != (n_dof,):
            raise InputError(f"{where}: a checkpoint of another model")
        return cls(
            q=arrays["q"],
            q_previous=arrays["q_previous"] if "q_previous" in arrays else None,
            kappa=float(arrays["kappa"]),
            history=arrays["history"].tolist(),
            pairs=arrays["pairs"].tolist(),
            displacements=list(arrays["displacements"]),
        )


@dataclass
class LooseCompaction:
    """A finished loose press: the steps' measures (``history``: one row per accepted
    step, columns :data:`HISTORY`), the contact table (step, travel, chip a, chip b,
    area mm^2; platens as :data:`PLATEN_IDS`), every step's chip displacements (k, n, 3)
    mm, the model's size and what it was pressed with."""

    history: np.ndarray
    pairs: np.ndarray
    displacements: np.ndarray
    points: np.ndarray
    cells: np.ndarray
    chip: np.ndarray
    used_nodes: np.ndarray  # the contact model's node of every chip node
    bottom_z: float
    footprint_mm: tuple[float, float, float, float]
    info: dict[str, Any]
    wall_time_s: float

    @property
    def press_mm(self) -> np.ndarray:
        return self.history[:, 0]

    @property
    def force_n(self) -> np.ndarray:
        return self.history[:, 1]


def contact_areas(press: IPCPress, q: np.ndarray, owner: np.ndarray) -> dict[tuple, float]:
    """The contact area (mm^2) of every pair of bodies closer than the barrier's distance
    at ``q``: half the area of the surface vertices of each side near the other's
    faces, summed (both sides meshed alike); a chip on a platen: its own vertices'.

    owner: the body of every collision-mesh vertex (chip index, or the platens' ids)."""
    found = press.contact_vertices(q)
    if not len(found):
        return {}
    areas = np.asarray(press.mesh.vertex_areas)
    faces = np.asarray(press.mesh.faces)
    vertex = found[:, 0]
    face_owner = owner[faces[found[:, 1], 0]]
    vertex_owner = owner[vertex]
    rows = np.unique(np.column_stack([vertex_owner, face_owner, vertex]), axis=0)
    sides: dict[tuple[int, int], float] = {}
    for a, b, v in rows:
        sides[(int(a), int(b))] = sides.get((int(a), int(b)), 0.0) + float(areas[v])
    out: dict[tuple, float] = {}
    for (a, b), area in sides.items():
        if a < 0:  # a platen's corner near a chip face: counted from the chip's side
            continue
        if b < 0:
            out[(a, b)] = out.get((a, b), 0.0) + area
        else:
            pair = (min(a, b), max(a, b))
            out[pair] = out.get(pair, 0.0) + 0.5 * area
    return out


def void_fraction(points, cells, box_xy, bottom_z: float, top_z: float) -> float:
    """1 - the chips' volume over the box's: ``box_xy`` (x0, x1, y0, y1) mm from the
    conveyor at ``bottom_z`` to the press plate at ``top_z``."""
    from chipstack.meshing.loose.elements import brick_volumes

    x0, x1, y0, y1 = box_xy
    box = (x1 - x0) * (y1 - y0) * (top_z - bottom_z)
    return float(1.0 - brick_volumes(points[cells]).sum() / box)


def thickness_map(points, surface, box_xy, bottom_z: float, cell_mm: float = THICKNESS_CELL_MM):
    """(x (i,), y (j,), top (i, j)) mm: the height of the stack's top surface above the
    conveyor over a grid of ``cell_mm`` cells (NaN where no chip lies): the upward-facing
    surface triangles rasterised at the cells' centres, the highest kept."""
    x0, x1, y0, y1 = box_xy
    xs = np.arange(x0 + cell_mm / 2, x1, cell_mm)
    ys = np.arange(y0 + cell_mm / 2, y1, cell_mm)
    top = np.full((len(xs), len(ys)), -np.inf)
    tri = points[surface]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    up = normal[:, 2] > 0.3 * np.linalg.norm(normal, axis=1)
    for a, b, c in tri[up]:
        lo, hi = np.minimum(np.minimum(a, b), c), np.maximum(np.maximum(a, b), c)
        i = np.flatnonzero((xs >= lo[0]) & (xs <= hi[0]))
        j = np.flatnonzero((ys >= lo[1]) & (ys <= hi[1]))
        if not (len(i) and len(j)):
            continue
        gx, gy = np.meshgrid(xs[i], ys[j], indexing="ij")
        det = (b[1] - c[1]) * (a[0] - c[0]) + (c[0] - b[0]) * (a[1] - c[1])
        if abs(det) < 1e-14:
            continue
        l1 = ((b[1] - c[1]) * (gx - c[0]) + (c[0] - b[0]) * (gy - c[1])) / det
        l2 = ((c[1] - a[1]) * (gx - c[0]) + (a[0] - c[0]) * (gy - c[1])) / det
        l3 = 1 - l1 - l2
        inside = (l1 >= -1e-9) & (l2 >= -1e-9) & (l3 >= -1e-9)
        z = l1 * a[2] + l2 * b[2] + l3 * c[2]
        block = top[np.ix_(i, j)]
        top[np.ix_(i, j)] = np.where(inside, np.maximum(block, z), block)
    top[~np.isfinite(top)] = np.nan
    return xs, ys, top - bottom_z


def _owners(press: IPCPress) -> np.ndarray:
    """The body of every collision-mesh vertex: chip index, then the platens' ids."""
    chip_of_node = press.bodies.node_chip
    return np.concatenate(
        [
            chip_of_node[press.surface_nodes],
            np.full(4, PLATEN_IDS["conveyor"]),
            np.full(4, PLATEN_IDS["press"]),
        ]
    )


def press_loose_stack(inputs: StageInputs, stage: str) -> LooseCompaction:
    """The loose press of the mesh stage's chips as ``[solve]`` asks (see the module
    docstring); resumes from the last accepted step of a killed run."""
    from chipstack.meshing.loose.ipc import IPCPress, PressError, PressSettings

    scenario = inputs.scenario
    solve, params = scenario.solve, scenario.solve.params
    model = load_contact_model(inputs.result("mesh").folder / MODEL_FILE)
    material = chip_material(params)
    clearance = 0.5 * params.barrier_distance_mm
    bodies, platens = press_bodies(model, material, clearance)
    lo, hi = bodies.points.min(axis=0), bodies.points.max(axis=0)
    footprint = (float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1]))
    area = (hi[0] - lo[0]) * (hi[1] - lo[1])
    height = platens.top_z - platens.bottom_z
    total = solve.press_fraction * height
    increments = solve.increments
    step_mm = total / increments
    target_force = params.target_pressure_mpa * area
    pressure_scale = (
        5 * params.target_pressure_mpa
        if params.target_pressure_mpa > 0
        else material.through_thickness_mpa * solve.press_fraction
    )
    settings = PressSettings(
        dhat_mm=params.barrier_distance_mm,
        friction=params.friction,
        pressure_scale_mpa=pressure_scale,
        max_newton=params.newton_iterations,
        step_time_s=step_mm / params.press_speed_mm_s,
        weight_n_mm3=params.density_g_cm3 * 1e-6 * 9.81,  # g/cm^3 = 1e-6 kg/mm^3
    )
    try:
        press = IPCPress(bodies, platens, settings)
    except PressError as exc:
        raise SolverError(str(exc)) from None
    owner = _owners(press)
    state = _State(q=press.q.copy(), kappa=press.kappa)
    checkpoint = inputs.checkpoint
    if checkpoint is not None:
        resumed = checkpoint.resume(lambda a, w: _State.from_arrays(a, w, press.n_dof))
        if resumed is not None:
            state = resumed
            log.info("loose press: resuming after step %d", state.batches_done)
    press.q, press.kappa = state.q.copy(), state.kappa
    report = inputs.options.progress
    started = time.perf_counter()

    def done_share() -> float:
        if not state.history:
            return 0.0
        last = state.history[-1]
        if params.drive == "pressure":
            return last[HISTORY.index("platen_force_n")] / max(target_force, 1e-12)
        return last[0] / total

    def measure(result, index: int) -> None:
        x = bodies.points + result.displacement
        top_z = platens.top_z - result.travel_mm
        contacts = contact_areas(press, press.q, owner)
        chip_area = sum(a for (i, j), a in contacts.items() if i >= 0 and j >= 0)
        state.history.append(
            [
                result.travel_mm,
                result.force_n,
                result.conveyor_force_n,
                result.force_n / area,
                chip_area,
                void_fraction(x, bodies.cells, footprint, platens.bottom_z, top_z),
                result.min_distance_mm,
                result.newton_iterations,
                result.barrier_stiffness,
                result.seconds,
            ]
        )
        for (i, j), a in sorted(contacts.items()):
            state.pairs.append([index, result.travel_mm, i, j, a])
        state.displacements.append(result.displacement.astype(np.float32))
        state.q_previous = state.q
        state.q, state.kappa = press.q.copy(), press.kappa

    def finished() -> bool:
        if not state.history:
            return False
        last = state.history[-1]
        if params.target_pressure_mpa > 0 and last[HISTORY.index("nominal_pressure_mpa")] >= (
            params.target_pressure_mpa * (1 - 1e-6)
        ):
            return True
        if params.drive == "pressure":
            return False
        # The drive's spring leaves the platen short of its target by its force over the
        # spring's stiffness (measured 3e-4 mm at 444 N on the 24-chip stack, which made a
        # 51st step of 0.3 um): within 5 % of a step the travel is reached.
        return last[0] >= total - 0.05 * step_mm or len(state.history) >= 4 * increments

    while not finished():
        if time.perf_counter() - started > solve.time_limit_s:  # this run's own time
            raise StoppedEarly(
                f"loose press: stopped at the time limit (solve.time_limit_s = "
                f"{solve.time_limit_s:g} s) after {state.batches_done} steps; run the same "
                "command again to resume from the last step"
            )
        k = state.batches_done + 1
        result = _step(press, params, state, step_mm, total, target_force, increments, k)
        if result is None:
            travel = state.history[-1][0] if state.history else 0.0
            raise SolverError(
                f"loose press: a step did not converge after {params.cutbacks} cutbacks at "
                f"travel {travel:.4f} mm; a smaller solve.increments step or a larger "
                "solve.barrier_distance_mm may help"
            )
        measure(result, k)
        if checkpoint is not None:
            checkpoint.save(state.arrays(), state.batches_done)
        if report is not None:
            report(stage, min(100, round(100 * done_share())), 100, {})
    arrays = state.arrays()
    history = arrays["history"]
    info = {
        "solver": "ipctk",
        "chips": int(model.n_chips),
        "nodes": int(bodies.n_nodes),
        "dofs": int(press.n_dof),
        "bricks": int(len(bodies.cells)),
        "surface_triangles": int(len(bodies.surface)),
        "material": {
            "preset": params.material,
            **{k: v for k, v in dataclasses.asdict(material).items()},
        },
        "barrier_distance_mm": params.barrier_distance_mm,
        "clearance_mm": clearance,
        "friction": params.friction,
        "drive": params.drive,
        "footprint_mm2": round(float(area), 3),
        "stack_height_mm": round(float(height), 5),
        "void_fraction_start": void_fraction(
            bodies.points, bodies.cells, footprint, platens.bottom_z, platens.top_z
        ),
    }
    return LooseCompaction(
        history=history,
        pairs=arrays["pairs"],
        displacements=arrays["displacements"],
        points=bodies.points,
        cells=bodies.cells,
        chip=bodies.chip,
        used_nodes=np.unique(model.cells),
        bottom_z=platens.bottom_z,
        footprint_mm=footprint,
        info=info,
        wall_time_s=float(history[:, HISTORY.index("seconds")].sum()),
    )


def _step(press, params, state, step_mm, total, target_force, increments, k):
    """One accepted step, its target cut in half up to ``params.cutbacks`` times when it
    does not converge; None when none converges."""
    from chipstack.meshing.loose.ipc import PressError

    done = state.history[-1][0] if state.history else 0.0
    load_done = state.history[-1][1] if state.history else 0.0
    before = state.history[-2] if len(state.history) > 1 else [0.0, 0.0]
    share = 1.0
    for _ in range(params.cutbacks + 1):
        try:
            if params.drive == "pressure":
                load = min(target_force, load_done + share * target_force / increments)
                guess = _predictor(state, load - load_done, load_done - before[1])
                return press.step(target=0.0, load=load, guess=guess)
            target = min(total, done + share * step_mm)
            guess = _predictor(state, target - done, done - before[0])
            return press.step(target=target, guess=guess)
        except PressError as exc:
            log.info("loose press: step %d cut back (%s)", k, exc)
            press.q, press.kappa = state.q.copy(), state.kappa
            share /= 2
    return None


def _predictor(state: _State, increment: float, last_increment: float) -> np.ndarray | None:
    """The last step's change of state scaled to this step's ``increment`` of travel or
    load (a secant predictor: Newton then starts near the answer); None at the first."""
    if state.q_previous is None or last_increment <= 0 or increment <= 0:
        return None
    return (state.q - state.q_previous) * (increment / last_increment)


def write_loose_press(result: LooseCompaction, folder: Path, inputs: StageInputs) -> StageOutput:
    """The loose press's files in ``folder`` and the stage's summary."""
    import meshio

    from chipstack.export.figure_kinds import draw_figures
    from chipstack.meshing.files import to_meshio, write_mesh
    from chipstack.meshing.loose.elements import hex_boundary_triangles

    folder = Path(folder)
    files = []
    with open(folder / "force_displacement.csv", "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["step", *HISTORY])
        for k, row in enumerate(result.history, start=1):
            writer.writerow([k, *(f"{v:.9g}" for v in row)])
    files.append("force_displacement.csv")
    with open(folder / "contact_areas.csv", "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["step", "travel_mm", "chip_a", "chip_b", "area_mm2"])
        for step, travel, a, b, area in result.pairs:
            writer.writerow([int(step), f"{travel:.9g}", int(a), int(b), f"{area:.6g}"])
    files.append("contact_areas.csv")
    final = result.points + result.displacements[-1]
    xs, ys, top = thickness_map(
        final, hex_boundary_triangles(result.cells), result.footprint_mm, result.bottom_z
    )
    with open(folder / "thickness_map.csv", "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["x_mm", "y_mm", "top_mm"])
        for i, x in enumerate(xs):
            for j, y in enumerate(ys):
                value = "" if math.isnan(top[i, j]) else f"{top[i, j]:.6g}"
                writer.writerow([f"{x:.6g}", f"{y:.6g}", value])
    files.append("thickness_map.csv")
    mesh = _pressed_mesh(inputs, result, final)
    steps = folder / "press_steps"
    steps.mkdir()
    entries = []
    for k, displacement in enumerate(result.displacements, start=1):
        grid = to_meshio(dataclasses.replace(mesh, points=result.points + displacement))
        grid.point_data["displacement_mm"] = np.asarray(displacement, dtype=float)
        name = f"step_{k:04d}.vtu"
        meshio.write(steps / name, grid)
        entries.append((float(result.history[k - 1][0]), f"press_steps/{name}"))
    _write_pvd(folder / "press.pvd", entries)
    files += ["press.pvd", *(path for _, path in entries)]
    files += [p.name for p in write_mesh(folder, "pressed", mesh, ["msh", "inp", "vtu"])]
    if inputs.options.figures:
        files += draw_figures("compaction", folder, result)
        files += draw_figures("loose_press", folder, result)
    history = result.history
    last = history[-1]
    column = {name: i for i, name in enumerate(HISTORY)}
    summary = {
        "solver": "ipctk",
        "increments": len(history),
        "press_mm": round(float(last[column["travel_mm"]]), 6),
        "force_n": round(float(last[column["platen_force_n"]]), 3),
        "conveyor_force_n": round(float(last[column["conveyor_force_n"]]), 3),
        "nominal_pressure_mpa": round(float(last[column["nominal_pressure_mpa"]]), 5),
        "contact_area_mm2": round(float(last[column["contact_area_mm2"]]), 3),
        "void_fraction": round(float(last[column["void_fraction"]]), 5),
        "void_fraction_start": round(float(result.info["void_fraction_start"]), 5),
        "smallest_gap_mm": float(history[:, column["min_distance_mm"]].min()),
        "newton_iterations": int(history[:, column["newton_iterations"]].sum()),
        "solver_wall_time_s": round(result.wall_time_s, 2),
        "model": result.info,
        "files": sorted(files),
    }
    (folder / "press_summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    summary["files"] = sorted([*files, "press_summary.json"])
    return StageOutput(summary)


def _pressed_mesh(inputs: StageInputs, result: LooseCompaction, final: np.ndarray):
    """The chips as the mesh stage's volume mesh, at their pressed positions."""
    from chipstack.core.arrangement import stack_history
    from chipstack.meshing.meshers import contact_volume_mesh

    model = load_contact_model(inputs.result("mesh").folder / MODEL_FILE)
    arrangement = stack_history(inputs.result("packing"))[-1]
    mesh = contact_volume_mesh(model, arrangement)
    # The chips' nodes only (the contact model's platen nodes are no part of a loose
    # stack): node k of the pressed mesh is node k of the press's bodies.
    index = np.full(len(mesh.points), -1)
    index[result.used_nodes] = np.arange(len(result.used_nodes))
    node_sets = {name: index[nodes][index[nodes] >= 0] for name, nodes in mesh.node_sets.items()}
    return dataclasses.replace(
        mesh, points=final, cells=index[mesh.cells], node_sets=node_sets, kind="loose"
    )


def _write_pvd(path: Path, entries: list[tuple[float, str]]) -> None:
    """A ParaView collection of the steps' files, the platen travel (mm) as the time."""
    lines = [
        '<?xml version="1.0"?>',
        '<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">',
        "  <Collection>",
        *(f'    <DataSet timestep="{t:.9g}" group="" part="0" file="{f}"/>' for t, f in entries),
        "  </Collection>",
        "</VTKFile>",
    ]
    path.write_text("\n".join(lines) + "\n")
