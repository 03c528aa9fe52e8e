"""DOLFINx and CalculiX press the reference crop alike: the platen forces and the times,
recorded in ``benchmarks/results/clients/measured.jsonl``.

The crop and the press are ``tests/test_clients.py``'s (``tests/clients/solvers.py``):
the paper's stack (``paper-volume``, seed 0) cropped to 30 x 30 mm at 1 mm voxels with
its pore space, sides free, one isotropic material (E 2000 MPa, nu 0.35), the bottom
fixed, the top moved down by 1 % of the height. CalculiX solves it twice, with the
iterative Cholesky solver the tests use and with SPOOLES (direct); each on one thread.

    python benchmarks/bench_clients.py            # needs make dolfinx and ccx
    python benchmarks/bench_clients.py --venv     # also times `make -B dolfinx`
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from clients import solvers  # noqa: E402

from chipstack.pipeline.measured import record  # noqa: E402

COMMAND = "python benchmarks/bench_clients.py"


def press(folder: Path) -> None:
    """Build the crop, press it in both solvers, record the figures."""
    start = time.perf_counter()
    run = solvers.build(solvers.CROP_SCENARIO, solvers.CROP_OVERRIDES, folder / "crop", ["stack"])
    build_s = time.perf_counter() - start
    stem = run / "mesh" / "stack_voxel"
    checks = json.loads((stem.parent / "stack_voxel_checks.json").read_text())
    low, high = checks["bounds_mm"]
    press_mm = solvers.PRESS_FRACTION * (high[2] - low[2])
    found, dolfinx_wall = solvers.dolfinx(
        "dolfinx_press.py", f"{stem}.msh", solvers.YOUNG_MPA, solvers.POISSON, press_mm
    )
    forces, walls = {}, {}
    for solver in ("ITERATIVE CHOLESKY", "SPOOLES"):
        deck = solvers.isotropic_deck(
            f"{stem}.inp", folder / f"press_{solver.split()[0].lower()}.inp", press_mm, solver
        )
        done = solvers.calculix(deck)
        forces[solver], walls[solver] = -done["forces"]["TOP"][2], done["wall_s"]
    dolfinx_force = -found["force_n"]
    size = f"{checks['elements']:,} hexahedra, {found['dofs']:,} dofs, press {press_mm:.3f} mm"
    for solver, force in forces.items():
        apart = abs(dolfinx_force - force) / force * 100
        print(f"{solver}: CalculiX {force:.2f} N, DOLFINx {dolfinx_force:.2f} N, {apart:.5f} %")
        record(
            "clients",
            f"crop 30 x 30 mm: DOLFINx against CalculiX ({solver}) platen force",
            round(apart, 5),
            "% apart",
            target="<= 0.5",
            command=COMMAND,
            note=f"DOLFINx {dolfinx_force:.2f} N, CalculiX {force:.2f} N; {size}",
            headline=solver == "SPOOLES",
        )
        record(
            "clients",
            f"crop 30 x 30 mm: CalculiX ({solver}) press, one thread",
            round(walls[solver], 2),
            "s",
            command=COMMAND,
            note=f"ccx wall time; {size}",
        )
    record(
        "clients",
        "crop 30 x 30 mm: DOLFINx platen force",
        round(dolfinx_force, 2),
        "N",
        command=COMMAND,
        note=f"{size}; E 2000 MPa, nu 0.35, bottom fixed, top pressed with x and y held",
    )
    record(
        "clients",
        "crop 30 x 30 mm: DOLFINx press, one process",
        round(dolfinx_wall, 2),
        "s",
        command=COMMAND,
        note=(
            f"the script's wall time: read {found['read_s']:.2f} s, assemble and solve "
            f"(MUMPS LU) {found['solve_s']:.2f} s, with interpreter start and JIT"
        ),
    )
    record(
        "clients",
        "crop 30 x 30 mm: building the crop (paper-volume, 270 chips)",
        round(build_s, 2),
        "s",
        command=COMMAND,
        note="chipstack.run to mesh, descriptors stack only, no figures",
    )


def venv() -> None:
    """Time ``make -B dolfinx`` (pip's cache as it is) and measure the environment."""
    start = time.perf_counter()
    subprocess.run(["make", "-B", "dolfinx"], cwd=ROOT, check=True)
    wall = time.perf_counter() - start
    used = subprocess.run(
        ["du", "-sm", ".venv-dolfinx"], cwd=ROOT, capture_output=True, text=True, check=True
    )
    megabytes = float(used.stdout.split()[0])
    print(f"make dolfinx: {wall:.1f} s, {megabytes:.0f} MB")
    record(
        "clients",
        "make dolfinx: build time",
        round(wall, 1),
        "s",
        target="<= 300",
        command="make -B dolfinx",
        note="pip's cache warm (the wheels downloaded before)",
    )
    record("clients", "make dolfinx: size of .venv-dolfinx", megabytes, "MB", command="du -sm")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--venv", action="store_true", help="also time make -B dolfinx")
    args = parser.parse_args()
    if args.venv:
        venv()
    with tempfile.TemporaryDirectory() as folder:
        press(Path(folder))


if __name__ == "__main__":
    main()
