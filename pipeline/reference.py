"""Reference tables generated from the code's own schema and registries, and the docs
pages that hold them (between ``<!-- BEGIN generated:NAME -->`` and ``<!-- END
generated:NAME -->`` markers). ``python -m chipstack.pipeline.reference`` refreshes the pages; a
test checks they are up to date, so the documentation cannot drift from the code."""

from __future__ import annotations

import dataclasses
import importlib
import logging
import pkgutil
import re
from collections.abc import Callable
from pathlib import Path

import chipstack.meshing.files  # noqa: F401  (registers the mesh's figure)
from chipstack.core.key_tables import key_table_markdown
from chipstack.core.registry import Registry
from chipstack.core.schema import sections
from chipstack.core.stages import load_stages
from chipstack.diagnosis.spec import EXPERIMENT_KINDS
from chipstack.diagnosis.stacks import QUANTITY_MEASURES
from chipstack.export.figure_kinds import FIGURES, SUBJECT_FOLDERS
from chipstack.geometry.descriptor_kinds import DESCRIPTORS
from chipstack.meshing.formats import MESH_FORMATS
from chipstack.meshing.kinds import MESH_KINDS
from chipstack.meshing.solve_models import SOLVE_MODELS
from chipstack.packing.effects import EFFECTS
from chipstack.packing.files import STACK_WRITERS
from chipstack.packing.kinds import SCENARIO_KINDS
from chipstack.packing.presets import PRESETS
from chipstack.packing.shapes import SHAPES
from chipstack.packing.sites import SITES

__all__ = ["GENERATED", "refresh", "stale_blocks"]

DOCS = Path(__file__).resolve().parent.parent / "docs"
_BLOCK = re.compile(
    r"(<!-- BEGIN generated:(?P<name>[a-z_]+) -->\n)"
    r"(?P<body>.*?)"
    r"(\n<!-- END generated:(?P=name) -->)",
    re.DOTALL,
)


def _first_line(text: str | None) -> str:
    return " ".join((text or "").strip().split("\n\n")[0].split())


def _table(header: tuple[str, str], rows: list[tuple[str, str]]) -> str:
    lines = [f"| {header[0]} | {header[1]} |", "|---|---|"]
    return "\n".join(lines + [f"| `{name}` | {text} |" for name, text in rows])


def stages_markdown() -> str:
    """The registered stages, upstream first."""
    rows = []
    for stage in load_stages():
        upstream = ", ".join(stage.upstream) or "-"
        doc = _first_line(type(stage).__doc__)
        owns = ", ".join(f"`[{cls.table}]`" for cls in stage.owned_sections) or "-"
        reads = ", ".join(f"`[{name}]`" for name in stage.sections)
        rows.append((stage.name, f"{doc} (after: {upstream}; declares {owns}; reads {reads})"))
    return _table(("stage", "what it does"), rows)


def _keys(parameters: type) -> str:
    """A kind's own keys, for its row (each key's meaning is in the scenario key table)."""
    names = [f"`{f.name}`" for f in dataclasses.fields(parameters)]
    return f" Keys: {', '.join(names)}." if names else " No keys of its own."


def shapes_markdown() -> str:
    rows = [
        (n, _first_line(SHAPES.get(n).builder.__doc__) + _keys(SHAPES.get(n).parameters))
        for n in SHAPES.in_order()
    ]
    return _table(("shape", "what it is"), rows)


def descriptors_markdown() -> str:
    rows = [(n, DESCRIPTORS.get(n).doc) for n in DESCRIPTORS.in_order()]
    return _table(("descriptor", "what it measures"), rows)


def mesh_formats_markdown() -> str:
    rows = [(n, _first_line(MESH_FORMATS.get(n).__doc__)) for n in MESH_FORMATS.in_order()]
    return _table(("format", "what is written"), rows)


def stack_writers_markdown() -> str:
    rows = []
    for name in STACK_WRITERS.in_order():
        writer = STACK_WRITERS.get(name)
        read = "; read by later stages" if writer.record else ""
        rows.append((name, f"`{writer.files}`: {writer.doc}{read}"))
    return _table(("stack writer", "what it writes into packing/"), rows)


