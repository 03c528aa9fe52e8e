"""The whole stack with its pore space as a consolidation model (issue 56), checked from
outside the project.

Each case is meshed by the command a user runs, ``pipeline run SCENARIO --to mesh
--seed N``, on the built-in scenario with the mesh settings below (the exact route with
the pore space; see docs/meshing.md, "The whole stack for a consolidation code"), in a
process of its own (its peak memory is the run's). The written ``.msh`` is then read
back with meshio and checked by code that shares nothing with the project's own check:
every element's signed inverse condition number (SICN) and its 1st percentile, every
chip present as one face-connected region of its own, the pore space a region, every
chip's volume against its exact solid (the packed shape's), and the interfaces (faces
two chips share, named ``interface_A_B``) against the interface table written beside
the mesh. The first case is run twice: the same seed must give the same file.

With ``--solve`` each valid case is then pressed in CalculiX by the solve stage's volume
model (``pipeline run SCENARIO --to solve``: the mesh reused, the pore space bonded and
softer than the chips, whole-face platens), and so is the voxel volume of the same stack
(1 mm voxels, pore space filled): their effective moduli (platen force over the box's
area and strain, each over its own box) must agree within 5 %.

    .venv/bin/python benchmarks/bench_whole_stack.py                         # every case
    .venv/bin/python benchmarks/bench_whole_stack.py --case paper-squares --seeds 0 1
    .venv/bin/python benchmarks/bench_whole_stack.py --no-record
    .venv/bin/python benchmarks/bench_whole_stack.py --case paper-squares --seeds 0 --solve

The figures are recorded per case (``pipeline.measured.record``, area ``meshing``):
time (target <= 180 s for the reference stack), peak memory (<= 4 GB), and in the note
the elements, the SICN, chips, volumes and interfaces.
"""

from __future__ import annotations

import argparse
import csv
import hashlib
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

# The mesh settings of a consolidation model of the whole stack.
MESH = {"mesh.kind": "conformal", "mesh.pore_space": "box", "mesh.formats": ["msh", "vtu", "inp"]}
# Scenario -> seeds meshed by default.
CASES = {
    "paper-squares": list(range(10)),
    "mixed-shapes": [0],
    "paper-rectangles": [0],
    "conveyor-line": [0],
}
# The voxel volume the whole stack's press is compared with.
VOXEL = {
    "mesh.kind": "voxel",
    "mesh.voxel_mm": 1.0,
    "mesh.pore_space": "box",
    "mesh.formats": ["inp"],
}
MODULUS_TOLERANCE = 0.05
MIN_SICN = 0.1
VOLUME_TOLERANCE = 0.02
# Runs the command in a child and reports its own peak memory (the run's, not ours).
RUNNER = """
import resource, subprocess, sys, time
start = time.perf_counter()
done = subprocess.run(sys.argv[1:], capture_output=True, text=True)
print(done.returncode, time.perf_counter() - start,
      resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024)
sys.stderr.write(done.stderr[-2000:])
"""


def sicn(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Signed inverse condition number of tetrahedra, written out here (not imported):
    the Jacobian mapped onto the regular tetrahedron's, 3 / (|S| |S^-1|), signed by det."""
    regular = np.array([[1, 0.5, 0.5], [0, 3**0.5 / 2, 3**0.5 / 6], [0, 0, (2 / 3) ** 0.5]])
    p = points[tets]
    jac = np.stack([p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]], axis=2)
    shape = jac @ np.linalg.inv(regular)
    det = np.linalg.det(shape)
    out = np.zeros(len(tets))
    ok = np.abs(det) > 1e-300
    inverse = np.linalg.inv(shape[ok])
    norm = np.linalg.norm(shape[ok], axis=(1, 2)) * np.linalg.norm(inverse, axis=(1, 2))
    out[ok] = np.sign(det[ok]) * 3.0 / norm
    return out


