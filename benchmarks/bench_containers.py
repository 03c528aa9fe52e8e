"""Container fills (the paper's section 5): wall time, volume fraction and contacts.

For each aspect ratio asked for (10: ``container-ar10``, 25: ``container-ar25``), fills
the container with each seed on one core and prints, per fill, the wall time, the rods
poured and inside, the volume fraction (centres of mass inside, as the paper counts),
phi * L / D and the mean number of rod-rod contacts per rod inside; then the mean, sd
and 95 % interval over the seeds beside the paper's model and Freeman et al.'s
measurement. Targets: AR 25 <= 5 min, AR 10 <= 2 min per fill. ``--dynamic`` fills with
every rod kept wakeable (``settling.buried_depth = 1e6``) for comparison.

    .venv/bin/python benchmarks/bench_containers.py [--ar 10 25] [--seeds 0 1 2] [--dynamic]
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import time

import numpy as np
from scipy.stats import t as student

from packing import deposit
from packing.fill import container_fill
from pipeline.scenario_files import load_scenario

# The paper's model (mean ± sd over 10 repeats) and Freeman et al. 2019 (measured, about).
PAPER = {10: (0.286, 0.0052), 25: (0.148, 0.0026)}
FREEMAN = {10: 0.37, 25: 0.18}


def fill(aspect: int, seed: int, dynamic: bool) -> dict:
    scenario = dataclasses.replace(load_scenario(f"container-ar{aspect}"), seed=seed)
    if dynamic:
        settling = dataclasses.replace(scenario.settling, buried_depth=1e6)
        scenario = dataclasses.replace(scenario, settling=settling)
    start = time.perf_counter()
    stack = deposit(scenario)
    seconds = time.perf_counter() - start
    c = scenario.container
    volumes = np.array([stack.shapes[k].volume_mm3 for k in stack.shape_index])
    result = container_fill(stack.positions, volumes, c.radius_mm, c.height_mm)
    last = stack.batches[-1]
    inside = (
        (np.hypot(last.positions[:, 0], last.positions[:, 1]) <= c.radius_mm)
        & (last.positions[:, 2] >= 0)
        & (last.positions[:, 2] <= c.height_mm)
    )
    contacts = last.contacts
    chips = (contacts.chip_a >= 0) & (contacts.chip_b >= 0)
    pairs = {
        (min(a, b), max(a, b))
        for a, b in zip(contacts.chip_a[chips], contacts.chip_b[chips], strict=True)
        if a != b
    }
    touching = np.zeros(len(inside), dtype=int)
    for a, b in pairs:
        touching[a] += 1
        touching[b] += 1
    chip = scenario.chips[0]
    return dict(
        seconds=seconds,
        poured=result["chips_poured"],
        inside=result["chips_inside"],
        phi=result["volume_fraction"],
        phi_l_over_d=result["volume_fraction"] * chip.length_mm / chip.thickness_mm,
        contacts_per_rod=float(touching[inside].mean()) if inside.any() else float("nan"),
        full=result["full"],
    )


def summary(values: list[float]) -> str:
    mean = statistics.mean(values)
    if len(values) < 2:
        return f"{mean:.4f}"
    sd = statistics.stdev(values)
    half = student.ppf(0.975, len(values) - 1) * sd / np.sqrt(len(values))
    return f"{mean:.4f} ± {sd:.4f} (95 % interval {mean - half:.4f} to {mean + half:.4f})"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ar", type=int, nargs="+", choices=(10, 25), default=[10, 25])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--dynamic", action="store_true", help="keep every rod wakeable")
    args = parser.parse_args()
    for aspect in args.ar:
        rows = []
        for seed in args.seeds:
            row = fill(aspect, seed, args.dynamic)
            rows.append(row)
            print(
                f"AR {aspect} seed {seed}: {row['seconds']:.0f} s wall, {row['poured']} rods "
                f"poured, {row['inside']} inside, full {row['full']}, volume fraction "
                f"{row['phi']:.4f}, phi L/D {row['phi_l_over_d']:.2f}, "
                f"{row['contacts_per_rod']:.2f} contacts per rod",
                flush=True,
            )
        mean, sd = PAPER[aspect]
        wall = statistics.median(r["seconds"] for r in rows)
        print(f"AR {aspect}: wall time median {wall:.0f} s")
        print(f"AR {aspect}: volume fraction {summary([r['phi'] for r in rows])}")
        print(f"  paper's model {mean:.3f} ± {sd:.4f}; Freeman et al. measured ~{FREEMAN[aspect]}")
        print(f"AR {aspect}: phi L/D {summary([r['phi_l_over_d'] for r in rows])}")
        print(f"AR {aspect}: contacts per rod {summary([r['contacts_per_rod'] for r in rows])}")


if __name__ == "__main__":
    main()
