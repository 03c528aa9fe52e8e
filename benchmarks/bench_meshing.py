"""Meshing: the voxel mesh and the conformal mesh of the 270-chip reference stack.

For every seed asked for, deposits the reference stack, then in a fresh process (so that
peak memory is its own) times

* ``voxel_mesh`` at 0.5 mm (target <= 10 s);
* the conformal route: contact resolution (``meshing.resolution``) and ``conformal_mesh``
  at 1.5 mm, chips only and with the pore space (``--pore-space``), each checked by
  ``meshing.checks.check_mesh`` (every chip present, volumes within 2 %, SICN >= 0.1,
  every snapped surface contact sharing faces). Targets: resolution plus mesh <= 60 s and
  <= 4 GB.

It prints one line per seed and kind, then the count of valid meshes and the median and
worst times beside the targets (ratios in the same run). Contact classes before and after
the resolution are compared pair by pair (the geometry stage's classification).

    .venv/bin/python benchmarks/bench_meshing.py                       # seed 0
    .venv/bin/python benchmarks/bench_meshing.py --seeds 0 1 2 3 4 5 6 7 8 9 --no-voxel
    .venv/bin/python benchmarks/bench_meshing.py --no-voxel --no-conformal --image
    .venv/bin/python benchmarks/bench_meshing.py --scenario paper-rectangles --no-voxel
    .venv/bin/python benchmarks/bench_meshing.py --no-voxel --pore-space box --crop 25

The image route (``--image``, CGAL's Mesh_3 on the labelled voxel image, default voxel an
eighth of the chip's thickness, then its sliver removal) is checked with volumes within
4 %, SICN >= 0.1 and every surface contact sharing faces (``--crop`` cuts it too); its
peak memory includes the Mesh_3 process.

The times are recorded as data (``pipeline.measured.record``, area ``meshing``;
``--no-record`` for a trial) and shown in docs/measured.md after ``make docs``.
"""

from __future__ import annotations

import argparse
import json
import pickle
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