def _regions_connected(tets: np.ndarray, region: np.ndarray) -> dict[int, int]:
    """Face-connected pieces of every region: {region: pieces}."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    faces = np.sort(tets[:, [[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]]].reshape(-1, 3), axis=1)
    owner = np.repeat(np.arange(len(tets)), 4)
    order = np.lexsort(faces.T[::-1])
    faces, owner = faces[order], owner[order]
    same = np.all(faces[1:] == faces[:-1], axis=1)
    a, b = owner[:-1][same], owner[1:][same]
    inside = region[a] == region[b]
    graph = coo_matrix((np.ones(inside.sum()), (a[inside], b[inside])), shape=(len(tets),) * 2)
    _, piece = connected_components(graph, directed=False)
    return {int(r): len(np.unique(piece[region == r])) for r in np.unique(region)}


def audit_msh(path: Path, exact_volumes: np.ndarray, interface_table: Path | None = None) -> dict:
    """The written .msh checked by meshio and numpy alone: quality, regions, volumes and
    interfaces (see the module docstring). ``exact_volumes``: mm3 per chip."""
    import meshio

    mesh = meshio.read(path)
    names = {int(tag): name for name, (tag, _dim) in mesh.field_data.items()}
    tets, tags = [], []
    for block, physical in zip(mesh.cells, mesh.cell_data["gmsh:physical"], strict=True):
        if block.type == "tetra":
            tets.append(block.data)
            tags.append(physical)
    tets, tags = np.concatenate(tets), np.concatenate(tags)
    region = np.array([names[t] for t in np.unique(tags)])[np.searchsorted(np.unique(tags), tags)]
    # chip_<id>: the region id, chip index + 1 (docs/run-directory.md)
    chip = np.array([int(r[5:]) - 1 if r.startswith("chip_") else -1 for r in region])
    quality = sicn(mesh.points, tets)
    p = mesh.points[tets]
    volume = (
        np.abs(
            np.einsum("ij,ij->i", p[:, 1] - p[:, 0], np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]))
        )
        / 6
    )
    present = np.unique(chip[chip >= 0])
    meshed = np.bincount(chip[chip >= 0], weights=volume[chip >= 0], minlength=len(exact_volumes))
    error = np.abs(meshed[present] - exact_volumes[present]) / exact_volumes[present]
    pieces = _regions_connected(tets, chip)
    interfaces = sorted(n for n in mesh.field_data if n.startswith("interface_"))
    listed = []
    if interface_table is not None and interface_table.exists():
        with open(interface_table) as f:
            # Rows with tag -1 are contacts the mesh shares no face for (points, lines).
            rows = [r for r in csv.DictReader(f) if int(r["tag"]) > 0]
            listed = sorted(f"interface_{r['region_a']}_{r['region_b']}" for r in rows)
    return dict(
        elements=int(len(tets)),
        pore_elements=int((chip < 0).sum()),
        sicn_min=float(quality.min()),
        sicn_p1=float(np.percentile(quality, 1)),
        below_min=int((quality < MIN_SICN).sum()),
        chips=int(len(exact_volumes)),
        chips_present=int(len(present)),
        chips_in_pieces=int(sum(1 for r, k in pieces.items() if r >= 0 and k > 1)),
        pore_space=bool((chip < 0).any()),
        volume_error_max=float(error.max()),
        interfaces=len(interfaces),
        interfaces_match_table=interfaces == listed,
        valid=bool(
            quality.min() >= MIN_SICN
            and len(present) == len(exact_volumes)
            and error.max() <= VOLUME_TOLERANCE
            and all(k == 1 for r, k in pieces.items() if r >= 0)
            and (chip < 0).any()
            and interfaces == listed
        ),
    )


def _exact_volumes(run: Path) -> np.ndarray:
    """Every chip's exact volume (mm3), from the packed stack the mesh stage read."""
    from chipstack.geometry import arrangements_from_stack
    from chipstack.packing.checkpoint import stack_from_arrays

    with np.load(run / "packing" / "stack.npz", allow_pickle=False) as arrays:
        stack = stack_from_arrays(dict(arrays))
    arrangement = arrangements_from_stack(stack)[-1]
    return np.array([s.volume_mm3 for s in arrangement.shapes])[arrangement.shape_index]


def _pipeline_run(spec: Path, stage: str, seed: int, out: Path, overwrite: bool):
    """``pipeline run`` in a child: (exit code, seconds, peak MB of the run, stderr)."""
    command = [sys.executable, "-m", "chipstack.pipeline", "run", str(spec), "--to", stage]
    command += ["--seed", str(seed), "--out", str(out), "--quiet"]
    command += ["--overwrite"] if overwrite else []
    done = subprocess.run([sys.executable, "-c", RUNNER, *command], capture_output=True, text=True)
    code, seconds, peak_mb = done.stdout.split()
    return int(code), float(seconds), float(peak_mb), done.stderr.strip()


def _modulus(run: Path, stem: str) -> dict:
    """The pressed box's effective modulus (MPa): platen force over its area and strain."""
    solve = json.loads((run / "manifest.json").read_text())["solve"]
    checks = json.loads((run / "mesh" / f"{stem}_checks.json").read_text())
    (x0, y0, z0), (x1, y1, z1) = checks["bounds_mm"]
    strain = solve["press_mm"] / (z1 - z0)
    return dict(
        force_n=solve["force_n"],
        modulus_mpa=solve["force_n"] / ((x1 - x0) * (y1 - y0)) / strain,
        solver_s=solve.get("solver_wall_time_s"),
        elements=checks["elements"],
    )


