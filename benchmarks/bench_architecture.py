"""Counts a reviewer can redo for the architecture (issue 57): which registries list their
names without a numerical library, which numerical libraries reading and checking the
reference scenario imports, how many imports sit inside functions (outside the tests and
benchmarks), and how many kinds declare keys of their own. Each figure is printed and,
with ``--record``, recorded under ``benchmarks/results/architecture/``.

Usage: ``python benchmarks/bench_architecture.py [--record]``.
"""

from __future__ import annotations

import argparse
import ast
import subprocess
import sys
from pathlib import Path

from chipstack.core.registry import Registry
from chipstack.pipeline.measured import record
from chipstack.pipeline.reference import _registries

ROOT = Path(__file__).resolve().parent.parent
HEAVY = ("numpy", "scipy", "trimesh", "pybullet", "gmsh", "sklearn", "meshio", "pyvista")
HEAVY += ("manifold3d", "matplotlib", "dask", "pandas", "pygalmesh")
COMMAND = "python benchmarks/bench_architecture.py --record"


def heavy_after(code: str) -> list[str]:
    """The numerical libraries a fresh interpreter holds after running ``code``."""
    probe = f"import sys\n{code}\nprint(*sorted({{m.split('.')[0] for m in sys.modules}}))"
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, cwd=ROOT)
    if out.returncode != 0:
        raise RuntimeError(out.stderr)
    return [m for m in HEAVY if m in out.stdout.split()]


def registry_homes() -> list[tuple[str, str, str]]:
    """(kind, module, attribute) of every registry of the project, in the module that
    makes it (``NAME = Registry(...)``), not one that imports it."""
    import inspect

    registries = [r for layer in _registries().values() for r in layer]
    homes: dict[int, tuple[str, str]] = {}
    for name, module in sorted(sys.modules.items()):
        if not name.startswith("chipstack.") or module is None:
            continue
        for attribute, value in vars(module).items():
            if isinstance(value, Registry) and id(value) not in homes:
                source = inspect.getsource(module)
                if f"{attribute}: Registry" in source or f"{attribute} = Registry(" in source:
                    homes[id(value)] = (name, attribute)
    return [(r.kind, *homes[id(r)]) for r in registries]


def in_function_imports() -> int:
    """Import statements inside functions, in the project's code (not tests, benchmarks)."""
    count = 0
    for path in ROOT.rglob("*.py"):
        parts = path.relative_to(ROOT).parts
        if parts[0] in ("tests", "benchmarks", ".venv", "docs", "runs"):
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                # Only the function's own body (nested functions are walked on their own).
                stack = list(node.body)
                while stack:
                    child = stack.pop()
                    if isinstance(child, ast.Import | ast.ImportFrom):
                        count += 1
                    elif not isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef):
                        stack.extend(ast.iter_child_nodes(child))
    return count


def kinds_with_keys() -> tuple[int, int]:
    """(kinds a table chooses, those of them declaring keys of their own)."""
    import dataclasses

    from chipstack.core.stages import load_stages

    total = own = 0
    for stage in load_stages():
        for table, choice in stage.kind_choices.items():
            for name in choice.names():
                total += 1
                own += bool(dataclasses.fields(choice.parameters_of(name, table)))
    return total, own


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--record", action="store_true", help="record the figures")
    args = parser.parse_args()
    homes = registry_homes()
    light = []
    for kind, module, attribute in homes:
        heavy = heavy_after(f"from {module} import {attribute}\n{attribute}.names()")
        print(f"{kind:18s} {module}:{attribute}: {', '.join(heavy) or 'no numerical library'}")
        light.append(not heavy)
    scenario = heavy_after(
        "import chipstack.pipeline.run\n"
        "from chipstack.pipeline.scenario_files import load_scenario\n"
        "load_scenario('paper-squares')"
    )
    imports = in_function_imports()
    total, own = kinds_with_keys()
    figures = [
        (
            "registries that list their names without a numerical library",
            sum(light),
            "",
            f"of {len(light)} registries",
        ),
        (
            "numerical libraries imported to read and check the reference scenario",
            len(scenario),
            "",
            ", ".join(scenario) or "none",
        ),
        ("imports inside functions, outside tests and benchmarks", imports, "", ""),
        (
            "kinds chosen by a table that declare keys of their own",
            own,
            "",
            f"of {total} (shapes; mesh kinds with `both`; solve models with `none`: "
            "`volume` and `none` read the press's keys only)",
        ),
    ]
    for name, value, unit, note in figures:
        print(f"{name}: {value} {note}")
        if args.record:
            record("architecture", name, value, unit, command=COMMAND, note=note)


if __name__ == "__main__":
    main()
