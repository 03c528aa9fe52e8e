"""The paper's fibre mat (section 5, Fig. 16): every definition the paper might have used,
for each physics preset, over repeats.

1,000 fibres 1 x 1 x 25 mm poured in five batches of 200 onto a 100 mm square target from
100-200 mm (``fibre-mat``). The paper reports a volume fraction of 6.68 % and 2,169 ± 24
fibre-fibre contacts without saying how either was measured. Each run records:

* volume fraction, five ways: all fibres over (target area x top height); fibres whose
  centre lies over the target, over the same; those over (target area x mean height of the
  top surface over the target, 1 mm pixels); the solid fraction under the top surface
  over the target (sum of the solid lengths of the vertical rays / sum of their top
  heights); and all fibres over their bounding box (x-y extent of every fibre x top);
* the top height, the mean top-surface height, and the fibres over the target;
* contacts, three ways: touching fibre pairs (surfaces within 0.05 mm, exact geometry),
  contact points (PyBullet closest points within 0.05 mm, several per pair), and fibre
  contacts counted once per fibre (2 x pairs);
* whether every batch settled, and the wall time.

Each run is cached in ``benchmarks/results/mat/<preset>-<seed>.json`` (delete to redo), so
the study resumes; ``--report`` prints the table (mean ± sd per definition and preset).

    .venv/bin/python benchmarks/bench_mat.py --preset default paper --seeds 0 1 2
    .venv/bin/python benchmarks/bench_mat.py --report
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import time
from pathlib import Path

import numpy as np

from chipstack.core.arrangement import arrangements_from_stack
from chipstack.geometry.contacts import find_contacts
from chipstack.geometry.rays import ray_maps
from chipstack.packing import deposit
from chipstack.pipeline.scenario_files import load_scenario

RESULTS = Path(__file__).parent / "results" / "mat"
PAPER_FRACTION, PAPER_CONTACTS = 6.68, (2169, 24)


def run(preset: str, seed: int) -> dict:
    scenario = load_scenario("fibre-mat")
    physics = dataclasses.replace(scenario.physics, preset=preset)
    scenario = dataclasses.replace(scenario, seed=seed, physics=physics)
    start = time.perf_counter()
    stack = deposit(scenario)
    seconds = time.perf_counter() - start
    arrangement = arrangements_from_stack(stack)[-1]
    pairs = find_contacts(arrangement, 0.05, 5.0)
    between = pairs.chip_b >= 0
    record = stack.batches[-1].contacts
    points = int(((record.chip_a >= 0) & (record.chip_b >= 0)).sum())
    maps = ray_maps(arrangement, pixel_mm=1.0)
    on_target = maps.grid.on_target
    top_surface = maps.top_mm[on_target]
    solid = maps.solid_mm[on_target]
    bounds = arrangement.bounds  # every fibre's box, from its vertices
    top = float(bounds[:, 1, 2].max())
    inside = stack.inside_target()
    area = scenario.deposition.target_size_mm**2
    volumes = np.array([stack.shapes[k].volume_mm3 for k in stack.shape_index])
    mean_top = float(top_surface.mean())
    box_area = float(np.prod(bounds[:, 1, :2].max(axis=0) - bounds[:, 0, :2].min(axis=0)))
    return {
        "preset": preset,
        "seed": seed,
        "seconds": seconds,
        "settled": all(b.settled for b in stack.batches),
        "warnings": list(stack.warnings),
        "fibres_over_target": int(inside.sum()),
        "top_mm": top,
        "mean_top_surface_mm": mean_top,
        "fraction_all_top_pct": 100 * volumes.sum() / (area * top),
        "fraction_over_target_top_pct": 100 * volumes[inside].sum() / (area * top),
        "fraction_over_target_mean_top_pct": 100 * volumes[inside].sum() / (area * mean_top),
        "fraction_bounding_box_pct": 100 * volumes.sum() / (box_area * top),
        "bounding_box_area_mm2": box_area,
        "fraction_under_surface_pct": 100 * float(solid.sum() / max(top_surface.sum(), 1e-9)),
        "contact_pairs": int(between.sum()),
        "contact_points": points,
        "contacts_per_fibre_sum": int(2 * between.sum()),
        "floor_contacts": int((~between).sum()),
    }


ROWS = (
    ("fraction_all_top_pct", "volume fraction, all fibres / (area x top) (%)"),
    ("fraction_over_target_top_pct", "volume fraction, over target / (area x top) (%)"),
    ("fraction_over_target_mean_top_pct", "volume fraction, over target / (area x mean top) (%)"),
    ("fraction_under_surface_pct", "solid fraction under the top surface (%)"),
    ("fraction_bounding_box_pct", "volume fraction, all fibres / their bounding box (%)"),
    ("bounding_box_area_mm2", "bounding box of all fibres, area in x-y (mm2)"),
    ("top_mm", "top height (mm)"),
    ("mean_top_surface_mm", "mean top-surface height over the target (mm)"),
    ("fibres_over_target", "fibres over the target"),
    ("contact_pairs", "touching fibre pairs"),
    ("contact_points", "contact points (PyBullet)"),
    ("contacts_per_fibre_sum", "contacts counted per fibre (2 x pairs)"),
    ("seconds", "wall time per mat (s)"),
)


def report() -> None:
    runs = [json.loads(p.read_text()) for p in sorted(RESULTS.glob("*.json"))]
    presets = sorted({r["preset"] for r in runs})
    by = {p: [r for r in runs if r["preset"] == p] for p in presets}
    head = " | ".join(f"{p} (n = {len(by[p])})" for p in presets)
    print(f"| quantity | paper | {head} |")
    print("|---|---|" + "---|" * len(presets))
    for key, label in ROWS:
        paper = ""
        if key.startswith("fraction_all"):
            paper = f"{PAPER_FRACTION}"
        elif key in ("contact_pairs", "contact_points", "contacts_per_fibre_sum"):
            paper = f"{PAPER_CONTACTS[0]} ± {PAPER_CONTACTS[1]}"
        cells = []
        for p in presets:
            values = [float(r[key]) for r in by[p] if key in r]
            if not values:
                cells.append("not measured")
                continue
            sd = statistics.stdev(values) if len(values) > 1 else float("nan")
            cells.append(f"{statistics.mean(values):.4g} ± {sd:.2g}")
        print(f"| {label} | {paper} | " + " | ".join(cells) + " |")
    for p in presets:
        unsettled = sum(not r["settled"] for r in by[p])
        print(f"{p}: {unsettled} of {len(by[p])} mats had a batch that did not settle")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", nargs="+", default=["default", "paper"])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--report", action="store_true", help="print the table and stop")
    args = parser.parse_args()
    if args.report:
        report()
        return
    RESULTS.mkdir(parents=True, exist_ok=True)
    for seed in args.seeds:
        for preset in args.preset:
            path = RESULTS / f"{preset}-{seed}.json"
            if path.exists():
                continue
            row = run(preset, seed)
            path.write_text(json.dumps(row, indent=1) + "\n")
            print(
                f"{preset} seed {seed}: {row['seconds']:.0f} s, settled {row['settled']}, "
                f"top {row['top_mm']:.1f} mm, fraction {row['fraction_all_top_pct']:.2f} %, "
                f"pairs {row['contact_pairs']}, points {row['contact_points']}",
                flush=True,
            )


if __name__ == "__main__":
    main()