def press_case(scenario: str, seed: int, folder: Path, result: dict) -> None:
    """The solve stage's volume model on the case's mesh (reused) and on the voxel volume
    of the same stack; the figures go into ``result``."""
    from chipstack.pipeline.scenario_files import dumps_toml, load_scenario, with_overrides

    out = folder / f"{scenario}-{seed}"
    code, seconds, peak_mb, err = _pipeline_run(
        folder / f"{scenario}.toml", "solve", seed, out, False
    )
    result["press"] = dict(seconds=seconds, peak_mb=peak_mb)
    if code != 0:
        result["press"]["error"] = err.splitlines()[-1] if err else str(code)
        return
    result["press"].update(_modulus(out, "stack_conformal"))
    spec = folder / f"{scenario}-voxel.toml"
    spec.write_text(dumps_toml(with_overrides(load_scenario(scenario), VOXEL)))
    voxel_out = folder / f"{scenario}-{seed}-voxel"
    code, seconds, peak_mb, err = _pipeline_run(spec, "solve", seed, voxel_out, True)
    result["voxel_press"] = dict(seconds=seconds, peak_mb=peak_mb)
    if code != 0:
        result["voxel_press"]["error"] = err.splitlines()[-1] if err else str(code)
        return
    result["voxel_press"].update(_modulus(voxel_out, "stack_voxel"))
    conformal, voxel = result["press"]["modulus_mpa"], result["voxel_press"]["modulus_mpa"]
    result["modulus_difference"] = abs(conformal - voxel) / voxel


def run_case(scenario: str, seed: int, folder: Path) -> dict:
    """``pipeline run`` of one case in a child, then the audit of what it wrote."""
    from chipstack.pipeline.scenario_files import dumps_toml, load_scenario, with_overrides

    spec = folder / f"{scenario}.toml"
    spec.write_text(dumps_toml(with_overrides(load_scenario(scenario), MESH)))
    out = folder / f"{scenario}-{seed}"
    load = os.getloadavg()[0]  # a shared machine: the time says how busy it was
    code, seconds, peak_mb, err = _pipeline_run(spec, "mesh", seed, out, True)
    result = dict(
        scenario=scenario,
        seed=seed,
        seconds=seconds,
        peak_mb=peak_mb,
        load=round(load, 1),
    )
    if code != 0:
        result["error"] = err.splitlines()[-1] if err else str(code)
        return result
    manifest = json.loads((out / "manifest.json").read_text())
    info = manifest["stages"]["mesh"]["summary"]["conformal"]["info"]
    result["mesh_s"] = info["mesh_time_s"]  # contact resolution and mesh
    result["slivers"] = info.get("slivers")
    msh = out / "mesh" / "stack_conformal.msh"
    result["sha256"] = hashlib.sha256(msh.read_bytes()).hexdigest()
    checks = json.loads((out / "mesh" / "stack_conformal_checks.json").read_text())
    result["project_check_valid"] = checks["valid"]
    result.update(
        audit_msh(msh, _exact_volumes(out), out / "mesh" / "stack_conformal_interfaces.csv")
    )
    return result


def describe(r: dict) -> str:
    head = f"{r['scenario']} seed {r['seed']}:"
    if "error" in r:
        return f"{head} FAILED after {r['seconds']:.1f} s, peak {r['peak_mb']:.0f} MB: {r['error']}"
    return (
        f"{head} {'valid' if r['valid'] else 'NOT VALID'} (the project's check: "
        f"{'valid' if r['project_check_valid'] else 'not valid'}); {r['elements']:,} tetrahedra "
        f"({r['pore_elements']:,} pore space); SICN worst {r['sicn_min']:.3f}, 1st percentile "
        f"{r['sicn_p1']:.3f}, {r['below_min']} under {MIN_SICN}; chips {r['chips_present']} of "
        f"{r['chips']}, {r['chips_in_pieces']} in pieces; chip volume error max "
        f"{100 * r['volume_error_max']:.2f} %; {r['interfaces']} interfaces"
        f"{'' if r['interfaces_match_table'] else ' (NOT as in the table)'}; "
        f"{r['seconds']:.1f} s (target 180 s: {r['seconds'] / 180:.2f}), peak "
        f"{r['peak_mb']:.0f} MB (target 4096 MB: {r['peak_mb'] / 4096:.2f})"
    )


