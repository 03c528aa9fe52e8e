"""The contract kit (issue 57): what every registered entry of every registry keeps, with
test ids generated from the registries themselves, so a new built-in or an installed
plugin's entry is tested without editing this file (``tests/test_plugins.py`` runs the
kit again with the test plugin installed and finds its entries among the ids).

Every entry has a generated row in the docs. Where a registry's entries run in a stage,
each runs end to end there on a small case, and what it writes is read back by the
library a user would read it with: every stack writer's files, every descriptor's section,
every mesh format (meshio), every mesh kind's mesh of a small stack; every effect changes
nothing at its neutral strength and something at its prior's middle.
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import meshio
import numpy as np
import pytest
import pyvista
from conftest import write_box_obj
from parts import require

from chipstack.pipeline.reference import GENERATED, _registries

REGISTRIES = {r.kind: r for layer in _registries().values() for r in layer}

# The generated docs table of each registry (pipeline/reference.py: GENERATED).
TABLE_OF = {
    "stage": "stages",
    "figure": "figures",
    "physics preset": "presets",
    "deposition site": "sites",
    "effect": "effects",
    "stack writer": "stack_writers",
    "scenario kind": "scenario_kinds",
    "shape": "shapes",
    "descriptor": "descriptors",
    "mesh format": "mesh_formats",
    "mesh kind": "mesh_kinds",
    "solve model": "solve_models",
    "experiment kind": "experiment_kinds",
    "quantity measure": "quantity_measures",
}


def entries(*kinds: str) -> list:
    """pytest params ``kind:name`` of every entry of the given registries (all if none)."""
    chosen = kinds or sorted(REGISTRIES)
    return [
        pytest.param(kind, name, id=f"{kind}:{name}")
        for kind in chosen
        for name in REGISTRIES[kind].in_order()
    ]


def names(kind: str) -> list:
    return [pytest.param(name, id=name) for name in REGISTRIES[kind].in_order()]


def test_every_registry_has_a_generated_docs_table_on_a_page():
    pages = "".join(p.read_text() for p in (Path(__file__).parent.parent / "docs").glob("*.md"))
    missing = sorted(set(REGISTRIES) - set(TABLE_OF))
    assert not missing, f"registries without a generated docs table: {missing}"
    for table in TABLE_OF.values():
        assert f"<!-- BEGIN generated:{table} -->" in pages, table


def _row(table: str, name: str) -> str | None:
    """The row of ``name`` in a generated table, if it has one row with a description."""
    rows = [line for line in table.splitlines() if line.startswith(f"| `{name}` |")]
    if len(rows) != 1:
        return None
    cells = [cell.strip() for cell in rows[0].strip().strip("|").split("|")]
    return rows[0] if len(cells) >= 2 and all(cells[1:]) else None


@pytest.mark.parametrize(("kind", "name"), entries())
def test_every_entry_has_a_row_in_its_generated_table(kind, name):
    row = _row(GENERATED[TABLE_OF[kind]](), name)
    assert row, f"{kind} {name!r}: no row of its own in the {TABLE_OF[kind]} table"


def test_the_kit_finds_a_missing_row_an_empty_one_and_a_nan():
    table = "| a | b |\n|---|---|\n| `box` | a box |\n| `bare` | |"
    assert _row(table, "box") and not _row(table, "star") and not _row(table, "bare")
    assert _finite({"a": [1.0, {"b": 2}]}) and not _finite({"a": [1.0, {"b": math.nan}]})


SMALL_MESHED = '[mesh]\nkind = "voxel"\nvoxel_mm = 1.0\n'


@pytest.fixture(scope="module")
def small_run(tmp_path_factory) -> Path:
    """The small stack through packing, geometry and the voxel mesh in every format."""
    from conftest import SMALL_SCENARIO, run_scenario

    return run_scenario(SMALL_SCENARIO + SMALL_MESHED, tmp_path_factory.mktemp("kit"), "mesh")


def _read_back(path: Path) -> None:
    """Read a written file with what a user reads it with; raises when it cannot."""
    suffix = path.suffix
    if suffix == ".csv":
        with path.open(newline="") as f:
            rows = list(csv.reader(f))
        assert rows and rows[0], path
    elif suffix == ".json":
        json.loads(path.read_text())
    elif suffix == ".npz":
        with np.load(path, allow_pickle=False) as arrays:
            assert arrays.files, path
    elif suffix in (".vtp", ".vtu", ".vti", ".pvd"):
        # pyvista reads an empty or truncated file as an empty dataset, never None: every
        # dataset read (each block of a .pvd series) must hold points and cells.
        data = pyvista.read(path)
        blocks = list(data) if isinstance(data, pyvista.MultiBlock) else [data]
        assert blocks, f"{path}: no dataset"
        for block in blocks:
            assert block.n_points > 0 and block.n_cells > 0, (path, block)
    else:
        assert path.stat().st_size > 0, path


@pytest.mark.parametrize("name", names("stack writer"))
def test_every_stack_writer_writes_files_that_read_back(small_run, name):
    writer = REGISTRIES["stack writer"].get(name)
    for pattern in (p.strip() for p in writer.files.split(",")):
        found = sorted((small_run / "packing").glob(pattern.replace("NN", "*")))
        assert found, f"stack writer {name!r}: no {pattern} in packing/"
        for path in found:
            _read_back(path)


def _finite(value) -> bool:
    if isinstance(value, dict):
        return all(_finite(v) for v in value.values())
    if isinstance(value, list):
        return all(_finite(v) for v in value)
    if isinstance(value, float):
        return math.isfinite(value)
    return True


@pytest.mark.parametrize("name", names("descriptor"))
def test_every_descriptor_writes_its_section_of_finite_numbers(small_run, name):
    sections = json.loads((small_run / "geometry" / "descriptors.json").read_text())
    section = sections["descriptors"].get(name)
    assert section, f"descriptor {name!r}: no section in descriptors.json"
    assert _finite(section), f"descriptor {name!r}: a NaN or an infinity in its section"


@pytest.mark.parametrize("name", names("mesh format"))
def test_every_mesh_format_reads_back_with_meshio(small_run, name):
    checks = json.loads((small_run / "mesh" / "stack_voxel_checks.json").read_text())
    back = meshio.read(small_run / "mesh" / f"stack_voxel.{name}")
    volume_cells = sum(len(b.data) for b in back.cells if b.type in ("hexahedron", "tetra"))
    assert volume_cells == checks["elements"], name
    # Every format writes the mesh's nodes once (measured: 31,467 read back from vtu,
    # msh, xdmf and inp alike): a duplicated or lost node is a defect.
    assert len(back.points) == checks["nodes"], name


TINY = """
name = "tiny"
seed = 4
[chip]
length_mm = 20.0
width_mm = 20.0
thickness_mm = 2.0
[deposition]
chips = 3
batch_size = 3
target_size_mm = 40.0
release_height_mm = [30.0, 50.0]
[mesh]
kind = "{kind}"
{keys}"""


@pytest.mark.parametrize("name", names("mesh kind"))
def test_every_mesh_kind_meshes_a_small_stack_valid(tmp_path, name):
    """Each mesh kind through ``pipeline run --to mesh`` on three settled chips: its files
    written and its own check valid (the image kind needs CGAL, which CI installs)."""
    from conftest import run_scenario

    if name == "image":
        require("cgal")
    # The voxel route at 1 mm, not its default 0.5: a kind that takes the key gets it.
    keys = "voxel_mm = 1.0\n" if REGISTRIES["mesh kind"].get(name).takes("voxel_mm") else ""
    out = run_scenario(TINY.format(kind=name, keys=keys), tmp_path, "mesh")
    summary = json.loads((out / "manifest.json").read_text())["stages"]["mesh"]["summary"]
    assert name in summary, summary
    # Every kind writes its own check's report (the contact model's too, whose manifest
    # entry has no "valid": it raises when its check fails).
    checks = json.loads((out / "mesh" / f"stack_{name}_checks.json").read_text())
    assert checks["valid"] is True, checks
    written = [p for p in (out / "mesh").iterdir() if p.name.startswith(f"stack_{name}")]
    assert written, f"mesh kind {name!r} wrote no stack_{name}* file"


@pytest.mark.parametrize("name", names("effect"))
def test_every_effect_changes_nothing_at_its_neutral_strength(name):
    """At its neutral strength an effect leaves every drop (or every settled chip of a
    small stack) exactly as the baseline's; at its prior's middle it moves something."""
    from chipstack.diagnosis.reference_table import simulate_pool
    from chipstack.packing.drop import DropProtocol
    from chipstack.packing.effects import EFFECTS, contact_model
    from chipstack.packing.presets import PRESETS
    from chipstack.pipeline.scenario_files import load_scenario

    effect = EFFECTS.get(name)
    lo, hi = effect.prior
    if "drop" in effect.kinds:
        scenario = load_scenario("single-chip-drop")
        contact = contact_model(PRESETS.get(scenario.physics.preset), scenario.physics)

        def outcome(strengths):
            return simulate_pool(scenario, DropProtocol(height_mm=300.0), 3, strengths, 5)
    else:
        import tempfile

        from chipstack.packing import deposit

        with tempfile.TemporaryDirectory() as folder:
            path = Path(folder) / "tiny.toml"
            path.write_text(TINY.format(kind="voxel", keys=""))
            scenario = load_scenario(path)
        contact = contact_model(PRESETS.get(scenario.physics.preset), scenario.physics)

        def outcome(strengths):
            return deposit(scenario, effects=strengths).positions

    baseline = outcome({})
    assert np.array_equal(outcome({name: effect.neutral(contact)}), baseline)
    assert not np.array_equal(outcome({name: (lo + hi) / 2}), baseline)


# Kinds with keys of their own: every kind a table chooses by name (the shapes of [chip]
# and [[mix]], the mesh kinds of [mesh]), found from the stages' declarations.
def _kind_tables() -> dict[str, object]:
    from chipstack.core.stages import load_stages

    return {t: c for stage in load_stages() for t, c in stage.kind_choices.items()}


TABLE_OF_REGISTRY = {"shape": "chip", "mesh kind": "mesh", "solve model": "solve"}


def _kind_params() -> list:
    """``kind:name`` of every entry of the registries whose kinds a table chooses (a
    combined mesh kind such as ``both`` included: its table is its kinds' keys)."""
    choices = _kind_tables()
    return [
        pytest.param(table, name, id=f"{table}:{name}")
        for table, choice in choices.items()
        for name in choice.names()
    ]


def test_every_registry_whose_kinds_a_table_chooses_is_in_the_kit():
    assert set(_kind_tables()) == set(TABLE_OF_REGISTRY.values())
    for registry, table in TABLE_OF_REGISTRY.items():
        names = set(_kind_tables()[table].names())
        assert set(REGISTRIES[registry].names()) <= names, registry


def _scenario_giving(table: str, name: str) -> dict:
    """Scenario tables whose kind of ``table`` follows as ``name`` (the solve model from
    the mesh): each mesh kind, alone and with its pore space, the first that gives it."""
    from chipstack.core.scenario_data import scenario_from_dict

    for kind in REGISTRIES["mesh kind"].in_order():
        pores = [{}] + (
            [{"pore_space": "box"}] if REGISTRIES["mesh kind"].get(kind).takes("pore_space") else []
        )
        for extra in pores:
            data = {"mesh": {"kind": kind, **extra}, table: {}}
            if getattr(scenario_from_dict(data), table).model == name:
                return data
    raise AssertionError(f"no mesh gives {table} kind {name!r}")


def _bad_values(f) -> list:
    """Values of the wrong type for a key, and one outside its declared range if it has
    one (found by asking its check), each refused by the scenario's validator. Only
    candidates of the default's type (or numbers for a number) are asked, so a check
    that raises is a defect of the check and fails here; a key with a check must have a
    candidate it refuses, or its range would go untested."""
    import dataclasses

    kind = str(f.type)
    wrong = {"str": [3], "bool": ["yes"], "int": [1.5, "2"], "float": ["1", True]}
    values = list(wrong.get(kind, ["x"] if kind.startswith("tuple") else [None]))
    check = f.metadata.get("check")
    if check is not None:
        default = f.default if f.default is not dataclasses.MISSING else None
        candidates = [
            candidate
            for candidate in (-1e9, 1e9, -1, 0, 10**9, "no-such-value", ("a",), (1.0,))
            if type(candidate) is type(default)
            or (isinstance(candidate, int | float) and isinstance(default, int | float))
        ]
        refused = [candidate for candidate in candidates if check(candidate) is not None]
        assert refused, f"{f.name}: its check refuses none of {candidates}"
        values.append(refused[0])
    return values


@pytest.mark.parametrize(("table", "name"), _kind_params())
def test_every_kind_with_keys_refuses_each_bad_value_and_round_trips(tmp_path, table, name):
    """A scenario that chooses the kind loads, writes its resolved TOML with the kind's
    keys and no other kind's, and loads back equal; each key of the kind given a value of
    the wrong type, or one outside its range, is refused with an ``InputError`` naming
    the key (the CLI's one-line error); a key of the table no kind declares is refused."""
    import dataclasses
    import tomllib

    from chipstack.core.errors import InputError
    from chipstack.core.scenario_data import scenario_from_dict
    from chipstack.core.schema import parameter_fields
    from chipstack.pipeline.scenario_files import dumps_toml

    choice = _kind_tables()[table]
    if choice.follows is None:  # a key of the table chooses the kind
        selector = {"chip": "shape", "mesh": "kind"}[table]
        base = {table: {selector: name}}
    else:  # the kind follows from the other tables: the first mesh that gives it
        selector = "model"
        base = _scenario_giving(table, name)
    keys = parameter_fields(choice.parameters_of(name, f"{table}.{selector}"))
    if any(f.metadata.get("path") for f in keys.values()):  # a file key: a 10 x 10 x 2 box
        path = write_box_obj(tmp_path / "chip.obj", 10.0, 2.0)
        base[table].update({n: str(path) for n, f in keys.items() if f.metadata.get("path")})
    scenario = scenario_from_dict(base)
    text = dumps_toml(scenario)
    assert scenario_from_dict(tomllib.loads(text)) == scenario
    written = tomllib.loads(text)[table]
    own = {f.name for f in dataclasses.fields(type(getattr(scenario, table)))} - {"params"}
    if choice.follows is not None:
        own.discard(selector)  # not a key of the file
    assert set(written) == own | set(keys), sorted(written)
    for key_, f in keys.items():
        for value in _bad_values(f):
            with pytest.raises(InputError, match=rf"^{table}\.{key_}(\[\d+\])?: ") as refused:
                scenario_from_dict({**base, table: {**base[table], key_: value}})
            assert "\n" not in str(refused.value)
    with pytest.raises(InputError, match=rf"^{table}\.no_such_key: unknown key"):
        scenario_from_dict({**base, table: {**base[table], "no_such_key": 1}})


@pytest.mark.parametrize("name", names("effect"))
def test_every_effect_refuses_a_strength_out_of_its_prior_and_a_kind_it_does_not_act_on(name):
    from chipstack.core.errors import InputError
    from chipstack.packing.effects import EFFECTS, check_effects

    effect = EFFECTS.get(name)
    lo, hi = effect.prior
    assert check_effects({name: (lo + hi) / 2}, effect.kinds[0]) == {name: (lo + hi) / 2}
    for bad in (hi + (hi - lo) + 1, "strong"):
        with pytest.raises(InputError, match=rf"^effects\.{name}: "):
            check_effects({name: bad}, effect.kinds[0])
    other = [k for k in REGISTRIES["scenario kind"].in_order() if k not in effect.kinds]
    if other:
        with pytest.raises(InputError, match=rf"^effects\.{name}: effect acts on"):
            check_effects({name: (lo + hi) / 2}, other[0])


@pytest.mark.parametrize("name", names("scenario kind"))
def test_every_scenario_kind_round_trips_and_refuses_bad_values_of_its_own_tables(name):
    """A scenario of the kind loads and round-trips through its resolved TOML; a key of
    each of the kind's own tables given a value of the wrong type is refused naming it."""
    import dataclasses
    import tomllib

    from chipstack.core.errors import InputError
    from chipstack.core.scenario_data import scenario_from_dict
    from chipstack.core.schema import sections
    from chipstack.pipeline.scenario_files import builtin_names, dumps_toml, load_scenario

    # A built-in scenario of the kind if there is one (a conveyor needs a long enough
    # pour), else the kind's defaults.
    built_in = [s for s in map(load_scenario, builtin_names()) if s.kind == name]
    scenario = built_in[0] if built_in else scenario_from_dict({"kind": name})
    data = tomllib.loads(dumps_toml(scenario))
    assert scenario_from_dict(data) == scenario
    for cls in (c for c in sections() if name in c.kinds):
        for f in dataclasses.fields(cls):
            for value in _bad_values(f)[:1]:
                bad = {**data, cls.table: {**data[cls.table], f.name: value}}
                with pytest.raises(InputError, match=rf"^{cls.table}\.{f.name}(\[\d+\])?: "):
                    scenario_from_dict(bad)


def _chip_keys(table, name: str, folder: Path) -> dict:
    """A small chip of shape ``name`` (its defaults; a file shape gets a 10 x 10 x 2 box)."""
    keys = {"shape": name}
    from chipstack.core.schema import parameter_fields

    fields = parameter_fields(table.parameters_of(name, "chip.shape"))
    for key_, f in fields.items():
        if f.metadata.get("path"):
            keys[key_] = str(write_box_obj(folder / "chip.obj", 10.0, 2.0))
    return keys


@pytest.mark.parametrize("name", names("shape"))
def test_every_shape_packs_a_small_stack_and_its_chips_read_back(tmp_path, name):
    """Three chips of each shape through ``pipeline run --to packing``: settled on the
    conveyor, their shapes written and read back, each as voluminous as the shape built
    from the scenario's own keys."""
    import tomllib

    from conftest import run_scenario

    from chipstack.core.scenario_data import scenario_from_dict
    from chipstack.packing.shapes import make_shape, shape_from_record
    from chipstack.pipeline.scenario_files import dumps_toml

    chip = _chip_keys(_kind_tables()["chip"], name, tmp_path)
    data = tomllib.loads(TINY.format(kind="voxel", keys=""))
    data["chip"] = chip
    data["deposition"]["target_size_mm"] = 80.0
    text = dumps_toml(scenario_from_dict(data))
    out = run_scenario(text, tmp_path, "packing")
    shapes = json.loads((out / "packing" / "shapes.json").read_text())["shapes"]
    spec = scenario_from_dict(data).chip
    built = make_shape(spec, np.random.default_rng(0), 1.0)
    assert len(shapes) >= 1
    for k, record in enumerate(shapes):
        shape = shape_from_record(record, f"shapes[{k}]")
        if not spec.chosen.varies_per_chip:
            assert shape.volume_mm3 == pytest.approx(built.volume_mm3, rel=1e-9)
    with open(out / "packing" / "poses_after_batch_01.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 3 and all(float(r["z_mm"]) > 0 for r in rows)