def figures_markdown() -> str:
    rows = []
    for name in FIGURES.in_order():
        kind = FIGURES.get(name)
        where = SUBJECT_FOLDERS[kind.subject]
        rows.append((name, f"`{where}{kind.files}`, from {kind.subject}: {kind.doc}"))
    return _table(("figure", "what it draws"), rows)


def mesh_kinds_markdown() -> str:
    rows = []
    for name in MESH_KINDS.in_order():
        kind = MESH_KINDS.get(name)
        solved = ", ".join(kind.solve_models) or "-"
        keys = _keys(kind.parameters)
        rows.append((name, f"{kind.doc} (solve models: {solved}).{keys}"))
    return _table(("mesh kind", "what it is"), rows)


def solve_models_markdown() -> str:
    rows = [
        (n, _first_line(type(model).__doc__) + _keys(model.parameters))
        for n, model in ((n, SOLVE_MODELS.get(n)) for n in SOLVE_MODELS.in_order())
    ]
    return _table(("solve model", "what it presses"), rows)


def effects_markdown() -> str:
    """Every effect: its strength and unit, the prior the diagnosis searches, the kinds of
    scenario it acts in and why it may be missing from the model."""
    lines = [
        "| effect | strength | prior | kinds | why it may be missing from the model |",
        "|---|---|---|---|---|",
    ]
    for name in EFFECTS.in_order():
        effect = EFFECTS.get(name)
        unit = f" ({effect.unit})" if effect.unit else ""
        lo, hi = effect.prior
        lines.append(
            f"| `{name}` | {effect.parameter}{unit} | {lo:g} to {hi:g} | "
            f"{', '.join(effect.kinds)} | {_first_line(effect.justification)} |"
        )
    return "\n".join(lines)


def scenario_kinds_markdown() -> str:
    """The registered scenario kinds, their own tables, deposition sites and which later
    stages run."""
    rows = []
    for name in SCENARIO_KINDS.in_order():
        kind = SCENARIO_KINDS.get(name)
        own = ", ".join(f"`[{c.table}]`" for c in sections() if name in c.kinds) or "-"
        later = [s.name for s in load_stages()[1:] if name in s.kinds]
        site = _first_line(type(SITES.get(name)).__doc__) if name in SITES else "-"
        rows.append(
            (
                name,
                f"{_first_line(type(kind).__doc__)} (own table: {own}; deposition site: "
                f"{site.rstrip('.')}; later stages: {', '.join(later) or 'none'})",
            )
        )
    return _table(("kind", "what it is"), rows)


def experiment_kinds_markdown() -> str:
    """The diagnosis's experiment kinds, what they observe and what the spec may set."""
    rows = []
    for name in EXPERIMENT_KINDS.in_order():
        kind = EXPERIMENT_KINDS.get(name)
        base = f"`{kind.default_scenario}`" if kind.default_scenario else "each condition's"
        tilt = "yes" if kind.release_tilt else "no"
        rows.append(
            (
                name,
                f"{kind.doc} (base scenario: {base}; `diagnosis.held_out`: "
                f"{', '.join(kind.held_out)}; release tilt: {tilt})",
            )
        )
    return _table(("kind", "what it observes"), rows)


# The layers, lowest first (``tests/test_architecture.py`` checks that no import runs up
# them), each with what it holds besides its registries.
LAYERS = (
    ("core", "data model (chip shape, stack, contacts, arrangement, overlap rules), scenario"),
    ("export", "CSV, VTK, figure drawing"),
    ("packing", "deposition, drops, conveyor, effects (PyBullet)"),
    ("geometry", "descriptors (manifold3d), ensembles"),
    (
        "meshing",
        "voxel, conformal, image and contact meshes, contact resolution; solve stage (CalculiX)",
    ),
    ("diagnosis", "experiment specs, drop and stack diagnoses, the report"),
    ("pipeline", "command line, run directory, stage cache, sweeps, validation"),
    ("chipstack", "the Python API: scenarios, runs and their results as arrays and tables"),
)


