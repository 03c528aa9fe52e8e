"""The clients, called from the project's environment: the crop both solvers press, the
CalculiX deck of that press, and the scripts run in DOLFINx's and ParaView's own
interpreters (``dolfinx_press.py``, ``dolfinx_open.py``, ``paraview_open.py`` beside
this file), each answering in JSON.

Used by ``tests/test_clients.py`` and ``benchmarks/bench_clients.py``.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
DOLFINX_PYTHON = ROOT / ".venv-dolfinx" / "bin" / "python"

# The press both solvers make: one isotropic material on every region (the pore space's
# PA6, MPa), the top moved down by 1 % of the height with x and y held, the bottom fixed,
# the sides free.
YOUNG_MPA, POISSON = 2000.0, 0.35
PRESS_FRACTION = 0.01

# The reference crop: the paper's stack (paper-volume: 270 chips, seed 0) cropped to
# 30 x 30 mm at 1 mm voxels with its pore space, sides not periodic (free), every format.
CROP_SCENARIO = "paper-volume"
CROP_OVERRIDES = {
    "mesh.region_mm": [-15.0, 15.0, -15.0, 15.0],
    "mesh.periodic": False,
    "mesh.formats": ["msh", "vtu", "inp", "xdmf"],
}
# A small stack of the paper's chips, chips only (no pore space): 24 chips on 80 mm.
SMALL_SCENARIO = "paper-squares"
SMALL_OVERRIDES = {
    "deposition.chips": 24,
    "deposition.batch_size": 12,
    "deposition.target_size_mm": 80.0,
}


def build(scenario: str, overrides: dict, out: Path, descriptors: list[str]) -> Path:
    """``chipstack.run(scenario, to="mesh")`` with ``overrides`` into ``out``; the run
    directory."""
    import chipstack

    run = chipstack.run(
        scenario, to="mesh", out=out, overrides=overrides, figures=False, descriptors=descriptors
    )
    return run.path


def isotropic_deck(mesh_inp: Path, deck: Path, press_mm: float, solver: str) -> Path:
    """The mesh's deck as written, every ``*ELASTIC`` replaced by the isotropic
    ``YOUNG_MPA``, ``POISSON`` (the element type, sets, sections and orientations kept),
    followed by the press: ``BOTTOM`` fixed, ``TOP`` moved by ``-press_mm`` in z and held
    in x and y, the total reaction on each printed (``*NODE PRINT, TOTALS=ONLY``).
    ``solver``: CalculiX's ``*STATIC`` solver (``SPOOLES`` or ``ITERATIVE CHOLESKY``)."""
    lines, skipping = [], False
    for line in Path(mesh_inp).read_text().splitlines():
        if line.startswith("*"):
            skipping = False
            if line.upper().startswith("*ELASTIC"):
                lines += ["*ELASTIC", f"{YOUNG_MPA}, {POISSON}"]
                skipping = True
                continue
        elif skipping:
            continue
        lines.append(line)
    Path(deck).write_text("\n".join([*lines, *press_step(press_mm, solver)]) + "\n")
    return Path(deck)


def press_step(press_mm: float, solver: str) -> list[str]:
    """The press as a CalculiX step (see :func:`isotropic_deck`)."""
    return [
        "*STEP",
        f"*STATIC, SOLVER={solver}",
        "*BOUNDARY",
        "BOTTOM, 1, 3, 0.",
        "TOP, 1, 2, 0.",
        f"TOP, 3, 3, {-press_mm:.9g}",
        "*NODE PRINT, NSET=TOP, TOTALS=ONLY",
        "RF",
        "*NODE PRINT, NSET=BOTTOM, TOTALS=ONLY",
        "RF",
        "*END STEP",
    ]


_TOTAL = re.compile(r"total force \(fx,fy,fz\) for set (\S+) and time")


def calculix(deck: Path) -> dict:
    """Run ``ccx`` on ``deck`` (one thread) in its folder: the total force on each
    printed set (N, (fx, fy, fz)), the wall time (s) and CalculiX's log. Raises
    RuntimeError when it does not finish."""
    deck = Path(deck)
    env = dict(os.environ, OMP_NUM_THREADS="1", CCX_NPROC_EQUATION_SOLVER="1")
    start = time.perf_counter()
    done = subprocess.run(
        [shutil.which("ccx") or "ccx", "-i", deck.stem],
        cwd=deck.parent,
        capture_output=True,
        text=True,
        env=env,
        timeout=600,
    )
    wall = time.perf_counter() - start
    if done.returncode != 0 or "Job finished" not in done.stdout:
        raise RuntimeError(f"ccx failed ({done.returncode}): {done.stdout[-2000:]}")
    forces, lines = {}, deck.with_suffix(".dat").read_text().splitlines()
    for k, line in enumerate(lines):
        if match := _TOTAL.search(line):
            values = next(v for v in lines[k + 1 :] if v.strip())
            forces[match.group(1)] = [float(v) for v in values.split()]
    return {"forces": forces, "wall_s": wall, "log": done.stdout}


def client(command: list[str], timeout_s: float = 600) -> tuple[dict, float]:
    """Run a client script; its JSON answer (stdout) and the wall time (s). Raises
    RuntimeError with the client's stderr when it fails."""
    start = time.perf_counter()
    done = subprocess.run(command, capture_output=True, text=True, timeout=timeout_s)
    wall = time.perf_counter() - start
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(command[:2])} failed: {done.stderr[-3000:]}")
    return json.loads(done.stdout), wall


def dolfinx(script: str, *args: str) -> tuple[dict, float]:
    """``.venv-dolfinx/bin/python tests/clients/SCRIPT ARGS``: its answer and wall time."""
    return client([os.fspath(DOLFINX_PYTHON), os.fspath(HERE / script), *map(str, args)])


def paraview(*files: Path) -> tuple[dict, float]:
    """``xvfb-run -a pvpython tests/clients/paraview_open.py FILES``: what ParaView read,
    by path, and the wall time."""
    command = ["xvfb-run", "-a", "pvpython", os.fspath(HERE / "paraview_open.py")]
    return client([*command, *map(os.fspath, files)])
