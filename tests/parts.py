"""The optional parts some tests need, and one switch that makes them required.

A part is something pip does not install with the project: CalculiX (``ccx``), the
image route's CGAL build (``cgal``), off-screen rendering (``offscreen``), the DOLFINx
virtual environment built by ``make dolfinx`` (``dolfinx``) and ParaView's ``pvpython``
under ``xvfb-run`` (``paraview``). A test asks for one with ``@needs("ccx")`` (a mark) or
``require("ccx")`` (inside the test). Where the part is missing the test is skipped,
saying which part and how to get it; with ``CHIPSTACK_REQUIRE_PARTS=1`` (set by
``.ci/run``) it fails instead, so CI proves every part works. ``make test`` ends with the
list of parts that were missing (``tests/conftest.py``).
"""

from __future__ import annotations

import functools
import os
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

__all__ = ["PARTS", "needs", "require", "available", "why_missing", "REQUIRE_VARIABLE"]

REQUIRE_VARIABLE = "CHIPSTACK_REQUIRE_PARTS"
ROOT = Path(__file__).resolve().parents[1]
DOLFINX_PYTHON = ROOT / ".venv-dolfinx" / "bin" / "python"


def _ccx() -> str | None:
    if shutil.which("ccx") is None:
        return "CalculiX (ccx) is not on the PATH (Debian: apt-get install calculix-ccx)"
    return None


def _cgal() -> str | None:
    from chipstack.meshing.image import cgal_available

    if not cgal_available():
        return "pygalmesh (CGAL) is not installed (make image)"
    return None


def _offscreen() -> str | None:
    # A subprocess: a failing OpenGL context can take the interpreter down with it.
    script = (
        "import pyvista; p = pyvista.Plotter(off_screen=True, window_size=(32, 32)); "
        "p.add_mesh(pyvista.Sphere()); p.screenshot(); p.close()"
    )
    try:
        done = subprocess.run(
            [sys.executable, "-c", script],
            capture_output=True,
            text=True,
            timeout=120,
        )
    except subprocess.TimeoutExpired:
        return "off-screen rendering (pyvista, OpenGL) timed out"
    if done.returncode != 0:
        last = (done.stderr.strip().splitlines() or ["no message"])[-1]
        return f"off-screen rendering (pyvista, OpenGL) failed: {last}"
    return None


def _dolfinx() -> str | None:
    if not DOLFINX_PYTHON.exists():
        venv = DOLFINX_PYTHON.parent.parent.name
        return f"the DOLFINx environment {venv} is missing (make dolfinx)"
    done = subprocess.run(
        [os.fspath(DOLFINX_PYTHON), "-c", "import dolfinx_solver, dolfinx"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    if done.returncode != 0:
        last = (done.stderr.strip().splitlines() or ["no message"])[-1]
        return f"DOLFINx does not import in {DOLFINX_PYTHON.parent.parent.name}: {last}"
    return None


def _paraview() -> str | None:
    missing = [tool for tool in ("pvpython", "xvfb-run") if shutil.which(tool) is None]
    if missing:
        debian = "apt-get install paraview python3-paraview xvfb xauth"
        return f"{' and '.join(missing)} not on the PATH (Debian: {debian})"
    return None


PARTS: dict[str, Callable[[], str | None]] = {
    "ccx": _ccx,
    "cgal": _cgal,
    "offscreen": _offscreen,
    "dolfinx": _dolfinx,
    "paraview": _paraview,
}

# Which parts were asked for and missing in this process: reported at the end of the run.
MISSING: dict[str, str] = {}


@functools.cache
def why_missing(part: str) -> str | None:
    """None when ``part`` is here, else why not (one line)."""
    if part not in PARTS:
        raise KeyError(f"unknown part {part!r}; the parts are {', '.join(PARTS)}")
    return PARTS[part]()


def available(part: str) -> bool:
    return why_missing(part) is None


def required() -> bool:
    """Whether missing parts fail the tests that need them (``CHIPSTACK_REQUIRE_PARTS=1``)."""
    value = os.environ.get(REQUIRE_VARIABLE, "")
    if value not in ("", "0", "1"):
        raise ValueError(f"{REQUIRE_VARIABLE}: must be 0 or 1, got {value!r}")
    return value == "1"


def require(part: str) -> None:
    """Inside a test: skip (or, when parts are required, fail) unless ``part`` is here."""
    reason = why_missing(part)
    if reason is None:
        return
    MISSING[part] = reason
    if required():
        pytest.fail(f"{part} is required ({REQUIRE_VARIABLE}=1): {reason}", pytrace=False)
    pytest.skip(f"needs {part}: {reason}")


def needs(*names: str) -> pytest.MarkDecorator:
    """The mark of a test that needs the parts ``names``: checked when the test is set up
    (``tests/conftest.py``), so collecting the suite probes nothing."""
    for name in names:
        if name not in PARTS:
            raise KeyError(f"unknown part {name!r}; the parts are {', '.join(PARTS)}")
    return pytest.mark.needs(*names)