CHILD = """
import json, pickle, resource, sys, time
import numpy as np
arrangement = pickle.load(open(sys.argv[1], "rb"))
kind, pore = sys.argv[2], sys.argv[3]
result = {"kind": kind, "pore_space": pore}
start = time.perf_counter()
if kind == "voxel":
    from chipstack.meshing import voxel_mesh
    mesh = voxel_mesh(arrangement, 0.5)
    result.update(elements=mesh.n_elements, seconds=time.perf_counter() - start)
elif kind == "image":
    from chipstack.geometry.contacts import KINDS, find_contacts
    from chipstack.meshing import MeshingError, check_mesh
    from chipstack.meshing.image import image_mesh
    voxel, optimise = float(sys.argv[4]), sys.argv[5] == "1"
    half = float(sys.argv[6])
    region = (-half, half, -half, half) if half > 0 else None
    try:
        mesh = image_mesh(
            arrangement, voxel, 1.5, pore, optimise=optimise, seed=0, region_mm=region
        )
        result["mesh_s"] = time.perf_counter() - start
        table = find_contacts(arrangement)
        # With a crop, the surface contacts whose centres lie inside it (1 mm in).
        surface = [
            (int(a), int(b))
            for a, b, k, c in zip(table.chip_a, table.chip_b, table.kind, table.centre_mm)
            if b >= 0 and KINDS[k] == "surface"
            and (region is None or (abs(c[0]) < half - 1 and abs(c[1]) < half - 1))
        ]
        # The route removes Mesh_3's slivers and holds every element to SICN 0.1.
        report = check_mesh(
            mesh, arrangement, np.array(surface).reshape(-1, 2), 0.1, 0.04,
            region_mm=mesh.info.get("region_mm"),
        )
        solid = mesh.chip >= 0
        exact = np.array([s.volume_mm3 for s in arrangement.shapes])[arrangement.shape_index]
        error = np.abs(mesh.chip_volumes() - exact) / exact
        if region is not None:  # a crop cuts chips: the check's maximum (cut parts) only
            error = np.array([np.nan])
        result.update(
            elements=mesh.n_elements, nodes=len(mesh.points), voxel_mm=mesh.info["voxel_mm"],
            clusters=mesh.info["clusters"], quality_min=report["quality_min"],
            quality_p1=report["quality_p1"], inverted=int((mesh.element_volumes() <= 0).sum()),
            volume_error_max=report["chip_volume_error_max"],
            volume_error_median=float(np.median(error)),
            total_volume_error=report["total_volume_error"], valid=report["valid"],
            shared_missing=report["interfaces"].get("missing"), surface_pairs=len(surface),
            chips_meshed=int(len(np.unique(mesh.chip[solid]))),
            below_0_1=int((mesh.quality < 0.1).sum()), slivers=mesh.info.get("slivers"),
        )
    except MeshingError as exc:
        result["error"] = str(exc)
    result["seconds"] = time.perf_counter() - start
else:
    from chipstack.geometry.contacts import KINDS, find_contacts
    from chipstack.meshing.resolution import UnresolvedError, resolve_contacts
    from chipstack.meshing import MeshingError, check_mesh, conformal_mesh
    before = find_contacts(arrangement)
    # As the conformal kind does: line contacts touching for a mesh of the chips alone,
    # cleared by the gap when the resolution or the mesh fails (or with the pore space).
    # With the pore space the clearance is the kind's default mesh.pore_gap_mm (a tenth of
    # the thinnest chip dimension); a crop resolves
    # only the chips that can reach into it, as the conformal kind does.
    half = float(sys.argv[6])
    region = (-half, half, -half, half) if half > 0 else None
    from chipstack.meshing.kinds import pore_gap_mm
    from chipstack.meshing.sections import MeshSpec
    conformal = MeshSpec(kind="conformal")
    gap = conformal.gap_mm if pore == "none" else pore_gap_mm(conformal, arrangement)
    def attempt(touching):
        from chipstack.meshing.resolution import resolve_chips
        from chipstack.meshing.conformal import chips_near
        if region is None:
            resolution = resolve_contacts(
                arrangement, gap, contacts=before, touching_lines=touching
            )
        else:
            resolution = resolve_chips(
                arrangement, chips_near(arrangement, region), gap_mm=gap,
                touching_lines=touching,
            )
        resolve_s = time.perf_counter() - start
        mesh = conformal_mesh(resolution.arrangement, 1.5, pore_space=pore, region_mm=region)
        return resolution, resolve_s, mesh
    resolution, mesh = None, None
    try:
        resolution, resolve_s, mesh = attempt(pore == "none")
    except (UnresolvedError, MeshingError) as exc:
        if pore == "none":
            result["touching_lines_failed"] = str(exc)
            try:
                resolution, resolve_s, mesh = attempt(False)
            except (UnresolvedError, MeshingError) as exc2:
                result["error"] = str(exc2)
        else:
            result["error"] = str(exc)
    if mesh is None:
        result["seconds"] = time.perf_counter() - start
    else:
        result["resolution"] = resolution.summary()
        result["resolve_s"] = resolve_s
        after = find_contacts(resolution.arrangement)
        def classes(table):
            rows = zip(table.chip_a, table.chip_b, table.kind)
            return {(int(a), int(b)): int(k) for a, b, k in rows}
        c0, c1 = classes(before), classes(after)
        changed = {}
        for pair in set(c0) | set(c1):
            was = KINDS[c0[pair]] if pair in c0 else "none"
            now = KINDS[c1[pair]] if pair in c1 else "none"
            if was != now:
                changed[f"{was}->{now}"] = changed.get(f"{was}->{now}", 0) + 1
        result["class_changes"] = changed
        result["pairs_before"] = len(c0)
        cleared = {frozenset(p) for p in resolution.surface_cleared}
        # In a crop, as the mesh stage checks: the patches inside it, 1 mm clear of its sides.
        def inside(centre):
            if region is None:
                return True
            x0, x1, y0, y1 = region
            return x0 + 1 < centre[0] < x1 - 1 and y0 + 1 < centre[1] < y1 - 1
        surface = [
            (int(a), int(b))
            for a, b, k, c in zip(before.chip_a, before.chip_b, before.kind, before.centre_mm)
            if b >= 0 and KINDS[k] == "surface" and frozenset((int(a), int(b))) not in cleared
            and inside(c)
        ]
        report = check_mesh(
            mesh, resolution.arrangement, np.array(surface).reshape(-1, 2), 0.1,
            region_mm=mesh.info.get("region_mm"),
        )
        solid = mesh.chip >= 0
        result.update(
            elements=mesh.n_elements, nodes=len(mesh.points),
            pore_elements=int((~solid).sum()),
            quality_min=report["quality_min"], quality_p1=report["quality_p1"],
            below_0_1=int((mesh.quality < 0.1).sum()), below_0_2=int((mesh.quality < 0.2).sum()),
            volume_error_max=report["chip_volume_error_max"],
            chips_meshed=int(len(np.unique(mesh.chip[solid]))), chips=int(mesh.n_chips),
            valid=report["valid"], shared_missing=report["interfaces"].get("missing"),
            surface_pairs=len(surface), region_mm=mesh.info.get("region_mm"),
        )
        result["seconds"] = time.perf_counter() - start
# Mesh_3 runs in a process of its own: the peak is the larger of this one and its children.
who = (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN)
peak = max(resource.getrusage(w).ru_maxrss for w in who)
result["peak_mb"] = peak / 1024
print(json.dumps(result))
"""


