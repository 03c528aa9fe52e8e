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

from typing import TYPE_CHECKING

from chipstack.core.lazy import lazy_package

if TYPE_CHECKING:
    from chipstack.api import Run, load_scenario, open_run, run, scenarios

__all__ = ["Run", "load_scenario", "open_run", "run", "scenarios"]

# The API is imported on first use: importing any package of the project
# (``chipstack.core``, ``chipstack.packing``...) runs this file first, and must not bring
# the command line and the stages with it.
lazy_package(__name__, {name: "chipstack.api" for name in __all__})
