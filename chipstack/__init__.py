"""chipstack from Python: deposit a stack of composite chips, describe it, mesh it, and
get the results back as the objects a notebook already uses (numpy arrays, pandas
DataFrames, ``meshio.Mesh``, pyvista datasets).

The functions here are the ones the command line ``pipeline run`` calls; a run written by
one is read by the other.

>>> import chipstack
>>> "paper-squares" in chipstack.scenarios()
True
>>> small = {"deposition.chips": 24, "deposition.batch_size": 12}
>>> scenario = chipstack.load_scenario("paper-squares", overrides=small)
>>> scenario.deposition.chips, scenario.seed
(24, 0)

See :func:`run` for a whole run, and ``docs/python.md`` for a tutorial.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

# The project's own top-level packages (their names are generic: a module of the user's
# called ``core`` or ``pipeline`` found first on sys.path would shadow them).
_OWN = ("core", "export", "packing", "geometry", "meshing", "diagnosis", "pipeline")


def _check_own_packages() -> None:
    """Refuse, at import, a module of someone else's that shadows one of ours, naming it
    (instead of an AttributeError deep inside a run)."""
    home = Path(__file__).resolve().parent.parent
    for name in _OWN:
        spec = importlib.util.find_spec(name)
        origin = spec.origin if spec is not None else None
        if origin is None or Path(origin).resolve().parent.parent != home:
            found = origin or "nothing importable"
            raise ImportError(
                f"chipstack: the module {name!r} found first on sys.path is {found}, not "
                f"chipstack's own ({home / name}); rename your module {name!r} or take its "
                "folder off sys.path"
            )


_check_own_packages()

from chipstack.api import Run, load_scenario, open_run, run, scenarios  # noqa: E402

__all__ = ["Run", "load_scenario", "open_run", "run", "scenarios"]