def run_child(path: Path, kind: str, pore: str, *extra: str) -> dict:
    start = time.perf_counter()
    out = subprocess.run(
        [sys.executable, "-c", CHILD, str(path), kind, pore, *extra],
        capture_output=True,
        text=True,
    )
    if out.returncode != 0:
        return {
            "kind": kind,
            "pore_space": pore,
            "error": "crashed: " + out.stderr[-500:],
            "seconds": time.perf_counter() - start,
            "peak_mb": float("nan"),
        }
    return json.loads(out.stdout.strip().splitlines()[-1])


def describe(seed: int, r: dict) -> str:
    head = f"seed {seed} {r['kind']:9s} pore={r['pore_space']:4s}"
    if "error" in r:
        return f"{head} FAILED after {r['seconds']:.1f} s, peak {r['peak_mb']:.0f} MB: {r['error']}"
    if r["kind"] == "voxel":
        return (
            f"{head} {r['elements']:,} elements, {r['seconds']:.1f} s, peak {r['peak_mb']:.0f} MB"
        )
    if r["kind"] == "image":
        return (
            f"{head} {'valid' if r['valid'] else 'NOT VALID'} at {r['voxel_mm']:g} mm voxels: "
            f"{r['chips_meshed']} chips in {r['clusters']} clusters, {r['elements']:,} "
            f"tetrahedra, {r['inverted']} inverted, SICN min {r['quality_min']:.4f} (1st "
            f"percentile {r['quality_p1']:.3f}; {r.get('below_0_1', 0)} under 0.1"
            + (
                f", {r['slivers']['below_0_1_before']:,} before the sliver removal, worst "
                f"{r['slivers']['worst_before']:.4f}; removal {r['slivers']['seconds']:.1f} s"
                if r.get("slivers")
                else ""
            )
            + f"); chip volume error against the exact solid "
            f"median {100 * r['volume_error_median']:.2f} %, max "
            f"{100 * r['volume_error_max']:.2f} % (target 4 %: "
            f"{r['volume_error_max'] / 0.04:.2f}), total {100 * r['total_volume_error']:.2f} %; "
            f"{r['surface_pairs']} surface contacts, missing shared faces: "
            f"{len(r['shared_missing'] or [])}; mesh {r['mesh_s']:.1f} s, with checks "
            f"{r['seconds']:.1f} s, peak {r['peak_mb']:.0f} MB (target 4096 MB: "
            f"{r['peak_mb'] / 4096:.2f})"
        )
    res = r["resolution"]
    if r.get("region_mm"):
        head += " crop x {:g} to {:g}, y {:g} to {:g} mm".format(*r["region_mm"])
    return (
        f"{head} {'valid' if r['valid'] else 'NOT VALID'}: {r['elements']:,} tetrahedra "
        f"({r['pore_elements']:,} of the pore space), {r['chips_meshed']} of {r['chips']} chips, "
        f"SICN min {r['quality_min']:.3f} (1st percentile {r['quality_p1']:.3f}; "
        f"{r['below_0_1']} under 0.1, {r['below_0_2']} under 0.2), "
        f"chip volume error max {100 * r['volume_error_max']:.2f} %, "
        f"{r['surface_pairs']} surface contacts share faces (missing: {r['shared_missing'] or 0}); "
        f"resolution {r['resolve_s']:.1f} s (moves <= {res['max_translation_mm']:.3f} mm, "
        f"{res['max_rotation_deg']:.2f} deg; snapped {res['snapped_chip_chip']} + "
        f"{res['snapped_conveyor']} conveyor; {res['surface_contacts_cleared']} surface "
        f"contacts cleared; class changes {r['class_changes']} of {r['pairs_before']} pairs) "
        f"+ mesh = {r['seconds']:.1f} s, peak {r['peak_mb']:.0f} MB"
        + (
            f" (line contacts kept touching failed: {r['touching_lines_failed']}; cleared "
            "by the gap instead)"
            if r.get("touching_lines_failed")
            else ""
        )
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--pore-space", nargs="+", default=["none", "box"])
    parser.add_argument("--no-voxel", action="store_true")
    parser.add_argument("--no-conformal", action="store_true")
    parser.add_argument(
        "--image", action="store_true", help="also the image route (CGAL Mesh_3; pygalmesh)"
    )
    parser.add_argument("--image-voxel", type=float, default=0.0, help="mm (0: the default)")
    parser.add_argument("--image-optimise", action="store_true")
    parser.add_argument(
        "--crop",
        type=float,
        default=0.0,
        help="conformal route: mesh only the middle 2 x CROP mm square (0: the whole stack)",
    )
    parser.add_argument(
        "--scenario", default=None, help="a built-in scenario or TOML file (default: the reference)"
    )
    parser.add_argument("--no-record", action="store_true", help="do not record the figures")
    args = parser.parse_args()
    from chipstack.geometry import arrangements_from_stack
    from chipstack.packing import deposit, scenario_from_dict
    from chipstack.pipeline.scenario_files import load_scenario

    # The reference stack as the benchmarks have always built it (the packing of the
    # built-in paper-squares file is the same; its name and mesh settings are not).
    scenario = load_scenario(args.scenario) if args.scenario else scenario_from_dict({})

    conformal: list[dict] = []
    measured: list[tuple[int, dict]] = []
    with tempfile.TemporaryDirectory() as folder:
        for seed in args.seeds:
            stack = deposit(scenario.with_seed(seed))
            path = Path(folder) / f"stack{seed}.pkl"
            path.write_bytes(pickle.dumps(arrangements_from_stack(stack)[-1]))
            kinds = [] if args.no_voxel else [("voxel", "none")]
            if not args.no_conformal:
                kinds += [("conformal", pore) for pore in args.pore_space]
            if args.image:
                kinds += [("image", pore) for pore in args.pore_space]
            extra = (repr(args.image_voxel), str(int(args.image_optimise)), repr(args.crop))
            for kind, pore in kinds:
                r = run_child(path, kind, pore, *extra)
                print(describe(seed, r), flush=True)
                measured.append((seed, r))
                if kind == "conformal":
                    conformal.append(r)
    for pore in args.pore_space:
        runs = [r for r in conformal if r["pore_space"] == pore]
        if not runs:
            continue
        valid = [r for r in runs if r.get("valid")]
        seconds = [r["seconds"] for r in runs]
        peak = max(r["peak_mb"] for r in runs)
        print(
            f"conformal, pore_space={pore}: {len(valid)} of {len(runs)} valid; resolution + mesh "
            f"median {statistics.median(seconds):.1f} s, worst {max(seconds):.1f} s "
            f"(target 60 s: worst/target {max(seconds) / 60:.2f}); peak {peak:.0f} MB "
            f"(target 4096 MB: {peak / 4096:.2f})"
        )
    print(
        f"(this process: peak {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB)"
    )
    if not args.no_record:
        record_figures(args, measured)


def record_figures(args, measured: list[tuple[int, dict]]) -> None:
    """The voxel mesh's time, the conformal route's worst time over the seeds and each
    valid image mesh's time, as data (pipeline.measured)."""
    from chipstack.pipeline.measured import record

    command = "python " + " ".join(["benchmarks/bench_meshing.py", *sys.argv[1:]])
    stack = f"the {args.scenario} stack" if args.scenario else "the reference stack"
    seeds = sorted({seed for seed, _ in measured})
    for seed, r in measured:
        if r["kind"] == "voxel" and "error" not in r and seed == seeds[0]:
            record(
                "meshing",
                f"voxel mesh of {stack} at 0.5 mm",
                round(r["seconds"], 2),
                "s",
                target="<= 10",
                command=command,
                note=f"seed {seed}, {r['elements']:,} elements, peak {r['peak_mb']:.0f} MB",
            )
        if r["kind"] != "image" or "error" in r:
            continue
        name = f"image mesh of {stack}" + (f"'s middle {2 * args.crop:g} mm" if args.crop else "")
        if r["valid"]:
            record(
                "meshing",
                f"{name} at {r['voxel_mm']:g} mm voxels, pore space {r['pore_space']}",
                round(r["mesh_s"], 1),
                "s",
                command=command,
                note=f"seed {seed}, {r['elements']:,} tetrahedra, largest chip volume error "
                f"{100 * r['volume_error_max']:.1f} %",
            )
        slivers = r.get("slivers")
        record(
            "meshing",
            f"{name}, pore space {r['pore_space']}: worst SICN",
            round(r["quality_min"], 4),
            "",
            target=">= 0.1",
            command=command,
            note=f"seed {seed}, {r['elements']:,} tetrahedra, {r['below_0_1']} under 0.1"
            + (
                f" ({slivers['below_0_1_before']:,} before the sliver removal, worst "
                f"{slivers['worst_before']:.4f}; removal {slivers['seconds']:.1f} s)"
                if slivers
                else ""
            ),
            headline=True,
        )
    # The whole stack with its pore space per seed is recorded by bench_whole_stack.py
    # (the user's command, the written file audited); here only the worst seed's time.
    for pore in args.pore_space:
        runs = [r for _, r in measured if r["kind"] == "conformal" and r["pore_space"] == pore]
        if not runs:
            continue
        valid = sum(1 for r in runs if r.get("valid"))
        seconds = [r["seconds"] for r in runs]
        what = "chips only" if pore == "none" else "with the pore space"
        crop = f", middle {2 * args.crop:g} x {2 * args.crop:g} mm" if args.crop else ""
        record(
            "meshing",
            f"conformal mesh of {stack} (resolution + mesh, {what}{crop}), worst seed",
            round(max(seconds), 1),
            "s",
            target="<= 60" if pore == "none" else "<= 180",
            command=command,
            note=f"{valid} of {len(runs)} seeds valid, {min(seconds):.1f} to {max(seconds):.1f} s",
            headline=pore == "none" and not args.crop and not args.scenario,
        )


if __name__ == "__main__":
    main()
