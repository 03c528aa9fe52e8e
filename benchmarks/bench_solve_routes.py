"""The bonded press of one cropped volume by two mesh routes: does the tetrahedral image
mesh give the voxel volume's force?

The reference stack (seed 0) cropped to its middle 50 x 50 mm with its pore space
(``paper-volume``, sides free instead of periodic, since the image mesh's sides are not
node-for-node twins), pressed by 1 % of its height between frictionless platens by
CalculiX: the voxel mesh at 1 and 0.5 mm and the image mesh (CGAL Mesh_3 on a 0.25 mm
labelled image, slivers removed). Each route runs ``pipeline run SCENARIO --to solve``
as a user would; a run directory already holding a finished solve is read again instead
(``--out`` keeps them, so the study resumes).

Target (issue 56, point 3): the image mesh's force within 5 % of the voxel volume's.

Usage: ``python benchmarks/bench_solve_routes.py [--out DIR] [--record]``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
BASE = ROOT / "pipeline" / "scenarios" / "paper-volume.toml"
ROUTES = {  # name -> (mesh.kind, mesh.voxel_mm)
    "voxel1": ("voxel", 1.0),
    "voxel05": ("voxel", 0.5),
    "image": ("image", 1.0),  # the image route's own voxel: an eighth of the thickness
}
TARGET = 0.05


def scenario_text(name: str, kind: str, voxel_mm: float) -> str:
    text = BASE.read_text()
    text = text.replace('name = "paper-volume"', f'name = "volume-{name}"')
    text = text.replace("periodic = true", "periodic = false")
    text = text.replace('kind = "voxel"', f'kind = "{kind}"')
    return text.replace("voxel_mm = 1.0", f"voxel_mm = {voxel_mm:g}")


def solved(folder: Path) -> dict | None:
    path = folder / "manifest.json"
    if not path.exists():
        return None
    manifest = json.loads(path.read_text())
    return manifest if "solve" in manifest.get("stages_completed", []) else None


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=None, help="keep the runs here")
    parser.add_argument("--record", action="store_true")
    args = parser.parse_args()
    out = args.out or Path(tempfile.mkdtemp(prefix="bench-solve-routes-"))
    out.mkdir(parents=True, exist_ok=True)
    pipeline = Path(sys.executable).parent / "pipeline"
    rows = {}
    for name, (kind, voxel) in ROUTES.items():
        run = out / f"run-{name}"
        manifest = solved(run)
        if manifest is None:
            scenario = out / f"{name}.toml"
            scenario.write_text(scenario_text(name, kind, voxel))
            command = [str(pipeline), "run", str(scenario), "--to", "solve", "--out", str(run)]
            subprocess.run([*command, "--overwrite", "--quiet"], check=True)
            manifest = solved(run)
        mesh = manifest["mesh"][kind]
        rows[name] = dict(
            elements=mesh["elements"],
            quality_min=mesh["quality_min"],
            chip_volume_error_max=mesh["chip_volume_error_max"],
            force_n=manifest["solve"]["force_n"],
            press_mm=manifest["solve"]["press_mm"],
            solver_s=manifest["solve"]["solver_wall_time_s"],
        )
        r = rows[name]
        print(
            f"{name}: {r['elements']:,} elements, quality min {r['quality_min']:.3f}, chips within "
            f"{100 * r['chip_volume_error_max']:.2f} %; press {r['press_mm']:.4f} mm, force "
            f"{r['force_n']:,.1f} N, CalculiX {r['solver_s']:.1f} s",
            flush=True,
        )
    gaps = {
        ref: rows["image"]["force_n"] / rows[ref]["force_n"] - 1 for ref in ("voxel1", "voxel05")
    }
    for ref, gap in gaps.items():
        verdict = "within" if abs(gap) <= TARGET else "NOT within"
        print(f"image against {ref}: {100 * gap:+.2f} % ({verdict} {100 * TARGET:.0f} %)")
    if args.record:
        from chipstack.pipeline.measured import record

        command = "python benchmarks/bench_solve_routes.py --record"
        for ref, gap in gaps.items():
            record(
                "meshing",
                f"image_vs_{ref}_press_force_gap",
                round(100 * gap, 2),
                "%",
                target=f"{-100 * TARGET:g} to {100 * TARGET:g}",
                command=command,
                note=(
                    f"paper-volume crop 50 x 50 mm, sides free, 1 % press: image mesh "
                    f"{rows['image']['elements']:,} tetrahedra {rows['image']['force_n']:,.0f} N "
                    f"against voxel {rows[ref]['elements']:,} hexahedra "
                    f"{rows[ref]['force_n']:,.0f} N"
                ),
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
