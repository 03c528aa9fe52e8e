"""Typed, frozen scenario configuration and its validation.

A scenario is a nested table (usually read from TOML). Every key is declared once here,
with its type, unit, default and a one-line description; the validator, the README's key
table and the resolved-scenario writer are all driven by these declarations, so they
cannot drift apart.
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from core.errors import InputError, brief, printable
from core.stages import load_stages

__all__ = [
    "ChipSpec",
    "DepositionSpec",
    "PhysicsSpec",
    "SettlingSpec",
    "OutputSpec",
    "GeometrySpec",
    "MeshSpec",
    "SolveSpec",
    "DropSpec",
    "ContainerSpec",
    "ConveyorSpec",
    "Scenario",
    "scenario_from_dict",
    "scenario_to_dict",
    "key_table",
    "printable",
]


def _key(default: Any, unit: str, doc: str, check: Callable[[Any], str | None] | None = None):
    return field(default=default, metadata={"unit": unit, "doc": doc, "check": check})


MAX_SEED = 2**63 - 1  # seeds are recorded in JSON manifests and TOML: 64-bit integers
MAX_REPEATS = 1000  # runs of an ensemble, repeats of a validation case
MAX_DROPS = 100_000  # drops of one experiment or condition
# Local worker processes: a few per core pay for waiting on files; thousands only hang.
MAX_WORKERS = 4 * (os.cpu_count() or 1)
MAX_LENGTH_MM = 1e4  # 10 m: beyond any conveyor, and safely inside float arithmetic
MAX_TIME_S = 1e4


def _positive(value: Any) -> str | None:
    return None if value > 0 else "must be positive"


def _length(value: float) -> str | None:
    if value <= 0:
        return "must be positive"
    return None if value <= MAX_LENGTH_MM else f"must not exceed {MAX_LENGTH_MM:g} mm"


def _duration(value: float) -> str | None:
    if value <= 0:
        return "must be positive"
    return None if value <= MAX_TIME_S else f"must not exceed {MAX_TIME_S:g} s"


def _name(value: str) -> str | None:
    ok = value and len(value) <= 100 and re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9._-]*", value)
    return None if ok else "must be 1-100 letters, digits, '.', '_' or '-' (used in file names)"


def _non_negative(value: Any) -> str | None:
    return None if value >= 0 else "must not be negative"


def _range(lo: float | None = None, hi: float | None = None):
    def check(value: tuple[float, float]) -> str | None:
        if len(value) != 2:
            return "must be a pair [low, high]"
        a, b = value
        if a > b:
            return f"low {a} is above high {b}"
        if lo is not None and a < lo:
            return f"must not go below {lo}"
        if hi is not None and b > hi:
            return f"must not go above {hi}"
        return None

    return check


def _between(lo: float, hi: float):
    def check(value: float) -> str | None:
        return None if lo <= value <= hi else f"must be between {lo} and {hi}"

    return check


def _one_of(*names: str):
    def check(value: str) -> str | None:
        return None if value in names else f"must be one of {', '.join(map(repr, names))}"

    return check


def _region(value: tuple[float, ...]) -> str | None:
    if value == ():
        return None
    if len(value) != 4:
        return f"must be [x_min, x_max, y_min, y_max] (4 numbers), got {len(value)}"
    x0, x1, y0, y1 = value
    if not (x0 < x1 and y0 < y1):
        return f"needs x_min < x_max and y_min < y_max, got {list(value)}"
    if max(abs(v) for v in value) > MAX_LENGTH_MM:
        return f"must lie within {MAX_LENGTH_MM:g} mm of the target's centre"
    return None


LENGTH_UNITS_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0, "um": 1e-3, "in": 25.4}


@dataclass(frozen=True)
class ChipSpec:
    """A chip shape and its size. Lengths in mm, fibre directions in degrees in the chip
    plane; which keys a shape reads is listed in the README (Chip shapes)."""

    shape: str = _key("box", "", "chip shape, from the shape registry (see Chip shapes)")
    length_mm: float = _key(
        20.0,
        "mm",
        "box, beam, fibre: length (local x); polygon, star, random_polygon: diameter of "
        "the circle through the corners",
        _length,
    )
    width_mm: float = _key(20.0, "mm", "box, beam: width (local y)", _length)
    thickness_mm: float = _key(
        2.0, "mm", "thickness (local z); a cylindrical beam or fibre's diameter", _length
    )
    sides: int = _key(
        6, "", "polygon: sides; star: points; random_polygon: corners", _between(3, 64)
    )
    inner_ratio: float = _key(
        0.5, "", "star: radius of the notches over the radius of the tips", _between(0.05, 0.95)
    )
    convex: bool = _key(True, "", "random_polygon: convex outline (else star-shaped)")
    irregularity: float = _key(
        0.5,
        "",
        "random_polygon (non-convex): corner radii uniform in [1 - irregularity, 1] x radius",
        _between(0.0, 0.9),
    )
    section: str = _key(
        "box", "", "beam, fibre: cross-section `box` or `cylinder`", _one_of("box", "cylinder")
    )
    file: str = _key("", "", "file: an STL, OBJ or PLY file (relative to the scenario file)")
    units: str = _key(
        "mm",
        "",
        f"file: the length unit of the file's coordinates ({', '.join(LENGTH_UNITS_MM)})",
        _one_of(*LENGTH_UNITS_MM),
    )
    size_distribution: str = _key(
        "fixed",
        "",
        "in-plane size factor per chip: `fixed` (1), `uniform` (1 +- spread), `normal` "
        "(mean 1, sd spread) or `lognormal` (median 1, log-sd spread); thickness is kept",
        _one_of("fixed", "uniform", "normal", "lognormal"),
    )
    size_spread: float = _key(0.0, "", "spread of the size factor", _between(0.0, 0.9))
    weight: float = _key(
        1.0, "", "in a `[[mix]]`: relative frequency of this chip", _between(0.0, 1e9)
    )
    fibre_directions_deg: tuple[float, ...] = _key(
        (),
        "deg",
        "fibre directions in the chip plane from local x ([]: the shape's own, woven "
        "twill [0, 90] for plates, [0] along beams and fibres)",
    )


@dataclass(frozen=True)
class DepositionSpec:
    """Batch deposition onto a square target centred on (0, 0), z up."""

    chips: int = _key(270, "", "number of chips in the stack", _positive)
    batch_size: int = _key(54, "", "chips released together; next batch once settled", _positive)
    target_size_mm: float = _key(
        150.0,
        "mm",
        "side of the square deposition target (conveyor: of the panel cut from the mat)",
        _length,
    )
    release_area_mm: float = _key(
        0.0,
        "mm",
        "side of the square over which centres are drawn (0: the target)",
        _between(0.0, MAX_LENGTH_MM),
    )
    release_height_mm: tuple[float, float] = _key(
        (100.0, 200.0),
        "mm",
        "range of the chip centre's height above the target",
        _range(0.0, MAX_LENGTH_MM),
    )
    orientation: str = _key(
        "uniform",
        "",
        "`uniform`: uniform random rotation; `ranges`: Euler angles drawn from the ranges below",
        _one_of("uniform", "ranges"),
    )
    roll_range_deg: tuple[float, float] = _key(
        (-180.0, 180.0), "deg", "rotation about x (with `ranges`)", _range(-360.0, 360.0)
    )
    pitch_range_deg: tuple[float, float] = _key(
        (-180.0, 180.0), "deg", "rotation about y (with `ranges`)", _range(-360.0, 360.0)
    )
    yaw_range_deg: tuple[float, float] = _key(
        (-180.0, 180.0), "deg", "rotation about z (with `ranges`)", _range(-360.0, 360.0)
    )

    @property
    def release_side_mm(self) -> float:
        return self.release_area_mm or self.target_size_mm


@dataclass(frozen=True)
class PhysicsSpec:
    """Contact model preset and the numerics of the rigid-body solver."""

    preset: str = _key("default", "", "physics preset: `default` or `paper`")
    friction: float = _key(-1.0, "", "override the preset's friction coefficient (-1: keep)")
    restitution: float = _key(-1.0, "", "override the preset's restitution (-1: keep)")
    time_step_s: float = _key(5e-4, "s", "integration step", _between(1e-5, 5e-3))
    solver_iterations: int = _key(10, "", "constraint-solver iterations per step", _between(1, 500))


@dataclass(frozen=True)
class SettlingSpec:
    """When a chip, and a batch, count as settled (see README: Settling)."""

    speed_mm_s: float = _key(
        5.0,
        "mm/s",
        "a chip is at rest while every point of it moves slower than this, "
        "on average over the hold time",
        _positive,
    )
    hold_time_s: float = _key(0.05, "s", "how long a chip must stay at rest to settle", _duration)
    wake_speed_mm_s: float = _key(
        20.0,
        "mm/s",
        "a chip this fast wakes the settled chips it can reach before the next check",
        _positive,
    )
    max_time_s: float = _key(
        10.0, "s", "simulated-time cap per batch; hitting it is a warning", _duration
    )
    buried_depth: float = _key(
        2.0,
        "chip lengths",
        "a settled chip whose top lies this far below the pile's surface over it is buried: "
        "never woken, static support only (1e6: every chip stays wakeable)",
        _between(0.5, 1e6),
    )
    freeze: bool = _key(
        True,
        "",
        "freeze chips at rest (false: every chip stays dynamic and a pour ends when all "
        "are at rest; the reference that freezing is checked against, its cost grows with "
        "the pile)",
    )


@dataclass(frozen=True)
class OutputSpec:
    """What is recorded in the run directory."""

    contact_distance_mm: float = _key(
        0.05, "mm", "surfaces closer than this are recorded as a contact", _non_negative
    )


@dataclass(frozen=True)
class DropSpec:
    """The single-chip drop experiment (kind `drop`; paper section 4.2)."""

    drops: int = _key(50, "", "independent drops, each onto an empty target", _between(1, 100000))
    height_mm: float = _key(
        200.0, "mm", "height of the chip's centre above the target at release", _length
    )
    tilt_deg: float = _key(
        5.7296,
        "deg",
        "tilts about x and about y are drawn uniform in [-tilt, tilt] (paper: 0.1 rad)",
        _between(0.0, 90.0),
    )
    yaw_deg: float = _key(
        0.0, "deg", "rotation about z at release (0: sides along x and y)", _between(-360, 360)
    )


@dataclass(frozen=True)
class ContainerSpec:
    """Filling a cylindrical container (kind `container`; paper section 5)."""

    radius_mm: float = _key(25.0, "mm", "inner radius of the cylinder", _length)
    height_mm: float = _key(100.0, "mm", "height of the cylinder wall", _length)
    wall_segments: int = _key(
        64, "", "flat panels approximating the round wall", _between(12, 1024)
    )
    release_radius: float = _key(
        0.5,
        "",
        "chip centres are released over a disc of this fraction of the radius",
        _between(0.0, 1.0),
    )
    release_gap_mm: tuple[float, float] = _key(
        (5.0, 30.0),
        "mm",
        "range of the clearance between the rim and a released chip's lowest possible point",
        _range(0.0, MAX_LENGTH_MM),
    )


@dataclass(frozen=True)
class ConveyorSpec:
    """A belt carrying the mat along +x, fed continuously (kind `conveyor`; see
    docs/conveyor.md). Chips are released `deposition.batch_size` at a time, at
    `deposition.release_height_mm` and `deposition.orientation`; the square panel of side
    `deposition.target_size_mm` cut from the middle of the mat is the stack that later
    stages take."""

    belt_speed_mm_s: float = _key(
        20.0,
        "mm/s",
        "speed of the belt along +x (0: the chips pile up under the pour zone)",
        _between(0.0, 1e5),
    )
    pour_rate_chips_s: float = _key(
        36.0, "chips/s", "chips released per second", _between(1e-6, 1e6)
    )
    zone_length_mm: float = _key(
        40.0,
        "mm",
        "length along the belt of the pour zone (a falling curtain's thickness)",
        _length,
    )
    zone_width_mm: float = _key(
        150.0, "mm", "width across the belt of the pour zone, centred on the belt", _length
    )
    zones: int = _key(
        1,
        "",
        "pour zones (feeders) in a row along the line, `zone_spacing_mm` apart; the belt "
        "passes under zone 0 first, and the pours take turns",
        _between(1, 100),
    )
    zone_spacing_mm: float = _key(
        100.0, "mm", "distance between the centres of neighbouring pour zones", _length
    )
    belt_width_mm: float = _key(
        200.0,
        "mm",
        "width of the belt; without side guides, a chip whose centre goes past an edge has "
        "fallen off (spilled)",
        _length,
    )
    side_guides: bool = _key(
        True,
        "",
        "walls along both edges of the belt, frictionless (a guide fixed in the line slides "
        "along the moving mat; that friction is not modelled); false: chips can fall off",
    )
    feed_speed_mm_s: float = _key(
        0.0,
        "mm/s",
        "horizontal speed along +x of a released chip, in the line's frame (an inclined "
        "feeding belt's end; 0: a falling curtain)",
        _between(-1e5, 1e5),
    )
    active_lengths: float = _key(
        5.0,
        "chip lengths",
        "settled chips this far downstream of the pour zone, with no moving chip near, "
        "leave the physics world (their poses are recorded): the cost per chip stays flat",
        _between(1.0, 1e6),
    )
    run_in_mm: float = _key(
        200.0,
        "mm",
        "the first this many mm of mat are left out of its steady part: the heap under the "
        "pour zone is still forming there (the built-in line's thickness reaches its "
        "plateau after about 200 mm; docs/conveyor.md)",
        _between(0.0, MAX_LENGTH_MM),
    )
    cell_mm: float = _key(
        50.0,
        "mm",
        "side of the square cells of the areal-weight map (its coefficient of variation is "
        "taken over the cells of the mat's steady part)",
        _length,
    )


@dataclass(frozen=True)
class GeometrySpec:
    """How the geometry stage describes the stack (see README: Descriptors)."""

    pixel_mm: float = _key(
        3.0, "mm", "pixel of the local stack thickness (NEH) map", _between(0.05, 1000.0)
    )
    layer_mm: float = _key(
        2.0, "mm", "thickness of a layer for layer filling and porosity", _between(0.05, 1000.0)
    )
    contact_gap_mm: float = _key(
        0.05, "mm", "surfaces closer than this touch (contact types)", _between(1e-4, 10.0)
    )
    contact_extent_mm: float = _key(
        5.0,
        "mm",
        "a contact patch this long is a line, this long and wide a surface",
        _between(1e-3, 1000.0),
    )
    voxel_mm: float = _key(1.0, "mm", "voxel of the stack's voxel image", _between(0.05, 100.0))


@dataclass(frozen=True)
class MeshSpec:
    """How the meshing stage meshes the stack (see README: Meshes)."""

    kind: str = _key(
        "voxel",
        "",
        "mesh kind, from the mesh-kind registry (see Meshes): `voxel` (hexahedra, always "
        "succeeds), `conformal` (gmsh tetrahedra), `image` (CGAL tetrahedra of the "
        "labelled image), `both`, or `contact` (every chip meshed on its own, contact "
        "pairs and rigid platens: the model the solve stage runs)",
    )
    voxel_mm: float = _key(0.5, "mm", "voxel of the hexahedral mesh", _between(0.05, 100.0))
    size_mm: float = _key(
        1.5, "mm", "largest element edge of the conformal mesh", _between(0.05, 100.0)
    )
    pore_space: str = _key(
        "none",
        "",
        "`box`: also mesh the pore space in the box over the chips from the conveyor to "
        "the top; `none`: chips only",
        _one_of("none", "box"),
    )
    crop: str = _key(
        "none",
        "",
        "voxel and image meshes: `target` crops them to the deposition target, `region` to "
        "`region_mm`; "
        "`none`: the whole stack",
        _one_of("none", "target", "region"),
    )
    region_mm: tuple[float, ...] = _key(
        (),
        "mm",
        "[x_min, x_max, y_min, y_max] of the crop with crop = 'region'",
        _region,
    )
    periodic: bool = _key(
        False,
        "",
        "voxel mesh cropped with pore_space = 'box': tie each node of the xmax and ymax "
        "sides to its twin on the opposite side (*EQUATION in the .inp, reference nodes "
        "REF_X and REF_Y carry the jumps): a representative volume",
    )
    min_quality: float = _key(
        0.1, "", "smallest accepted element quality (SICN) of the conformal mesh", _between(0, 1)
    )
    image_voxel_mm: float = _key(
        0.0,
        "mm",
        "image mesh: voxel of the labelled image CGAL meshes (0: an eighth of the thinnest "
        "chip dimension; below that dimension)",
        _between(0.0, 100.0),
    )
    image_optimise: bool = _key(
        False,
        "",
        "image mesh: perturb and exude slivers after the refinement (about five times the "
        "time, the worst SICN ~0.04 instead of ~0.001; CGAL's optimisers do not give the "
        "same mesh twice, so the run is no longer reproducible)",
    )
    gap_mm: float = _key(
        0.03,
        "mm",
        "conformal mesh: contact resolution leaves chips that are not in surface contact at "
        "least this far apart (at most a tenth of the thinnest chip dimension)",
        _between(1e-4, 10.0),
    )
    snap_angle_deg: float = _key(
        3.0,
        "deg",
        "conformal mesh: surface contacts whose faces are within this angle are made exactly "
        "coplanar and touching",
        _between(0.0, 15.0),
    )
    formats: tuple[str, ...] = _key(
        ("msh", "vtu", "inp", "xdmf"), "", "files to write (the CLI's --formats overrides)"
    )
    element_mm: float = _key(
        0.0,
        "mm",
        "contact model: in-plane element size (0: a tenth of the chip's shortest side, at "
        "most 2 mm)",
        _between(0.0, 100.0),
    )
    through_thickness: int = _key(
        2, "", "contact model: elements through a chip's thickness", _between(1, 16)
    )
    element: str = _key(
        "C3D8I",
        "",
        "contact model: CalculiX element (`C3D8I` incompatible modes for bending with few "
        "elements, `C3D8`, or `C3D20R`)",
        _one_of("C3D8I", "C3D8", "C3D20R"),
    )
    contact_gap_mm: float = _key(
        0.3,
        "mm",
        "contact model: chips closer than this get a contact pair",
        _between(1e-4, 10.0),
    )


@dataclass(frozen=True)
class SolveSpec:
    """The compaction the solve stage runs on the contact model (see docs/solve.md)."""

    press_fraction: float = _key(
        0.05,
        "",
        "the top platen moves down this fraction of the stack's height",
        _between(1e-4, 0.5),
    )
    friction: float = _key(
        0.3, "", "Coulomb friction between chips and on the platens", _between(0, 2)
    )
    contact_stiffness_mpa_mm: float = _key(
        1e4,
        "MPa/mm",
        "penalty stiffness of the linear pressure-overclosure contact law",
        _between(1.0, 1e8),
    )
    spring_n_mm: float = _key(
        1e-3,
        "N/mm",
        "weak springs to ground, 3 per corner of each chip's mid-plane, that make a chip "
        "held only by contact non-singular (their force is at most 12 x this x the press "
        "per chip)",
        _between(0.0, 1e3),
    )
    increments: int = _key(
        20, "", "the press is applied in at least this many increments", _between(1, 10000)
    )
    time_limit_s: float = _key(
        7200.0, "s", "stop the solver after this wall time", _between(1.0, 1e6)
    )
    threads: int = _key(0, "", "solver threads (0: one per core)", _between(0, 256))


@dataclass(frozen=True)
class Scenario:
    """A complete, validated scenario."""

    name: str = _key("scenario", "", "name used in outputs and file names", _name)
    kind: str = _key(
        "stack",
        "",
        "`stack`: batch deposition on a square target; `drop`: single-chip drops; "
        "`container`: filling a cylinder; `conveyor`: a mat poured onto a moving belt",
        _one_of("stack", "drop", "container", "conveyor"),
    )
    seed: int = _key(0, "", "seed of every random draw (the CLI's --seed overrides it)")
    chip: ChipSpec = field(default_factory=ChipSpec)
    mix: tuple[ChipSpec, ...] = _key(
        (),
        "",
        "a mix of chips, `[[mix]]` tables with the `[chip]` keys and a `weight` each; "
        "used instead of `[chip]`",
    )
    deposition: DepositionSpec = field(default_factory=DepositionSpec)
    physics: PhysicsSpec = field(default_factory=PhysicsSpec)
    settling: SettlingSpec = field(default_factory=SettlingSpec)
    output: OutputSpec = field(default_factory=OutputSpec)
    geometry: GeometrySpec = field(default_factory=GeometrySpec)
    mesh: MeshSpec = field(default_factory=MeshSpec)
    solve: SolveSpec = field(default_factory=SolveSpec)
    drop: DropSpec = field(default_factory=DropSpec)
    container: ContainerSpec = field(default_factory=ContainerSpec)
    conveyor: ConveyorSpec = field(default_factory=ConveyorSpec)

    @property
    def chips(self) -> tuple[ChipSpec, ...]:
        """The chip specs drawn from: the mix, or the single `[chip]`."""
        return self.mix or (self.chip,)

    def with_seed(self, seed: int) -> Scenario:
        return dataclasses.replace(self, seed=seed)


_SECTIONS: dict[str, type] = {
    "chip": ChipSpec,
    "deposition": DepositionSpec,
    "physics": PhysicsSpec,
    "settling": SettlingSpec,
    "output": OutputSpec,
    "geometry": GeometrySpec,
    "mesh": MeshSpec,
    "solve": SolveSpec,
    "drop": DropSpec,
    "container": ContainerSpec,
    "conveyor": ConveyorSpec,
}


def _coerce(path: str, value: Any, annotation: str) -> Any:
    """Convert a TOML value to the declared type or raise naming the key."""

    def bad(expected: str) -> InputError:
        return InputError(f"{path}: expected {expected}, got {type(value).__name__} {brief(value)}")

    if annotation == "str":
        if not isinstance(value, str):
            raise bad("a string")
        return value
    if annotation == "bool":
        if not isinstance(value, bool):
            raise bad("true or false")
        return value
    if annotation == "int":
        if isinstance(value, bool) or not isinstance(value, int):
            raise bad("an integer")
        return value
    if annotation == "float":
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise bad("a number")
        if not math.isfinite(value):
            raise InputError(f"{path}: must be finite, got {brief(value)}")
        return float(value)
    if annotation == "tuple[str, ...]":
        if not isinstance(value, list | tuple) or not all(isinstance(v, str) for v in value):
            raise bad("a list of strings")
        return tuple(value)
    if annotation.startswith("tuple[float"):
        if not isinstance(value, list | tuple):
            raise bad("a list of numbers")
        items = tuple(_coerce(f"{path}[{i}]", v, "float") for i, v in enumerate(value))
        if annotation == "tuple[float, float]" and len(items) != 2:
            raise InputError(f"{path}: expected a pair [low, high], got {len(items)} values")
        return items
    raise TypeError(f"undeclared type {annotation} for {path}")  # a bug here, not user input


def _build(cls: type, table: Mapping[str, Any], prefix: str) -> Any:
    if not isinstance(table, Mapping):
        raise InputError(f"{prefix or 'scenario'}: expected a table, got {type(table).__name__}")
    declared = {f.name: f for f in dataclasses.fields(cls)}
    nested = {name for name in declared if name in _SECTIONS and prefix == ""}
    for key in table:
        if key not in declared:
            where = f"[{prefix}]" if prefix else "the top level"
            valid = ", ".join(sorted(declared))
            raise InputError(
                f"{prefix + '.' if prefix else ''}{printable(key)}: unknown key in {where}; "
                f"valid keys: {valid}"
            )
    values: dict[str, Any] = {}
    for name, f in declared.items():
        path = f"{prefix}.{name}" if prefix else name
        if name in nested:
            values[name] = _build(_SECTIONS[name], table.get(name, {}), name)
            continue
        if name not in table:
            continue
        if str(f.type) == "tuple[ChipSpec, ...]":
            items = table[name]
            if not isinstance(items, list) or not all(isinstance(t, Mapping) for t in items):
                raise InputError(f"{path}: expected [[{name}]] tables")
            if not items:
                raise InputError(f"{path}: give at least one [[{name}]] table")
            values[name] = tuple(
                _build(ChipSpec, item, f"{name}[{i}]") for i, item in enumerate(items)
            )
            continue
        value = _coerce(path, table[name], str(f.type))
        check = f.metadata.get("check")
        problem = check(value) if check else None
        if problem:
            raise InputError(f"{path}: {problem} (got {brief(value)})")
        values[name] = value
    return cls(**values)


def scenario_from_dict(data: Mapping[str, Any], base_dir: str | None = None) -> Scenario:
    """Validate a nested mapping (a parsed TOML file) into a :class:`Scenario`.

    ``base_dir``: where relative geometry-file paths start (the scenario file's folder).
    Raises :class:`InputError` naming the first bad key.
    """
    if isinstance(data, Mapping) and "chip" in data and "mix" in data:
        raise InputError("mix: give either [chip] or [[mix]] tables, not both")
    scenario = _build(Scenario, data, "")
    scenario = _resolve_files(scenario, base_dir)
    _check_consistency(scenario)
    for stage in load_stages():
        stage.check(scenario)
    return scenario


def _resolve_files(scenario: Scenario, base_dir: str | None) -> Scenario:
    """Geometry-file paths made absolute, so the resolved scenario works from anywhere."""

    def resolve(spec: ChipSpec) -> ChipSpec:
        if not spec.file or os.path.isabs(spec.file):
            return spec
        return dataclasses.replace(
            spec, file=os.path.abspath(os.path.join(base_dir or os.getcwd(), spec.file))
        )

    return dataclasses.replace(
        scenario, chip=resolve(scenario.chip), mix=tuple(resolve(c) for c in scenario.mix)
    )


def _check_consistency(s: Scenario) -> None:
    """Checks that need only the schema; each stage adds its own (``Stage.check``)."""
    d = s.deposition
    if d.batch_size > d.chips:
        raise InputError(
            f"deposition.batch_size: {d.batch_size} is larger than deposition.chips ({d.chips})"
        )
    if not 0 <= s.seed <= MAX_SEED:
        raise InputError(f"seed: must be between 0 and {MAX_SEED} (got {brief(s.seed)})")
    if s.mix and sum(c.weight for c in s.mix) <= 0:
        raise InputError("mix: the weights sum to 0; give at least one chip a positive weight")
    for name in ("friction", "restitution"):
        value = getattr(s.physics, name)
        if value != -1.0 and not 0 <= value <= 10:
            raise InputError(
                f"physics.{name}: must be between 0 and 10 (or -1 to keep the "
                f"preset's), got {brief(value)}"
            )
    if s.settling.hold_time_s >= s.settling.max_time_s:
        raise InputError("settling.hold_time_s: must be shorter than settling.max_time_s")
    if d.chips > 200_000:
        raise InputError(f"deposition.chips: {d.chips} is beyond what one run can hold (200000)")


def scenario_to_dict(scenario: Scenario) -> dict[str, Any]:
    """The resolved scenario as a nested dict of plain TOML values (every key present)."""

    def plain(value: Any) -> Any:
        if dataclasses.is_dataclass(value):
            return {f.name: plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
        if isinstance(value, tuple):
            return [plain(v) for v in value]
        return value

    return plain(scenario)


def key_table() -> list[tuple[str, str, str, str]]:
    """(key, unit, default, description) for every scenario key, for documentation."""
    rows = []
    for f in dataclasses.fields(Scenario):
        if f.name in _SECTIONS:
            for g in dataclasses.fields(_SECTIONS[f.name]):
                rows.append(
                    (f"{f.name}.{g.name}", g.metadata["unit"], repr(g.default), g.metadata["doc"])
                )
        else:
            rows.append((f.name, f.metadata["unit"], repr(f.default), f.metadata["doc"]))
    return rows


def key_table_markdown() -> str:
    """The README's table of scenario keys (a test checks the README holds it verbatim)."""
    lines = ["| key | unit | default | meaning |", "|---|---|---|---|"]
    lines += [
        f"| `{key}` | {unit or '-'} | `{default}` | {doc} |"
        for key, unit, default, doc in key_table()
    ]
    return "\n".join(lines)