def _registries() -> dict[str, list]:
    """Every registry of the project, by the layer that defines it (found by importing
    every module of each layer: a registry is first met in its own layer, since only
    higher layers import it)."""
    found: dict[int, tuple[str, Registry]] = {}
    for layer, _ in LAYERS:
        name = layer if layer == "chipstack" else f"chipstack.{layer}"
        package = importlib.import_module(name)
        for info in pkgutil.walk_packages(package.__path__, name + "."):
            if info.name.endswith("__main__"):
                continue
            module = importlib.import_module(info.name)
            for item in vars(module).values():
                if isinstance(item, Registry) and id(item) not in found:
                    found[id(item)] = (layer, item)
    by_layer: dict[str, list] = {layer: [] for layer, _ in LAYERS}
    for layer, registry in found.values():
        by_layer[layer].append(registry)
    return by_layer


def layers_markdown() -> str:
    """The layers, lowest at the bottom, with the registries each defines: what the
    registry holds, its entry-point group and its built-in names."""
    by_layer = _registries()
    lines = ["```text"]
    for k, (layer, what) in enumerate(reversed(LAYERS)):
        if k:
            lines.append("   ^ imports only the layers below")
        lines.append(f"{layer + '/':<11}{what}")
        for registry in sorted(by_layer[layer], key=lambda r: r.kind):
            names = ", ".join(registry.in_order())
            lines.append(f"{'':<11}  [{registry.kind}] {registry.entry_points}: {names}")
    lines.append("```")
    return "\n".join(lines)


def sites_markdown() -> str:
    rows = [(n, _first_line(type(SITES.get(n)).__doc__)) for n in SITES.in_order()]
    return _table(("deposition site", "what holds the chips"), rows)


def quantity_measures_markdown() -> str:
    rows = [
        (n, _first_line(QUANTITY_MEASURES.get(n).__doc__)) for n in QUANTITY_MEASURES.in_order()
    ]
    return _table(
        ("quantity measure", "what a deposition of that scenario kind is reduced to"), rows
    )


def presets_markdown() -> str:
    rows = [(n, PRESETS.get(n).description) for n in PRESETS.in_order()]
    return _table(("preset", "what it is"), rows)


GENERATED: dict[str, Callable[[], str]] = {
    "layers": layers_markdown,
    "scenario_keys": key_table_markdown,
    "scenario_kinds": scenario_kinds_markdown,
    "stages": stages_markdown,
    "shapes": shapes_markdown,
    "descriptors": descriptors_markdown,
    "mesh_formats": mesh_formats_markdown,
    "stack_writers": stack_writers_markdown,
    "figures": figures_markdown,
    "mesh_kinds": mesh_kinds_markdown,
    "solve_models": solve_models_markdown,
    "effects": effects_markdown,
    "presets": presets_markdown,
    "sites": sites_markdown,
    "quantity_measures": quantity_measures_markdown,
    "experiment_kinds": experiment_kinds_markdown,
}


def _blocks(text: str) -> list[re.Match]:
    return list(_BLOCK.finditer(text))


def stale_blocks(folder: Path = DOCS) -> list[str]:
    """``page: block`` for every generated block that differs from the code's."""
    stale = []
    for page in sorted(folder.glob("*.md")):
        for match in _blocks(page.read_text()):
            if match["body"] != GENERATED[match["name"]]():
                stale.append(f"{page.name}: {match['name']}")
    return stale


def refresh(folder: Path = DOCS) -> list[str]:
    """Rewrite every generated block from the code; returns the pages changed."""
    changed = []
    for page in sorted(folder.glob("*.md")):
        text = page.read_text()
        new = _BLOCK.sub(lambda m: m[1] + GENERATED[m["name"]]() + m[4], text)
        if new != text:
            page.write_text(new)
            changed.append(page.name)
    return changed


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    for name in refresh():
        logging.getLogger(__name__).info("refreshed docs/%s", name)
