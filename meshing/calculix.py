"""Running CalculiX (``ccx``) on a deck and reading its results back.

The ``.dat`` file holds what ``*NODE PRINT`` asked for (the platens' force and
displacement at every increment); the ``.frd`` file holds the fields, turned into VTU
for ParaView by ``ccx2paraview`` (CalculiX's own maintained converter).
"""

from __future__ import annotations

import logging
import os
import re
import shutil
import subprocess
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from chipstack.core.errors import ChipstackError, InputError

__all__ = [
    "SolverError",
    "ccx_path",
    "run_ccx",
    "read_node_prints",
    "frd_to_vtu",
]

log = logging.getLogger(__name__)

_PRINT_HEADER = re.compile(
    r"^\s*(forces|displacements) \((?:fx,fy,fz|vx,vy,vz)\) for set (\S+) and time\s+(\S+)"
)
_INCREMENT = re.compile(r"^\s*increment\s+(\d+)\s+attempt")
_STEP_TIME = re.compile(r"actual step time=\s*(\S+)")


class SolverError(ChipstackError, RuntimeError):
    """The solver stopped with an error; the message is its own."""


def ccx_path() -> str:
    """The ``ccx`` executable, or InputError saying how to get it."""
    found = shutil.which("ccx")
    if found is None:
        raise InputError(
            "solve: CalculiX (ccx) is not on the PATH; install it (Debian: apt-get install "
            "calculix-ccx) or stop at --to mesh"
        )
    return found


@dataclass(frozen=True)
class SolverRun:
    """A finished solver run: its folder, job name, wall time and log."""

    folder: Path
    job: str
    wall_time_s: float
    log_path: Path


def run_ccx(
    folder: Path,
    job: str,
    threads: int = 0,
    time_limit_s: float = 7200.0,
    progress: Callable[[float], None] | None = None,
) -> SolverRun:
    """Run ``ccx -i job`` in ``folder``; ``progress(step time 0..1)`` as it goes.

    Raises SolverError with CalculiX's own message when it stops with an error, does not
    reach the end of the step, or runs out of ``time_limit_s``.
    """
    executable = ccx_path()
    env = dict(os.environ)
    cores = threads or os.cpu_count() or 1
    env.update(OMP_NUM_THREADS=str(cores), CCX_NPROC_EQUATION_SOLVER=str(cores))
    log_path = folder / f"{job}.log"
    start = time.perf_counter()
    with open(log_path, "w") as log_file:
        process = subprocess.Popen(
            [executable, "-i", job],
            cwd=folder,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            env=env,
        )
        try:
            _follow(process, log_file, start, time_limit_s, progress)
        finally:
            if process.poll() is None:
                process.kill()
                process.wait()
    wall = time.perf_counter() - start
    _check_finished(log_path, process.returncode)
    return SolverRun(folder, job, wall, log_path)


def _follow(process, log_file, start: float, limit: float, progress) -> None:
    """Copy the solver's output to its log, report the step time, enforce the limit."""
    assert process.stdout is not None  # opened with stdout=PIPE above
    for line in process.stdout:
        log_file.write(line)
        match = _STEP_TIME.search(line)
        if match and progress is not None:
            progress(float(match.group(1)))
        if time.perf_counter() - start > limit:
            process.kill()
            raise SolverError(f"solve: CalculiX ran out of solve.time_limit_s ({limit:g} s)")
    process.wait()


def _check_finished(log_path: Path, returncode: int) -> None:
    text = log_path.read_text(errors="replace")
    errors = [line.strip() for line in text.splitlines() if "*ERROR" in line]
    if errors:
        raise SolverError(f"solve: CalculiX stopped: {errors[0]}")
    if returncode != 0:
        raise SolverError(f"solve: CalculiX exited with status {returncode}")
    if "Job finished" not in text:
        raise SolverError("solve: CalculiX did not finish the step (see its log)")


def read_node_prints(dat: Path) -> dict[str, dict[str, np.ndarray]]:
    """``*NODE PRINT`` blocks of a ``.dat`` file: {set: {"time": (k,), "forces": (k, 3),
    "displacements": (k, 3)}}, summed over the set's nodes at each time."""
    out: dict[str, dict[str, list]] = {}
    current = None
    for line in Path(dat).read_text(errors="replace").splitlines():
        header = _PRINT_HEADER.match(line)
        if header:
            kind, name, at = header.group(1), header.group(2).upper(), float(header.group(3))
            entry = out.setdefault(name, {})
            times = entry.setdefault(f"{kind}_time", [])
            if not times or times[-1] != at:
                times.append(at)
                entry.setdefault(kind, []).append(np.zeros(3))
            current = entry[kind]
            continue
        parts = line.split()
        if current is not None and len(parts) == 4:
            try:
                current[-1] = current[-1] + np.array([float(v) for v in parts[1:]])
            except ValueError:
                current = None
        elif not parts:
            continue
        else:
            current = None
    result = {}
    for name, entry in out.items():
        result[name] = {
            "time": np.array(entry.get("forces_time", entry.get("displacements_time", []))),
            **{k: np.array(entry[k]) for k in ("forces", "displacements") if k in entry},
        }
    return result


def frd_to_vtu(frd: Path) -> list[Path]:
    """Convert a ``.frd`` result file into one VTU per increment (and a ``.pvd``) beside
    it, with ccx2paraview; returns the files written."""
    from ccx2paraview import Converter  # imports vtk: only when converting

    before = set(frd.parent.iterdir())
    # ccx2paraview logs every block at INFO to the root logger; keep the run's log clean.
    converter_log = logging.getLogger()
    level = converter_log.level
    converter_log.setLevel(max(level, logging.WARNING))
    try:
        Converter(str(frd), ["vtu"]).run()
    finally:
        converter_log.setLevel(level)
    return sorted(set(frd.parent.iterdir()) - before)