def describe_press(r: dict) -> str:
    head = f"{r['scenario']} seed {r['seed']} pressed:"
    press, voxel = r["press"], r.get("voxel_press", {})
    for name, part in (("the conformal model", press), ("the voxel volume", voxel)):
        if "error" in part:
            return f"{head} {name} FAILED after {part['seconds']:.1f} s: {part['error']}"
    return (
        f"{head} {press['elements']:,} tetrahedra, {press['force_n']:,.0f} N, effective "
        f"modulus {press['modulus_mpa']:,.0f} MPa against {voxel['modulus_mpa']:,.0f} MPa on "
        f"the {voxel['elements']:,} hexahedra of the 1 mm voxel volume "
        f"({100 * r['modulus_difference']:.2f} % apart, target 5 %); CalculiX "
        f"{press['solver_s']:.0f} s, the solve run {press['seconds']:.0f} s, peak "
        f"{press['peak_mb']:.0f} MB (voxel: {voxel['solver_s']:.0f} s, peak "
        f"{voxel['peak_mb']:.0f} MB)"
    )


def record_press(r: dict) -> None:
    from chipstack.pipeline.measured import record

    command = (
        f"python benchmarks/bench_whole_stack.py --case {r['scenario']} --seeds {r['seed']} --solve"
    )
    name = f"whole {r['scenario']} stack pressed in CalculiX, seed {r['seed']}: "
    if "modulus_difference" not in r:  # a failure: what ran, and how long, with why
        part = r.get("voxel_press", r["press"])
        record(
            "meshing",
            name + "solve run time",
            round(part["seconds"], 1),
            "s",
            command=command,
            note="FAILED: " + describe_press(r)[:300],
        )
        return
    record(
        "meshing",
        name + "modulus against the voxel volume",
        round(100 * r["modulus_difference"], 2),
        "% apart",
        target="<= 5",
        command=command,
        note=describe_press(r),
        headline=r["scenario"] == "paper-squares",
    )


def record_figures(results: list[dict]) -> None:
    from chipstack.pipeline.measured import record

    for r in results:
        command = (
            f"python benchmarks/bench_whole_stack.py --case {r['scenario']} --seeds {r['seed']}"
        )
        reference = r["scenario"] == "paper-squares"
        name = f"whole {r['scenario']} stack with the pore space, seed {r['seed']}: "
        if "error" in r:
            note = f"FAILED: {r['error'][:200]}"
        else:
            note = (
                f"{'valid' if r['valid'] else 'NOT VALID'} by the audit of the written .msh; "
                f"{r['elements']:,} tetrahedra ({r['pore_elements']:,} pore space); SICN worst "
                f"{r['sicn_min']:.3f}, 1st percentile {r['sicn_p1']:.3f}; chips "
                f"{r['chips_present']} of {r['chips']}, {r['chips_in_pieces']} in pieces; chip "
                f"volume error max {100 * r['volume_error_max']:.2f} %; {r['interfaces']} "
                f"interfaces; peak {r['peak_mb']:.0f} MB; load average {r.get('load')} at "
                "the start (2 cores)" + ("; the same file twice" if r.get("reproducible") else "")
            )
        record(
            "meshing",
            name + "time",
            round(r["seconds"], 1),
            "s",
            target="<= 180" if reference else "",
            command=command,
            note=note,
            headline=reference and r["seed"] == 0,
        )
        record(
            "meshing",
            name + "peak memory",
            round(r["peak_mb"] / 1024, 2),
            "GB",
            target="<= 4",
            command=command,
            note=f"pipeline run --to mesh, the whole process; {len(results)} cases in the run",
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--case", choices=sorted(CASES), action="append")
    parser.add_argument("--seeds", type=int, nargs="+", default=None)
    parser.add_argument("--no-repeat", action="store_true", help="skip the repeated first run")
    parser.add_argument("--no-record", action="store_true")
    parser.add_argument(
        "--solve", action="store_true", help="also press each valid case and its voxel volume"
    )
    args = parser.parse_args()
    cases = [(c, s) for c in args.case or CASES for s in (args.seeds or CASES[c])]
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        for k, (scenario, seed) in enumerate(cases):
            r = run_case(scenario, seed, Path(tmp))
            if k == 0 and not args.no_repeat and "error" not in r:
                again = run_case(scenario, seed, Path(tmp))
                r["reproducible"] = again.get("sha256") == r["sha256"]
                print(f"{scenario} seed {seed} again: same .msh: {r['reproducible']}", flush=True)
            print(describe(r), flush=True)
            if args.solve and r.get("valid"):
                press_case(scenario, seed, Path(tmp), r)
                print(describe_press(r), flush=True)
            results.append(r)
    ok = [r for r in results if r.get("valid")]
    print(f"{len(ok)} of {len(results)} cases valid by the audit of the written .msh")
    if not args.no_record:
        record_figures(results)
        for r in results:
            if "press" in r:
                record_press(r)


if __name__ == "__main__":
    main()
