"""Typed, frozen scenario configuration and its validation.

A scenario is a nested table (usually read from TOML). Every key is declared once here,
with its type, unit, default and a one-line description; the validator, the README's key
table and the resolved-scenario writer are all driven by these declarations, so they
cannot drift apart.
"""

from __future__ import annotations

import dataclasses
import math
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from packing.errors import InputError

__all__ = [
    "ChipSpec",
    "DepositionSpec",
    "PhysicsSpec",
    "SettlingSpec",
    "OutputSpec",
    "GeometrySpec",
    "MeshSpec",
    "Scenario",
    "scenario_from_dict",
    "scenario_to_dict",
    "key_table",
]


def printable(text: object) -> str:
    """``text`` as is when it prints on one line, else its repr (messages stay one line)."""
    text = str(text)
    return text if text.isprintable() else repr(text)


def _key(default: Any, unit: str, doc: str, check: Callable[[Any], str | None] | None = None):
    return field(default=default, metadata={"unit": unit, "doc": doc, "check": check})


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


@dataclass(frozen=True)
class ChipSpec:
    """The chip: a flat plate. Lengths in mm, fibre directions in degrees in the chip plane."""

    shape: str = _key("box", "", "chip shape from the shape registry (`box`: square or rectangle)")
    length_mm: float = _key(20.0, "mm", "in-plane length (local x)", _length)
    width_mm: float = _key(20.0, "mm", "in-plane width (local y)", _length)
    thickness_mm: float = _key(2.0, "mm", "thickness (local z)", _length)
    fibre_directions_deg: tuple[float, ...] = _key(
        (0.0, 90.0), "deg", "fibre directions in the chip plane from local x (twill: two)"
    )


@dataclass(frozen=True)
class DepositionSpec:
    """Batch deposition onto a square target centred on (0, 0), z up."""

    chips: int = _key(270, "", "number of chips in the stack", _positive)
    batch_size: int = _key(54, "", "chips released together; next batch once settled", _positive)
    target_size_mm: float = _key(150.0, "mm", "side of the square deposition target", _length)
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


@dataclass(frozen=True)
class OutputSpec:
    """What is recorded in the run directory."""

    contact_distance_mm: float = _key(
        0.05, "mm", "surfaces closer than this are recorded as a contact", _non_negative
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
        "`voxel` (hexahedra, always succeeds), `conformal` (gmsh tetrahedra) or `both`",
        _one_of("voxel", "conformal", "both"),
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
    min_quality: float = _key(
        0.1, "", "smallest accepted element quality (SICN) of the conformal mesh", _between(0, 1)
    )
    formats: tuple[str, ...] = _key(
        ("msh", "vtu", "inp", "xdmf"), "", "files to write (the CLI's --formats overrides)"
    )


@dataclass(frozen=True)
class Scenario:
    """A complete, validated scenario."""

    name: str = _key("scenario", "", "name used in outputs and file names", _name)
    kind: str = _key("stack", "", "scenario kind (`stack`: batch deposition)", _one_of("stack"))
    seed: int = _key(0, "", "seed of every random draw (the CLI's --seed overrides it)")
    chip: ChipSpec = field(default_factory=ChipSpec)
    deposition: DepositionSpec = field(default_factory=DepositionSpec)
    physics: PhysicsSpec = field(default_factory=PhysicsSpec)
    settling: SettlingSpec = field(default_factory=SettlingSpec)
    output: OutputSpec = field(default_factory=OutputSpec)
    geometry: GeometrySpec = field(default_factory=GeometrySpec)
    mesh: MeshSpec = field(default_factory=MeshSpec)

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
}


def _coerce(path: str, value: Any, annotation: str) -> Any:
    """Convert a TOML value to the declared type or raise naming the key."""

    def bad(expected: str) -> InputError:
        return InputError(f"{path}: expected {expected}, got {type(value).__name__} {value!r}")

    if annotation == "str":
        if not isinstance(value, str):
            raise bad("a string")
        return value
    if annotation == "int":
        if isinstance(value, bool) or not isinstance(value, int):
            raise bad("an integer")
        return value
    if annotation == "float":
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise bad("a number")
        if not math.isfinite(value):
            raise InputError(f"{path}: must be finite, got {value!r}")
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
        value = _coerce(path, table[name], str(f.type))
        check = f.metadata.get("check")
        problem = check(value) if check else None
        if problem:
            raise InputError(f"{path}: {problem} (got {value!r})")
        values[name] = value
    return cls(**values)


def scenario_from_dict(data: Mapping[str, Any]) -> Scenario:
    """Validate a nested mapping (a parsed TOML file) into a :class:`Scenario`.

    Raises :class:`InputError` naming the first bad key.
    """
    scenario = _build(Scenario, data, "")
    _check_consistency(scenario)
    return scenario


MESH_FORMAT_NAMES = ("inp", "msh", "vtu", "xdmf")  # export.mesh_files registers these


def check_formats(formats: tuple[str, ...], key: str) -> None:
    """Refuse an empty list or an unknown mesh format, listing the valid ones."""
    if not formats:
        raise InputError(f"{key}: give at least one format ({', '.join(MESH_FORMAT_NAMES)})")
    for name in formats:
        if name not in MESH_FORMAT_NAMES:
            raise InputError(
                f"{key}: unknown mesh format {printable(name)!r}; "
                f"valid formats: {', '.join(MESH_FORMAT_NAMES)}"
            )


def _check_consistency(s: Scenario) -> None:
    from packing.presets import PRESETS
    from packing.shapes import SHAPES

    SHAPES.get(s.chip.shape, key="chip.shape")
    PRESETS.get(s.physics.preset, key="physics.preset")
    d = s.deposition
    if d.batch_size > d.chips:
        raise InputError(
            f"deposition.batch_size: {d.batch_size} is larger than deposition.chips ({d.chips})"
        )
    if s.seed < 0:
        raise InputError(f"seed: must not be negative (got {s.seed})")
    if s.chip.thickness_mm >= min(s.chip.length_mm, s.chip.width_mm):
        raise InputError("chip.thickness_mm: a chip must be thinner than it is long and wide")
    if not s.chip.fibre_directions_deg:
        raise InputError("chip.fibre_directions_deg: give at least one fibre direction")
    for name in ("friction", "restitution"):
        value = getattr(s.physics, name)
        if value != -1.0 and not 0 <= value <= 10:
            raise InputError(
                f"physics.{name}: must be between 0 and 10 (or -1 to keep the "
                f"preset's), got {value!r}"
            )
    circumradius = 0.5 * math.dist(
        (0, 0, 0), (s.chip.length_mm, s.chip.width_mm, s.chip.thickness_mm)
    )
    if d.release_height_mm[0] <= circumradius:
        raise InputError(
            "deposition.release_height_mm: the lowest release height must clear the chip's "
            f"circumradius ({circumradius:.1f} mm) so no release pose touches the floor"
        )
    if s.settling.hold_time_s >= s.settling.max_time_s:
        raise InputError("settling.hold_time_s: must be shorter than settling.max_time_s")
    check_formats(s.mesh.formats, "mesh.formats")
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
